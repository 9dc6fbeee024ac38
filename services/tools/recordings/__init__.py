"""Tools on recordings: ``nwr replay`` (:mod:`.replay`), ``nwr compare`` (:mod:`.compare`), ``nwr summary``
(:mod:`.summary`), ``nwr verify`` (:mod:`.verify`), ``nwr import`` (:mod:`.rosbag_import`), and the per-touch
analysis they share (:mod:`.analysis`)."""
