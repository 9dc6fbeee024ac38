"""The ``nwr`` command: run one service, launch the pipeline, run the demo, summarise a recording."""

from __future__ import annotations

import argparse
import gc
import logging
import os
import signal
import subprocess
import sys
import time
from importlib import import_module
from pathlib import Path
from typing import Any

from nwr.common.config import STRATEGIES, Profile, env_overrides, insecure, load_profile, load_script, profile_for
from nwr.common.errors import ConfigError, NwrError
from nwr.common.node import setup_logging

log = logging.getLogger("nwr")

SERVICES = {
    "gateway": "skin gateway: simulated AIRSKIN pads -> skin/pressure",
    "gain": "gain estimator: skin/pressure -> skin/pain (pain level and gain per pad)",
    "planner": "reflex planner: task, state machine and reflex -> robot/command/<name>",
    "bridge": "robot bridge: the active planner's robot/command/<name> -> the (simulated) arm -> robot/state",
    "recorder": "recorder: everything under nwr/<robot>/ -> MCAP",
    "view": "view (read-only): the live 3D scene and signals for Foxglove over WebSocket",
}
# Modules that add subcommands of their own (see build_parser).
COMMAND_MODULES: list[str] = [
    "nwr.services.recorder.commands",
    "nwr.services.figures",
    "nwr.services.view.commands",
    "nwr.services.switch",
    "nwr.services.status",
    "nwr.services.router",
    "nwr.services.replay",
    "nwr.services.compare",
    "nwr.services.verify",
    "nwr.services.study",
    "nwr.services.bench",
    "nwr.services.certs",
]
# Started in this order: the recorder first (the others start once it is
# alive, so it records every service's journal from its first batch); the
# gateway starts its clock once the others are alive. Stopped in reverse, the
# recorder last, once the others have exited (their journals' last batches).
START_ORDER = ["recorder", "bridge", "planner", "gain", "gateway"]


def _service_module(name: str) -> Any:
    return import_module(f"nwr.services.{name}.main")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nwr",
        description="Tactile withdrawal reflexes for a skin-covered robot arm: Zenoh services, launcher and tools.",
    )
    parser.add_argument("--profile", "-p", default=os.environ.get("NWR_PROFILE", "default"),
                        help="profile: a packaged name or a .toml path (default: $NWR_PROFILE or 'default')")
    parser.add_argument("--log-level", default=os.environ.get("NWR_LOG_LEVEL", "INFO"),
                        help="logging level (default: INFO)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run one service in the foreground",
                         description="Run one service as its own process until Ctrl-C or SIGTERM.")
    run_sub = run.add_subparsers(dest="service", required=True, metavar="SERVICE")
    for name, doc in SERVICES.items():
        p = run_sub.add_parser(name, help=doc, description=doc)
        _service_module(name).add_arguments(p)

    up = sub.add_parser("up", help="start every service as its own process (Ctrl-C stops them all)",
                        description="Start bridge, planner, gain estimator, recorder and skin gateway as separate "
                                    "processes on this machine and stop them all cleanly on Ctrl-C or SIGTERM.")
    _launch_arguments(up)

    demo = sub.add_parser("demo", help="run a scripted ~30 s touch session and print the per-touch table",
                          description="Run the whole pipeline on a touch script, record it to "
                                      "recordings/<session>.mcap and print one row per touch.")
    _launch_arguments(demo)
    demo.add_argument("--fast", action="store_true",
                      help="no processes: the simulated skin, the cores and the simulated arm chained in this process "
                           "on simulated time (lockstep), as fast as they go; deterministic")
    demo.set_defaults(script="demo")

    summary = sub.add_parser("summary", help="print the per-touch table of a recording")
    summary.add_argument("file", help="MCAP recording")
    summary.add_argument("--script", help="touch script to compare the recording with")

    # Tools that live beside their service register their own subcommands:
    # each module has register(subparsers), whose parsers set_defaults(handler=
    # fn(args) -> int).
    for name in COMMAND_MODULES:
        import_module(name).register(sub)
    return parser


def _launch_arguments(p: argparse.ArgumentParser) -> None:
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
                   help="simulated participant: press the study's target pad every SECONDS")
    p.add_argument("--closed-loop", action="store_true",
                   help="simulated skin: a touch's pressure falls as its pad withdraws from the finger "
                        "(gateway.sim.closed_loop; default: as scripted, open loop)")
    p.add_argument("--reflex", choices=STRATEGIES,
                   help="reflex strategy; the planner is then named after it and is the active one "
                        "(default: the profile's planner)")


def _spawn(profile: str, log_level: str, service: str, extra: list[str]) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "nwr.services.cli", "--profile", profile, "--log-level", log_level,
           "run", service, *extra]
    return subprocess.Popen(cmd)


