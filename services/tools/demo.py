"""``nwr up`` and ``nwr demo``: the whole pipeline, every service its own process (or ``demo --fast``: lockstep).

The processes come from the pipeline's graph (:mod:`nwr.services.pipeline.graph`)
and run under its supervisor; ``demo`` then prints the recording's per-touch
table and checks it against the touch script (:mod:`.summary`).
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

import numpy as np

from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.launch import load_script
from nwr.services.bridge import backends
from nwr.services.bridge.main import CONFIRM_FLAG, add_arm_arguments, check_arm_flags
from nwr.services.gateway.core import sim_settings, with_sim
from nwr.services.pipeline import supervisor
from nwr.services.pipeline.graph import Layout, recorder_args
from nwr.services.planner import strategies
from nwr.services.profile import profile_for
from nwr.services.recorder.main import session_name
from nwr.services.tools.recordings.summary import add_table_arguments, print_summary

log = logging.getLogger(__name__)


def add_launch_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--script", help="touch script for the simulated skin: packaged name or .toml path")
    p.add_argument("--session", help="session name of the recording (default: the start time)")
    p.add_argument("--output", "-o", help="recording file (default: recordings/<session>.mcap)")
    p.add_argument("--no-record", action="store_true", help="do not start the recorder")
    p.add_argument("--view", nargs="?", type=int, const=8765, metavar="PORT",
                   help="also start the Foxglove view (read-only) on ws://127.0.0.1:PORT (default 8765)")
    p.add_argument("--planners", metavar="R1,R2,...",
                   help="run one planner per reflex strategy, each named after it, all at once (switch between "
                        "them with `nwr switch NAME`); the first (or --reflex) is active")
    p.add_argument("--follow-target", type=float, metavar="SECONDS",
                   help="simulated participant: press the study's target pad every SECONDS while the arm does its task")
    p.add_argument("--world", choices=WORLDS,
                   help="what holds the arm, its skin and the people touching it: the scripted world (pressure "
                        "curves, the simulated arm) or the physics world (MuJoCo: fingers pressing the pads push "
                        "back; the bridge's physics backend and the gateway's physics source, docs/worlds.md); "
                        "default: `nwr up` the profile's (bridge.backend and gateway.source both \"physics\", or "
                        "neither); `nwr demo` the physics world for a robot with collision shapes (the UR10e), else "
                        "the scripted world, which it also takes, saying why as it starts, for --closed-loop, a "
                        "script the physics world refuses, the taxel skin, or a profile that names an arm or a skin")
    p.add_argument("--skin", choices=SKINS,
                   help="the skin the pipeline runs on: the AIRSKIN pads or the robot's taxel skin "
                        "(skin-taxels.toml, docs/skins.md); default: the profile's robot.skin")
    p.add_argument("--closed-loop", action="store_true",
                   help="simulated skin: a touch's pressure falls as its pad withdraws from the finger "
                        "(gateway.sim.closed_loop; default: as scripted, open loop)")
    p.add_argument("--stop-on-exit", action="store_true",
                   help="stop every service when one exits unexpectedly (default: restart it with backoff, "
                        "the others keep running; a restarted recorder writes <stem>-restartN.mcap)")
    p.add_argument("--reflex", choices=strategies.names(),
                   help="reflex strategy; the planner is then named after it and is the active one "
                        "(default: the profile's planner)")
    add_arm_arguments(p.add_argument_group("the arm (passed to the bridge; see docs/lab.md)"))


WORLDS = ("scripted", "physics")
SKINS = ("pads", "taxels")


def world_for(args: argparse.Namespace, profile: Profile) -> str:
    """The world a launch runs in: ``--world``, else the profile's, else the command's default
    (:func:`default_world`); the profile made to say it (the bridge's
    backend and the gateway's source), the touch script checked against a physics world before anything starts.
    ConfigError for a profile that names half a physics world, or a script or flag the world cannot take."""
    if getattr(args, "skin", None):
        profile.robot.skin = args.skin
    physics = (profile.bridge.backend == "physics", profile.gateway.source == "physics")
    if physics[0] != physics[1]:
        raise ConfigError(f"bridge.backend = {profile.bridge.backend!r} and gateway.source = "
                          f"{profile.gateway.source!r}: a physics world is both (\"physics\") or neither")
    backend = getattr(args, "backend", None)
    world = getattr(args, "world", None) or ("physics" if physics[0] or backend == "physics" else None)
    if world is None:
        world, why = default_world(args, profile)
        if why:
            log.warning("the scripted world: %s", why)
        if world == "physics":  # its script already checked
            log.info("the physics world, `nwr demo`'s default (--world scripted: the scripted world)")
            profile.bridge.backend, profile.gateway.source = "physics", "physics"
            return world
    if world == "scripted":
        if backend == "physics":
            raise ConfigError("--backend physics is the physics world's: give --world physics (or leave --world)")
        if physics[0]:
            profile.bridge.backend, profile.gateway.source = "sim", "sim"
        return world
    if getattr(args, "closed_loop", False):
        raise ConfigError("--closed-loop is the scripted world's contact model; the physics world pushes back itself")
    if backend not in (None, "physics"):
        raise ConfigError(f"--backend {args.backend} with --world physics: the physics world is the bridge's "
                          "physics backend")
    check_physics_script(args, profile)
    profile.bridge.backend, profile.gateway.source = "physics", "physics"
    return world


def default_world(args: argparse.Namespace, profile: Profile) -> tuple[str, str]:
    """The world of a launch that names none (no ``--world``, a profile with neither half of a physics world) and
    why it is not the physics world where that is `nwr demo`'s default ("": nothing to say).

    ``nwr up`` keeps the profile's: the scripted world. ``nwr demo`` (``args.default_world == "physics"``) runs
    the physics world wherever it can serve: not for a backend given on the command line (the scripted world's
    arm, or a real arm: no world), a profile that names an arm or a skin other than the simulated ones, the
    scripted skin's closed loop, a robot without collision shapes (its physics world would be a skeleton of
    capsules: the FR3's), a touch script the physics world refuses (the session runs in the scripted world;
    ``--world physics`` insists, and is refused), or the taxel skin (measured live at 1 kHz, docs/skins.md: the
    physics world's taxels cost more CPU than the scripted ones, react later and split a touch whose finger
    chatters on the arm; ``--world physics`` runs them).
    """
    if getattr(args, "default_world", "scripted") != "physics" or getattr(args, "backend", None):
        return "scripted", ""
    if profile.bridge.backend != "sim" or profile.gateway.source != "sim":
        return "scripted", ""  # the profile's arm or skin (a real one: no world)
    if getattr(args, "closed_loop", False) or sim_settings(profile.gateway).closed_loop:
        return "scripted", "closed loop is the scripted world's contact model (the physics world pushes back itself)"
    if profile.robot.skin == "taxels":
        return "scripted", ("the taxel skin's default world: at 1 kHz the physics world's taxels cost more CPU, a "
                            "later onset and split touches where a finger chatters (docs/skins.md; --world physics "
                            "runs them)")
    from nwr.common.robot import load_description
    from nwr.services.bridge.backends import KIND
    from nwr.services.worlds.mjcf import PACKAGED_SHAPES
    from nwr.services.worlds.settings import PhysicsSettings

    desc = load_description(profile.robot.description or None)
    if desc.name not in PACKAGED_SHAPES and not KIND.settings(profile.bridge, "physics", PhysicsSettings).shapes:
        return "scripted", (f"the physics world has no collision shapes for the {desc.name} (--world physics: "
                            "capsules between its joints)")
    try:
        check_physics_script(args, profile)
    except ConfigError as exc:
        return "scripted", f"the physics world refuses the touch script ({exc}; --world physics insists)"
    return "physics", ""


def check_physics_script(args: argparse.Namespace, profile: Profile) -> None:
    """The touch script checked against the physics world at the arm's starting pose, before anything starts
    (ConfigError: a push no finger makes, more fingers at once than the world holds, a finger inside the arm;
    on a taxel skin, a pad the taxels do not cover)."""
    from nwr.common.robot import load_description
    from nwr.common.skin import load_skin
    from nwr.services.bridge.backends import KIND
    from nwr.services.gateway.taxels import check_covered
    from nwr.services.worlds.hosted import check_script
    from nwr.services.worlds.settings import PhysicsSettings, check_taxel_rate

    script = getattr(args, "script", None) or sim_settings(profile.gateway).script
    desc = load_description(profile.robot.description or None)
    settings = KIND.settings(profile.bridge, "physics", PhysicsSettings)
    skin = load_skin(profile, desc)
    if skin is not None:
        check_taxel_rate(settings)
    if script:
        touches = load_script(script, profile.robot.description)
        q0 = profile.bridge.initial_q or desc.home
        check_script(touches, settings, desc, np.asarray(q0, dtype=float))
        if skin is not None:
            check_covered(skin, desc.pads, touches)


def output_path(args: argparse.Namespace, profile: Profile) -> tuple[str, Path]:
    """The session's name and recording file (default: recordings/<session>.mcap)."""
    session = args.session or session_name()
    return session, Path(args.output) if args.output else Path(profile.recorder.directory) / f"{session}.mcap"


