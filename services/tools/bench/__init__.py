"""``nwr bench``: the reflex path measured (:mod:`.main`), its pure pieces (:mod:`.core`), its baselines (the bare
Zenoh chain :mod:`.bare`, ROS 1 :mod:`.ros1`) and its in-process figures (:mod:`.strategies`, :mod:`.tracking`)."""