def _stop_all(procs: dict[str, subprocess.Popen[bytes]], timeout_s: float = 10.0) -> dict[str, int]:
    """SIGTERM in reverse start order (the gateway first), the recorder once the others have exited; kill stragglers."""
    deadline = time.monotonic() + timeout_s
    codes = {}

    def stop(names: list[str]) -> None:
        for name in names:
            if procs[name].poll() is None:
                procs[name].send_signal(signal.SIGTERM)
                if name == "gateway":
                    time.sleep(0.05)
        for name in names:
            try:
                codes[name] = procs[name].wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("%s did not stop within %.0f s: killing it", name, timeout_s)
                procs[name].kill()
                codes[name] = procs[name].wait()

    stop([n for n in reversed(list(procs)) if n != "recorder"])
    if "recorder" in procs:
        stop(["recorder"])
    return {n: codes[n] for n in procs}


def launch(args: argparse.Namespace, *, until_script_end: bool, settle_s: float = 2.0) -> tuple[int, Path | None]:
    """Start every service; wait for Ctrl-C/SIGTERM (or the script's end); stop them all."""
    from nwr.common.keys import planner_service
    from nwr.services.recorder.main import session_name

    profile = profile_for(args)
    session = args.session or session_name()
    output = Path(args.output) if args.output else Path(profile.recorder.directory) / f"{session}.mcap"
    strategy = args.reflex or profile.planner.strategy
    planners = [p for p in (args.planners or "").split(",") if p]
    unknown = [p for p in planners if p not in STRATEGIES]
    if unknown:
        raise ConfigError(f"--planners names {unknown}; the strategies are {list(STRATEGIES)}")
    active = args.reflex or (planners[0] if planners else None)
    if active and planners and active not in planners:
        planners.insert(0, active)
    # (process label, service, extra arguments)
    units: list[tuple[str, str, list[str]]] = []
    for name in START_ORDER:
        if name == "recorder" and args.no_record:
            continue
        if name == "planner":
            for p in planners or ([active] if active else [None]):
                units.append((f"planner-{p}" if p else "planner", "planner", ["--name", p, "--reflex", p] if p else []))
        elif name == "bridge":
            units.append(("bridge", "bridge", ["--active", active] if active else []))
        elif name == "recorder":
            units.append(("recorder", "recorder",
                          ["--session", session, "--output", str(output), "--strategy", active or strategy]))
        elif name == "gateway":
            waits = [planner_service(p or profile.planner.name) for p in (planners or [active])]
            waits += [u[0] for u in units if u[1] not in ("planner", "view")]
            extra = ["--wait-for", ",".join(waits)]
            if args.script:
                extra += ["--script", args.script]
            if until_script_end:
                extra.append("--exit-at-end")
            if args.follow_target:
                extra += ["--follow-target", str(args.follow_target)]
            if args.closed_loop:
                extra.append("--closed-loop")
            if getattr(args, "view", None):
                units.append(("view", "view", ["--port", str(args.view)]))  # read-only: nobody waits for it
            units.append(("gateway", "gateway", extra))
        else:
            units.append((name, name, []))
    procs: dict[str, subprocess.Popen[bytes]] = {}
    stop = False

    def on_signal(signum: int, _frame: object) -> None:
        nonlocal stop
        stop = True

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        for label, service, extra in units:
            procs[label] = _spawn(args.profile, args.log_level, service, extra)
            if label == "recorder":
                _wait_for_recorder(profile)
        log.info("started %s", ", ".join(f"{n} (pid {p.pid})" for n, p in procs.items()))
        while not stop:
            dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
            if until_script_end and dead.get("gateway") == 0 and len(dead) == 1:
                time.sleep(settle_s)  # let the last reflex return and the recorder catch up
                break
            if dead:
                log.error("service(s) exited unexpectedly: %s", dead)
                _stop_all(procs)
                return 1, None
            time.sleep(0.1)
    finally:
        codes = _stop_all(procs)
        for s, handler in old.items():
            signal.signal(s, handler)
    bad = {n: c for n, c in codes.items() if c not in (0, -signal.SIGTERM, -signal.SIGINT)}
    if bad:
        log.error("service(s) stopped with errors: %s", bad)
        return 1, None
    return 0, (output if "recorder" in procs else None)


def _wait_for_recorder(profile: Profile, timeout_s: float = 30.0) -> None:
    """Until the recorder is alive (subscribed): what the others publish from their start is recorded."""
    if profile.zenoh.secure:
        return  # the launcher has no certificate of its own: the services start at once
    from nwr.common.node import Node

    with Node("launcher", profile.robot.name, profile.zenoh, token=False) as node:
        if node.wait_for(["recorder"], timeout_s):
            log.warning("the recorder is not alive after %.0f s: starting the other services anyway", timeout_s)