def layout_for(args: argparse.Namespace, profile: Profile, recording: tuple[str, Path] | None) -> Layout:
    """The processes ``nwr up`` / ``nwr demo`` start, from their flags; ``recording``: (session, file) or None."""
    planners = [p for p in (args.planners or "").split(",") if p]
    unknown = [p for p in planners if p not in strategies.names()]
    if unknown:
        raise ConfigError(f"--planners names {unknown}; the strategies are {list(strategies.names())}")
    if not (args.reflex or planners):
        strategies.check(profile.planner.strategy)  # here, not in the planner's process once the others run
    layout = Layout(planners=planners, active=args.reflex, planner_name=profile.planner.name, view_port=args.view)
    if recording is not None:
        session, output = recording
        layout.recorder = recorder_args(output, session, layout.active or profile.planner.strategy)
    gateway = ["--script", args.script] if args.script else []
    if world_for(args, profile) == "physics":
        gateway += ["--source", "physics"]
    if args.follow_target:
        gateway += ["--follow-target", str(args.follow_target)]
    if args.closed_loop:
        gateway.append("--closed-loop")
    layout.gateway = gateway
    if getattr(args, "skin", None):
        os.environ["NWR_SKIN"] = args.skin  # every service the launcher starts reads it (common/launch.py)
    layout.bridge = bridge_arguments(args, profile)
    return layout


