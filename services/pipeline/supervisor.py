"""The supervisor: starts a layout of the graph as processes, watches them, stops them in the graph's order.

Each unit is ``python -m nwr.services.cli [--profile P --log-level L] run
SERVICE ARGS`` (or ``router ARGS``). :func:`launch` is ``nwr up`` and the live
``nwr demo``; ``nwr bench``, ``nwr replay`` and ``nwr study`` spawn and stop
their units with :func:`spawn` and :func:`stop_all`.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path

from nwr.common.config import Profile
from nwr.common.errors import NwrError
from nwr.services.pipeline.graph import ROUTER, Layout, Unit, stop_order, units

log = logging.getLogger("nwr")

# A stop by signal is a clean stop.
CLEAN_EXITS = (0, -signal.SIGTERM, -signal.SIGINT)
# Once the gateway has exited, its last samples (and the reflexes they cause) reach the others before they are
# asked to stop, s: a loaded machine at 1 kHz lags by tens of ms.
GATEWAY_GRACE_S = 0.3

# How long a router may take to listen before its clients (which give up at once on one that is not there) start.
ROUTER_START_S = 30.0


def listen_endpoint(unit: Unit) -> str | None:
    """The endpoint a router unit listens on (its ``--listen``), if it names one."""
    args = list(unit.args)
    return args[args.index("--listen") + 1] if "--listen" in args[:-1] else None


def wait_listening(endpoint: str, proc: subprocess.Popen[bytes], timeout_s: float = ROUTER_START_S) -> None:
    """Until something accepts TCP connections on ``endpoint`` (``tcp/HOST:PORT`` or ``tls/HOST:PORT``); a
    NwrError if ``proc`` exits first or ``timeout_s`` passes. A loaded machine starts a router in more than a
    fixed half second."""
    host, _, port = endpoint.split("/", 1)[-1].rpartition(":")
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
                return
        except OSError:
            if proc.poll() is not None:
                raise NwrError(f"the router exited (code {proc.returncode}) before it listened on {endpoint}") \
                    from None
            if time.monotonic() > deadline:
                raise NwrError(f"the router did not listen on {endpoint} within {timeout_s:.0f} s") from None
            time.sleep(0.05)


def wait_for_router(unit: Unit, proc: subprocess.Popen[bytes]) -> None:
    """Before the router's clients start: until it listens where its unit says (a moment, if it names nothing)."""
    endpoint = listen_endpoint(unit)
    if endpoint is None or endpoint.split("/", 1)[0] not in ("tcp", "tls"):
        time.sleep(0.3)
        return
    wait_listening(endpoint, proc)


# This launcher's pipeline instance, which every process it starts carries (NWR_INSTANCE): a service it
# restarts finds its own pipeline's owner tokens, and refuses another's (nwr.common.node.Node.claim).
INSTANCE = os.environ.get("NWR_INSTANCE") or f"{socket.gethostname()}.{os.getpid()}.{int(time.time())}"
# Why a process is a restart (nwr.common.node.RESTART_ENV): the service says so on its diag/<service>.
RESTART_ENV = "NWR_RESTART"


def spawn(unit: Unit, profile: str, log_level: str, log_path: Path | None = None, *,
          pass_fds: tuple[int, ...] = (), restart: str | None = None) -> subprocess.Popen[bytes]:
    """Start one unit; its output goes to ``log_path`` if given, else to this process's; ``pass_fds``: inherited;
    ``restart``: why this is a restart, which the service reports on its ``diag/<service>`` (``restarted``)."""
    cmd = [sys.executable, "-m", "nwr.services.cli", "--profile", profile, "--log-level", log_level, *unit.command()]
    env = {**os.environ, "NWR_INSTANCE": INSTANCE}
    env.pop(RESTART_ENV, None)
    if restart is not None:
        env[RESTART_ENV] = restart
    if log_path is None:
        return subprocess.Popen(cmd, pass_fds=pass_fds, env=env)
    with log_path.open("wb") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, pass_fds=pass_fds, env=env)


