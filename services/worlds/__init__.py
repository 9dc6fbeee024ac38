"""Worlds: whatever holds the arm, its skin and the people touching it.

A world is where the pipeline's two ends meet: the bridge's joint commands
go in, and out come the arm as its controller measures it and the skin as
the device samples it. Three worlds are meant to sit behind one interface:

- the **scripted** world (today's: :mod:`nwr.services.gateway` plays touch
  scripts as pressure curves and :mod:`nwr.services.bridge`'s simulated
  backend integrates the commands; nothing pushes back);
- the **physics** world (:mod:`nwr.services.worlds.physics`, MuJoCo): the
  arm with collision shapes and compliant pad cushions, driven by
  joint-level servos with the robot's torque limits; people's fingers,
  palms and forearms as bodies pulled toward where their owner wants them
  by springs; each pad's pressure change from the contact forces on its
  cushion; the force, pressure and energy every body part receives, beside
  ISO/TS 15066's limits for it;
- the **lab**, where the real arm and skin are the world.

The services cannot tell them apart: a world reaches the pipeline only
through a skin source (the gateway reads its samples like any other) and a
bridge backend (which sends it commands and reads the arm back).

The interface (:class:`nwr.services.worlds.world.World`)
-------------------------------------------------------
- ``step(q_command, dq_command=None)``: advance one fixed time step, the
  arm's servos tracking the command; single-threaded, deterministic (same
  calls in the same order: bit-identical readings), on the world's own
  clock (``time_ns`` from 0, ``timestep_ns`` per step), never the wall
  clock. A world that cannot go on raises instead of returning a state it
  does not trust.
- ``arm()``: the arm now (:class:`~nwr.services.worlds.world.ArmState`:
  joints, speeds, torques, the external torques contacts cause).
- ``skin()``: the skin samples delivered since the last call
  (:class:`~nwr.services.worlds.skin.SkinSample`: absolute pressures per
  pad at the skin's rate, with its noise and latency).

A physics world adds people (``add``, ``press``, ``retarget``, ``remove``
between steps), the contact set, and per body part the force figures.

In the pipeline the bridge's ``physics`` backend hosts the physics world
(:mod:`~nwr.services.worlds.hosted`: on the bridge's clock, a touch
script's touches as fingers) and the gateway's ``physics`` source reads its
skin (docs/worlds.md).

Modules: :mod:`~nwr.services.worlds.world` (the interface and readings),
:mod:`~nwr.services.worlds.hosted` (the world as the bridge hosts it),
:mod:`~nwr.services.worlds.physics` (the physics world and its settings),
:mod:`~nwr.services.worlds.mjcf` (its MuJoCo model, generated from the robot
description), :mod:`~nwr.services.worlds.skin` (pressure from force,
sampling), :mod:`~nwr.services.worlds.people` (body parts, ISO/TS 15066).
"""