def run_demo_fast(args: argparse.Namespace) -> int:
    """``nwr demo --fast``: the demo session in lockstep, recorded, then its per-touch table."""
    from nwr.services.recorder.main import session_name
    from nwr.services.replay import simulate

    unsupported = [flag for flag, value in (("--planners", args.planners), ("--follow-target", args.follow_target),
                                            ("--view", args.view), ("--no-record", args.no_record)) if value]
    if unsupported:
        raise ConfigError(f"{', '.join(unsupported)}: not with --fast (one planner, the touch script, a recording)")
    profile = profile_for(args)
    if args.closed_loop:
        profile.gateway.sim.closed_loop = True
    session = args.session or session_name()
    output = Path(args.output) if args.output else Path(profile.recorder.directory) / f"{session}.mcap"
    strategy = args.reflex or profile.planner.strategy
    path, simulated, wall = simulate(profile, args.script, strategy, output)
    print(f"simulated {simulated:.1f} s of the touch script {args.script!r} against {strategy!r} in lockstep in "
          f"{wall:.2f} s{' (closed loop)' if profile.gateway.sim.closed_loop else ''}: {path}")
    return print_summary(path, args.script, profile)


def print_summary(path: Path, script_name: str | None, profile: Profile | None = None) -> int:
    from nwr.common.recordings import read_recording
    from nwr.common.robot import load_description
    from nwr.services import analysis

    records, metadata = read_recording(path)
    profile = profile or load_profile(None)
    desc = load_description(profile.robot.description or None)
    touches = analysis.summarize(records, desc)
    first = next((r.message.stamp_ns for r in records if r.key == "skin/pressure"), 0)
    print(f"\nRecording {path}: {len(records)} messages")
    print(analysis.format_table(analysis.HEADER, analysis.table_rows(touches, first)))
    latencies = [t.onset_latency_ms for t in touches if t.onset_latency_ms is not None]
    if latencies:
        import numpy as np

        print(f"\nreflex onset latency over {len(latencies)} reflexes: median {np.median(latencies):.2f} ms, "
              f"worst {max(latencies):.2f} ms")
    if script_name:
        return _compare_with_script(touches, script_name, desc, first, profile)
    return 0


def _compare_with_script(touches: list[Any], script_name: str, desc: Any, t0_ns: int, profile: Profile) -> int:
    """Every scripted touch seen on its pad at its time, with a reflex exactly when G(peak) > 0."""
    from nwr.services.gain.core import GainEstimator

    estimator = GainEstimator(profile.gain, desc.pads)
    script = load_script(script_name)
    mismatches = []
    for touch in script.touch:
        pad = desc.pad(touch.pad)
        _, expected_gain = estimator.gain(pad.id, touch.peak_hpa)
        window = (touch.start_s - 0.2, touch.start_s + touch.ramp_s + 0.3)
        match = next((t for t in touches if t.pad == pad.id and window[0] <= (t.start_ns - t0_ns) / 1e9 <= window[1]),
                     None)
        if match is None:
            mismatches.append(f"touch on {pad.name} at {touch.start_s} s was not seen")
        elif (match.reflex_seq > 0) != (expected_gain > 0):
            mismatches.append(f"touch on {pad.name} at {touch.start_s} s ({touch.peak_hpa} hPa): "
                              f"expected {'a' if expected_gain > 0 else 'no'} reflex")
    if mismatches:
        print("\nthe recording does NOT match its script:\n  " + "\n  ".join(mismatches))
        return 1
    print(f"\nall {len(script.touch)} scripted touches as expected "
          f"({sum(1 for t in touches if t.reflex_seq)} reflexes, none from sub-threshold touches)")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    service = args.service if args.command == "run" else args.command
    setup_logging(args.log_level, service)
    try:
        # Read here, not at import: flags and environment override the profile in main.
        args.env_overrides = env_overrides(os.environ)
        if insecure(args.env_overrides):
            log.warning("NWR_INSECURE=1: secure mode is OFF (no TLS, no access control): anyone who reaches the "
                        "router can move the arm; for a first try on a trusted network only")
        if args.command == "run":
            profile = profile_for(args)
            return int(_service_module(args.service).run(profile, args) or 0)
        if args.command == "up":
            load_profile(args.profile)  # fail here, not in five processes
            return launch(args, until_script_end=False)[0]
        if args.command == "demo" and args.fast:
            return run_demo_fast(args)
        if args.command == "demo":
            load_profile(args.profile)
            load_script(args.script)
            code, path = launch(args, until_script_end=True)
            if code or path is None:
                return code or 1
            return print_summary(path, args.script, profile_for(args))
        if args.command == "summary":
            return print_summary(Path(args.file), args.script, profile_for(args))
        if hasattr(args, "handler"):
            return int(args.handler(args) or 0)
    except NwrError as exc:
        log.error("%s", exc)
        return 2
    except FileNotFoundError as exc:
        log.error("%s", exc)
        return 2
    finally:
        # Free the trajectory generators (nanobind objects caught in reference
        # cycles) before the interpreter tears their module down, which would
        # otherwise report them as leaked on exit.
        gc.collect()
    parser.error(f"unknown command {args.command}")
    return 2


if __name__ == "__main__":
    sys.exit(main())