def check_robot_free(profile: Profile) -> None:
    """Before a launch: a NwrError naming every live service of another pipeline on the profile's robot."""
    if profile.zenoh.secure:
        return  # the launcher has no certificate of its own: each service checks for itself (Node.claim)
    from nwr.common.node import Node

    with Node("launcher", profile.robot.name, profile.zenoh, token=False) as node:
        others = node.owners()
    if others:
        raise NwrError(
            f"robot {profile.robot.name!r} is already driven by another pipeline: "
            f"{'; '.join(o.describe() for o in others)}. Stop it, or run this one under another robot name "
            "(NWR_ROBOT=NAME or [robot] name; on one machine, another [zenoh] base_port too)")


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


# A service that exits unexpectedly is restarted after this long, doubling per restart up to the cap, s.
RESTART_DELAY_S = 0.5
RESTART_DELAY_MAX_S = 30.0
# A service that has run this long since its last start restarts after RESTART_DELAY_S again, s.
STABLE_S = 60.0


class Restarts:
    """When each unit that exited may start again: exponential backoff, reset once it ran a while."""

    def __init__(self) -> None:
        self.count: dict[str, int] = {}
        self.delay: dict[str, float] = {}
        self.due: dict[str, float] = {}

    def schedule(self, label: str, started_at: float, now: float) -> float:
        if now - started_at >= STABLE_S:
            self.delay.pop(label, None)
        delay = self.delay.get(label, RESTART_DELAY_S / 2) * 2
        self.delay[label] = min(delay, RESTART_DELAY_MAX_S)
        self.due[label] = now + self.delay[label]
        self.count[label] = self.count.get(label, 0) + 1
        return self.delay[label]

    def ready(self, now: float) -> list[str]:
        ready = [label for label, at in self.due.items() if at <= now]
        for label in ready:
            del self.due[label]
        return ready