def bridge_arguments(args: argparse.Namespace, profile: Profile) -> list[str]:
    """The bridge's backend flags; checked here, before any process starts, as the bridge checks them."""
    backend = args.backend or profile.bridge.backend
    check_arm_flags(backend, args.robot_ip, args.confirmed)
    flags = ["--backend", backend] if args.backend or backend == "physics" else []
    return [*flags, "--robot-ip", args.robot_ip, CONFIRM_FLAG] if backends.plugin(backend).REAL_ARM else flags


def run_up(args: argparse.Namespace) -> int:
    profile = profile_for(args)  # fails here, not in five processes
    recording = None if args.no_record else output_path(args, profile)
    layout = layout_for(args, profile, recording)
    return supervisor.launch(layout, profile, args.profile, args.log_level, until_script_end=False,
                             restart=not args.stop_on_exit)


def run_demo(args: argparse.Namespace) -> int:
    if args.fast:
        return run_demo_fast(args)
    profile = profile_for(args)
    load_script(args.script, profile.robot.description)
    recording = None if args.no_record else output_path(args, profile)
    layout = layout_for(args, profile, recording)
    code = supervisor.launch(layout, profile, args.profile, args.log_level, until_script_end=True,
                             restart=not args.stop_on_exit)
    if code or recording is None:
        return code or 1
    return print_summary(recording[1], args.script, profile, wide=args.wide, columns=args.columns)


def run_demo_fast(args: argparse.Namespace) -> int:
    """``nwr demo --fast``: the demo session in lockstep, recorded, then its per-touch table."""
    from nwr.services.tools.recordings.replay import simulate

    real_arm = bool(args.backend) and backends.plugin(args.backend).REAL_ARM
    unsupported = [flag for flag, value in (("--planners", args.planners), ("--follow-target", args.follow_target),
                                            ("--view", args.view), ("--no-record", args.no_record),
                                            ("--robot-ip", args.robot_ip), ("--backend", real_arm))
                   if value]
    if unsupported:
        raise ConfigError(f"{', '.join(unsupported)}: not with --fast (one planner, the touch script, a recording)")
    profile = profile_for(args)
    world = world_for(args, profile)
    if args.closed_loop:
        profile.gateway = with_sim(profile.gateway, closed_loop=True)
    _, output = output_path(args, profile)
    strategy = args.reflex or profile.planner.strategy
    strategies.check(strategy)  # before the recording is opened
    path, simulated, wall = simulate(profile, args.script, strategy, output)
    how = " (closed loop)" if sim_settings(profile.gateway).closed_loop else " (physics world)" \
        if world == "physics" else ""
    print(f"simulated {simulated:.1f} s of the touch script {args.script!r} against {strategy!r} in lockstep in "
          f"{wall:.2f} s{how}: {path}")
    return print_summary(path, args.script, profile, wide=args.wide, columns=args.columns)


def register(sub: argparse._SubParsersAction) -> None:
    up = sub.add_parser("up", help="start every service as its own process (Ctrl-C stops them all)",
                        description="Start recorder, bridge, planner, gain estimator and skin gateway as separate "
                                    "processes on this machine and stop them all cleanly on Ctrl-C or SIGTERM.")
    add_launch_arguments(up)
    up.set_defaults(handler=run_up)

    demo = sub.add_parser("demo", help="run a scripted ~30 s touch session and print the per-touch table",
                          description="Run the whole pipeline on a touch script, record it to "
                                      "recordings/<session>.mcap and print one row per touch.")
    add_launch_arguments(demo)
    demo.add_argument("--fast", action="store_true",
                      help="no processes: the world (skin and arm: physics or scripted), the cores and the bridge "
                           "chained in this process on simulated time (lockstep), as fast as they go; deterministic")
    add_table_arguments(demo)
    demo.set_defaults(script="demo", handler=run_demo, default_world="physics")
