"""The supervisor: starts a layout of the graph as processes, watches them, stops them in the graph's order.

Each unit is ``python -m nwr.services.cli [--profile P --log-level L] run
SERVICE ARGS`` (or ``router ARGS``). :func:`launch` is ``nwr up`` and the live
``nwr demo``; ``nwr bench``, ``nwr replay`` and ``nwr study`` spawn and stop
their units with :func:`spawn` and :func:`stop_all`.
"""

from __future__ import annotations

import logging
import signal
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path

from nwr.common.config import Profile
from nwr.services.pipeline.graph import ROUTER, Layout, Unit, stop_order, units

log = logging.getLogger("nwr")

# A stop by signal is a clean stop.
CLEAN_EXITS = (0, -signal.SIGTERM, -signal.SIGINT)
# Once the gateway has exited, its last samples (and the reflexes they cause) reach the others before they are
# asked to stop, s: a loaded machine at 1 kHz lags by tens of ms.
GATEWAY_GRACE_S = 0.3


def spawn(unit: Unit, profile: str, log_level: str, log_path: Path | None = None) -> subprocess.Popen[bytes]:
    """Start one unit; its output goes to ``log_path`` if given, else to this process's."""
    cmd = [sys.executable, "-m", "nwr.services.cli", "--profile", profile, "--log-level", log_level, *unit.command()]
    if log_path is None:
        return subprocess.Popen(cmd)
    with log_path.open("wb") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)


def stop_all(procs: Mapping[str, subprocess.Popen[bytes]], timeout_s: float = 10.0) -> dict[str, int]:
    """SIGTERM in the graph's stop order, each group once the one before has exited; kill stragglers."""
    deadline = time.monotonic() + timeout_s
    codes: dict[str, int] = {}
    for group in stop_order(list(procs)):
        for name in group:
            if procs[name].poll() is None:
                procs[name].send_signal(signal.SIGTERM)
        for name in group:
            try:
                codes[name] = procs[name].wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("%s did not stop within %.0f s: killing it", name, timeout_s)
                procs[name].kill()
                codes[name] = procs[name].wait()
        if "gateway" in group and len(procs) > 1:
            time.sleep(GATEWAY_GRACE_S)  # what the gateway sent last is still on its way through the others
    return {n: codes[n] for n in procs}


def failed(codes: Mapping[str, int]) -> dict[str, int]:
    """The processes that did not stop cleanly."""
    return {n: c for n, c in codes.items() if c not in CLEAN_EXITS}


def launch(layout: Layout, profile: Profile, profile_arg: str, log_level: str, *, until_script_end: bool,
           settle_s: float = 2.0) -> int:
    """Start every unit; wait for Ctrl-C/SIGTERM (or the gateway's end of script); stop them all; 0 if all went well."""
    procs: dict[str, subprocess.Popen[bytes]] = {}
    stop = False

    def on_signal(signum: int, _frame: object) -> None:
        nonlocal stop
        stop = True

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        for unit in units(layout):
            procs[unit.label] = spawn(unit, profile_arg, log_level)
            if unit.label == "recorder":
                wait_for_recorder(profile)
            elif unit.service == ROUTER:
                time.sleep(0.3)  # clients connect at start-up
        log.info("started %s", ", ".join(f"{n} (pid {p.pid})" for n, p in procs.items()))
        while not stop:
            dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None}
            if until_script_end and dead.get("gateway") == 0 and len(dead) == 1:
                time.sleep(settle_s)  # let the last reflex return and the recorder catch up
                break
            if dead:
                log.error("service(s) exited unexpectedly: %s", dead)
                stop_all(procs)
                return 1
            time.sleep(0.1)
    finally:
        codes = stop_all(procs)
        for s, handler in old.items():
            signal.signal(s, handler)
    bad = failed(codes)
    if bad:
        log.error("service(s) stopped with errors: %s", bad)
        return 1
    return 0


def wait_for_recorder(profile: Profile, timeout_s: float = 30.0) -> None:
    """Until the recorder is alive (subscribed): what the others publish from their start is recorded."""
    if profile.zenoh.secure:
        return  # the launcher has no certificate of its own: the services start at once
    from nwr.common.node import Node

    with Node("launcher", profile.robot.name, profile.zenoh, token=False) as node:
        if node.wait_for(["recorder"], timeout_s):
            log.warning("the recorder is not alive after %.0f s: starting the other services anyway", timeout_s)