def launch(layout: Layout, profile: Profile, profile_arg: str, log_level: str, *, until_script_end: bool,
           settle_s: float = 2.0, restart: bool = True) -> int:
    """Start every unit; wait for Ctrl-C/SIGTERM (or the gateway's end of script); stop them all; 0 if all went well.

    With ``until_script_end`` the gateway tells the end of its touch script on
    a pipe (``--notify-fd``) and goes on publishing the pads at rest: after
    ``settle_s`` (the last reflex returns) the units stop in the graph's order,
    the bridge first, so the session ends with the arm brought to rest while
    the skin is still watched, not with a stale input.

    A unit that exits unexpectedly is restarted with backoff (:class:`Restarts`) while the others keep running
    (the bridge holds the arm meanwhile; nothing waits for the recorder, so the arm's task goes on while it is
    gone, and the launcher says loudly that the recording has a hole); with ``restart=False`` every unit is
    stopped instead, and 1 returned.
    """
    by_label = {unit.label: unit for unit in units(layout)}
    if "gateway" in by_label:
        from nwr.services.gateway import sources

        sources.live(profile.gateway.source)  # a source that is not there fails here, before anything starts
    check_robot_free(profile)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    started: dict[str, float] = {}
    restarts = Restarts()
    stop = False

    def on_signal(signum: int, _frame: object) -> None:
        nonlocal stop
        stop = True

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    ends = ScriptEnd() if until_script_end else None
    if ends is not None and "gateway" in by_label:
        gateway = by_label["gateway"]
        by_label["gateway"] = Unit(gateway.label, gateway.service, (*gateway.args, "--notify-fd", str(ends.write_fd)))

    def start(unit: Unit, restart: str | None = None) -> subprocess.Popen[bytes]:
        fds = (ends.write_fd,) if ends is not None and unit.service == "gateway" else ()
        return spawn(unit, profile_arg, log_level, pass_fds=fds, restart=restart)

    try:
        for unit in by_label.values():
            procs[unit.label] = start(unit)
            started[unit.label] = time.monotonic()
            if unit.label == "recorder":
                wait_for_recorder(profile, procs[unit.label])
            elif unit.service == ROUTER:
                wait_for_router(unit, procs[unit.label])
        log.info("started %s", ", ".join(f"{n} (pid {p.pid})" for n, p in procs.items()))
        while not stop:
            now = time.monotonic()
            dead = {n: p.returncode for n, p in procs.items() if p.poll() is not None and n not in restarts.due}
            if ends is not None and ends.ended():
                log.info("the touch script has ended: stopping in %.1f s, once the last reflex has returned",
                         settle_s)
                time.sleep(settle_s)
                break
            if dead and not restart:
                log.error("service(s) exited unexpectedly: %s (stopping every service: --stop-on-exit)", dead)
                stop_all(procs)
                return 1
            for label, code in dead.items():
                delay = restarts.schedule(label, started[label], now)
                log.error("%s exited unexpectedly (code %s): restarting it in %.1f s (restart %d); the others "
                          "keep running", label, code, delay, restarts.count[label])
                if by_label[label].service == "recorder":
                    # The arm's task goes on without it (nothing waits for the recorder): say loudly that the
                    # session's recording has a hole, and where it goes on.
                    log.error("NOTHING IS RECORDED until the recorder is back (in %.1f s or more): the session's "
                              "recording has a hole from here; the arm and the other services keep running; the "
                              "restarted recorder writes %s", delay,
                              _restart_output(by_label[label], restarts.count[label]))
            for label in restarts.ready(now):
                n = restarts.count[label]
                procs[label] = start(by_label[label].restarted(n),
                                     f"its last process ended with code {procs[label].returncode} (restart {n})")
                started[label] = now
                log.warning("restarted %s (pid %d)", label, procs[label].pid)
            time.sleep(0.1)
    finally:
        codes = stop_all({n: p for n, p in procs.items() if n not in restarts.due})
        for s, handler in old.items():
            signal.signal(s, handler)
        if ends is not None:
            ends.close()
    if restarts.count:
        log.warning("restarts: %s", ", ".join(f"{n} {k}x" for n, k in restarts.count.items()))
    bad = failed(codes)
    if bad:
        log.error("service(s) stopped with errors: %s", bad)
        return 1
    return 0


class ScriptEnd:
    """The pipe on which a gateway tells the launcher its touch script has ended (``--notify-fd``)."""

    def __init__(self) -> None:
        self.read_fd, self.write_fd = os.pipe()  # the write end stays open here: a restarted gateway inherits it
        os.set_blocking(self.read_fd, False)

    def ended(self) -> bool:
        try:
            return b"script-end" in os.read(self.read_fd, 4096)
        except BlockingIOError:
            return False

    def close(self) -> None:
        for fd in (self.read_fd, self.write_fd):
            os.close(fd)


def _restart_output(unit: Unit, n: int) -> str:
    args = unit.restarted(n).args
    return args[args.index("--output") + 1] if "--output" in args else "a new file of its own"


def wait_for_recorder(profile: Profile, proc: subprocess.Popen[bytes] | None = None,
                      timeout_s: float = 30.0) -> None:
    """Until the recorder is alive (subscribed): what the others publish from their start is recorded.

    A recorder that exits meanwhile (``proc``) is not waited for: the others start at once, and the
    launcher's loop restarts it.
    """
    if profile.zenoh.secure:
        return  # the launcher has no certificate of its own: the services start at once
    from nwr.common.node import Node

    deadline = time.monotonic() + timeout_s
    with Node("launcher", profile.robot.name, profile.zenoh, token=False) as node:
        while node.wait_for(["recorder"], min(1.0, max(0.0, deadline - time.monotonic()))):
            if proc is not None and proc.poll() is not None:
                log.error("the recorder exited at its start (code %s): starting the other services without it",
                          proc.returncode)
                return
            if time.monotonic() >= deadline:
                log.warning("the recorder is not alive after %.0f s: starting the other services anyway",
                            timeout_s)
                return
