"""``nwr status``: which services are alive and what flows, from any host that reaches the pipeline.

- ``nwr status`` lists the live services (liveliness tokens
  ``nwr/<robot>/alive/*``; planners announce themselves as
  ``planner-<name>``), the active planner and the bridge's status (from
  ``robot/state``), every planner's mode, each key's message rate over a
  short window, the last pain event seen in it, and a recorder that cannot
  write its disk (its ``diag/recorder``: it says so once a second while it
  cannot).
- ``nwr status --check SERVICE`` exits 0 if SERVICE's token is visible and 1
  if not: the compose health checks ask each service this way whether it is
  alive, through the same router every other service uses. SERVICE may be a
  glob (``'planner-*'``).

``python -m nwr.services.tools.status ...`` is the same command without the rest
of the CLI: it does not import the robot model or the services, so a health
check every few seconds stays cheap (about 0.3 s of CPU instead of 1.3 s).

:class:`StatusCollector` and :func:`format_report` are pure (no Zenoh, no
clock); :func:`collect` is the thin Zenoh adapter.
"""

from __future__ import annotations

import argparse
import fnmatch
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass, field

import zenoh

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile, ZenohSection
from nwr.common.errors import DecodeError, NwrError
from nwr.common.node import sender_instance, tls_endpoints, zenoh_config
from nwr.services.pipeline.graph import NOT_WAITED_FOR, SERVICES, START_ORDER, process_name

log = logging.getLogger(__name__)

RECORDER_DIAG = keys.diag("recorder")
# The recorder's codes about its disk (nwr.services.recorder.disk.DISK_CODES; not imported from there, which would
# load mcap into every health check, and test_recorder_disk holds the two equal).
RECORDER_DISK_CODES = ("write_failed", "not_writing", "recording_resumed")

# Long enough for every key of the pipeline (the slowest, planner status, is
# 10 Hz or more) to show a rate; short enough for a command a person waits on.
DEFAULT_WINDOW_S = 2.0
# A liveliness query through a router answers within a few ms on a LAN; the
# timeout only bounds the wait when the router or a peer is unreachable.
DEFAULT_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class PainEvent:
    """The strongest contact of the last ``skin/pain`` sample that had one."""

    contact: m.Contact
    received_ns: int


@dataclass
class StatusReport:
    robot: str
    endpoints: list[str]
    window_s: float
    alive: list[str]
    rates_hz: dict[str, float] = field(default_factory=dict)
    state: m.RobotState | None = None
    planners: dict[str, m.PlannerStatus] = field(default_factory=dict)
    pain: PainEvent | None = None
    undecodable: int = 0
    now_ns: int = 0
    recorder: m.Diagnostic | None = None  # the recorder's last disk diagnostic in the window
    # The other robots whose services are alive on the same mesh (a lab's router shared by several arms): robot
    # name -> its live services.
    others: dict[str, list[str]] = field(default_factory=dict)
    # Messages in the window per pipeline instance they carried (keys.NO_INSTANCE: a process started alone).
    instances: dict[str, int] = field(default_factory=dict)

    @property
    def active_planner(self) -> str | None:
        """The planner that moves the arm: the bridge's command owner, else the planner that says it is active."""
        if self.state is not None and self.state.owner:
            return self.state.owner
        active = [name for name, s in self.planners.items() if s.active]
        return active[0] if len(active) == 1 else None


class StatusCollector:
    """Counts messages per key and keeps the latest state, statuses and pain event."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.counts: dict[str, int] = {}
        self.state: m.RobotState | None = None
        self.planners: dict[str, m.PlannerStatus] = {}
        self.pain: PainEvent | None = None
        self.recorder: m.Diagnostic | None = None
        self.undecodable = 0
        self.instances: dict[str, int] = {}
        self._lock = threading.Lock()  # Zenoh calls observe() from its own threads

    def reset(self) -> None:
        """Start the rate window afresh (the latest state, statuses and pain event are kept).

        The recorder's disk diagnostic is not kept: it is repeated while the
        trouble lasts, so one from before the window would be stale.
        """
        with self._lock:
            self.counts.clear()
            self.instances.clear()
            self.recorder = None

    def observe(self, full_key: str, payload: bytes, received_ns: int, instance: str = keys.NO_INSTANCE) -> None:
        """One message; ``instance``: the pipeline instance it carried (common.node.sender_instance)."""
        try:
            relative = keys.relative_key(self.robot, full_key)
        except DecodeError:
            return  # not this robot's (the subscription is on its prefix, so only a malformed key)
        with self._lock:
            self.counts[relative] = self.counts.get(relative, 0) + 1
            self.instances[instance] = self.instances.get(instance, 0) + 1
            if relative not in (keys.ROBOT_STATE, keys.SKIN_PAIN, RECORDER_DIAG) and not (
                relative.startswith("reflex/") and relative.endswith("/status")
            ):
                return  # only counted: the report shows no content of other keys
            try:
                message = keys.codec(relative).decode(payload)
            except DecodeError:
                self.undecodable += 1
                return
            match message:
                case m.RobotState():
                    self.state = message
                case m.PlannerStatus():
                    self.planners[message.name] = message
                case m.SkinPain(strongest=m.Contact() as contact) if contact.level >= 1:
                    self.pain = PainEvent(contact, received_ns)
                case m.Diagnostic(code=code) if code in RECORDER_DISK_CODES:
                    self.recorder = message

    def report(self, alive: list[str], window_s: float, now_ns: int, endpoints: list[str]) -> StatusReport:
        with self._lock:
            return StatusReport(
                robot=self.robot, endpoints=endpoints, window_s=window_s, alive=sorted(alive),
                rates_hz={k: n / window_s for k, n in sorted(self.counts.items())},
                state=self.state, planners=dict(sorted(self.planners.items())), pain=self.pain,
                undecodable=self.undecodable, now_ns=now_ns, recorder=self.recorder,
                instances=dict(sorted(self.instances.items())),
            )


def matching(alive: list[str], service: str) -> list[str]:
    """The live services that ``service`` (a name or a glob such as ``planner-*``) names."""
    return [name for name in alive if fnmatch.fnmatchcase(name, service)]


def not_alive(alive: list[str]) -> list[str]:
    """The graph's services (but the read-only ones) that no live process stands for; planners as ``planner-*``."""
    out = []
    for service in START_ORDER:
        if service not in SERVICES or service in NOT_WAITED_FOR:
            continue
        name = process_name(service, "*") if service == "planner" else service
        if not matching(alive, name):
            out.append(name)
    return out


def format_report(report: StatusReport) -> str:
    where = ", ".join(report.endpoints) if report.endpoints else "the embedded mesh on loopback"
    lines = [f"robot {report.robot} via {where}; rates over {report.window_s:.1f} s"]
    lines.append(f"alive ({len(report.alive)}): {', '.join(report.alive) if report.alive else 'none'}")
    missing = not_alive(report.alive)
    if missing:
        lines.append(f"not alive: {', '.join(missing)}")
    active = report.active_planner
    if report.state is not None:
        s = report.state
        detail = f" ({s.detail})" if s.detail else ""
        pending = f", switching to {s.pending_owner}" if s.pending_owner else ""
        lines.append(f"active planner: {active or 'none'}{pending}; bridge ({s.backend}): {s.status}{detail}, "
                     f"{s.rejected} commands rejected, {s.clipped} clipped")
    else:
        lines.append(f"active planner: {active or 'unknown'}; bridge: no robot/state in the window")
    for name, p in report.planners.items():
        role = "active" if name == active else "standby"
        lines.append(f"  planner {name}: {p.strategy}, {p.mode}, {role}")
    if report.rates_hz:
        width = max(len(k) for k in report.rates_hz)
        lines.append("message rates:")
        lines.extend(f"  {k:<{width}s}  {hz:7.1f} Hz" for k, hz in report.rates_hz.items())
    else:
        lines.append("message rates: no message in the window")
    if report.pain is not None:
        c = report.pain.contact
        ago = (report.now_ns - report.pain.received_ns) / 1e9
        lines.append(f"last pain event: {c.name} ({c.region}) PL {c.level}, gain {c.gain:.3f}, "
                     f"{c.change_hpa:+.1f} hPa, {ago:.1f} s ago")
    else:
        lines.append(f"last pain event: none in the last {report.window_s:.1f} s")
    if report.recorder is not None:
        # The recorder's own words: "not writing: disk full (...) at FILE; ...", or "recording resumed in FILE ...".
        lines.append(f"recorder: {report.recorder.message}")
    if report.undecodable:
        lines.append(f"warning: {report.undecodable} samples did not decode (see diag/*)")
    launched = {i: n for i, n in report.instances.items() if i != keys.NO_INSTANCE}
    if len(launched) > 1:
        lines.append(f"warning: messages of {len(launched)} pipeline instances on this robot's keys ("
                     + ", ".join(f"{i}: {n}" for i, n in launched.items())
                     + "): each service takes its own pipeline's only (foreign_instance on its diag key); a stale "
                       "process of an earlier run, or a second pipeline under this robot's name, publishes here")
    if report.others:
        lines.append("other robots on this mesh: " + "; ".join(
            f"{robot} ({len(services)} alive: {', '.join(services)})" for robot, services in report.others.items()))
    return "\n".join(lines)


# -- the Zenoh adapter ------------------------------------------------------

def _open(profile: Profile) -> zenoh.Session:
    try:
        return zenoh.open(zenoh_config(profile.zenoh))
    except zenoh.ZError as exc:
        where = profile.zenoh.router or "the embedded mesh on loopback"
        raise ConnectionError(f"cannot open a Zenoh session to {where}: {exc}; is the router (or the pipeline) "
                              "running and reachable? Set NWR_ROUTER or [zenoh] router to its endpoint") from exc


def alive_services(session: zenoh.Session, robot: str, timeout_s: float) -> list[str]:
    """Names of the services whose liveliness token ``nwr/<robot>/alive/<name>`` is visible."""
    found = set()
    for reply in session.liveliness().get(keys.key(robot, keys.alive("*")), timeout=timeout_s):
        if reply.ok is not None:
            found.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
    return sorted(found)


def robots_alive(session: zenoh.Session, timeout_s: float) -> dict[str, list[str]]:
    """Every robot with a live service on the mesh (tokens ``nwr/<robot>/alive/<name>``): robot -> its services."""
    found: dict[str, set[str]] = {}
    for reply in session.liveliness().get(f"{keys.PREFIX_ROOT}/*/{keys.alive('*')}", timeout=timeout_s):
        if reply.ok is not None:
            parts = str(reply.ok.key_expr).split("/")
            if len(parts) == 4:
                found.setdefault(parts[1], set()).add(parts[3])
    return {robot: sorted(services) for robot, services in sorted(found.items())}


def dialled(zcfg: ZenohSection) -> list[str]:
    """The router endpoints as the session dials them: in secure mode tcp/ ones as tls/ (common.node.zenoh_config)."""
    return tls_endpoints(zcfg.router, "[zenoh] router") if zcfg.secure else list(zcfg.router)


def collect(profile: Profile, window_s: float, timeout_s: float) -> StatusReport:
    robot = profile.robot.name
    collector = StatusCollector(robot)
    with _open(profile) as session:
        sub = session.declare_subscriber(
            f"{keys.prefix(robot)}/**",
            lambda s: collector.observe(str(s.key_expr), s.payload.to_bytes(), time.monotonic_ns(),
                                        sender_instance(s.attachment)),
        )
        alive = alive_services(session, robot, timeout_s)
        # The query's reply came back through the router after the
        # subscriber's declaration reached it: count from here, over the
        # time really elapsed, or the rates come out low.
        collector.reset()
        start = time.monotonic_ns()
        time.sleep(window_s)
        elapsed_s = (time.monotonic_ns() - start) / 1e9
        sub.undeclare()
        alive = sorted(set(alive) | set(alive_services(session, robot, timeout_s)))
        report = collector.report(alive, elapsed_s, time.monotonic_ns(), dialled(profile.zenoh))
        report.others = {r: s for r, s in robots_alive(session, timeout_s).items() if r != robot}
        return report


def check(profile: Profile, service: str, timeout_s: float) -> int:
    """0 if ``service`` is alive, 1 if not (the health-check contract)."""
    robot = profile.robot.name
    with _open(profile) as session:
        deadline = time.monotonic() + timeout_s
        # Right after the session opens, the router may not have sent every
        # token yet: ask again until the deadline before saying "not alive".
        while True:
            alive = alive_services(session, robot, min(1.0, timeout_s))
            found = matching(alive, service)
            if found or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
    if found:
        print(f"{', '.join(found)} alive (robot {robot})")
        return 0
    print(f"{service} is not alive (robot {robot}); alive: {', '.join(alive) if alive else 'none'}", file=sys.stderr)
    return 1


# -- the command ------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--check", metavar="SERVICE",
                        help="exit 0 if SERVICE (e.g. bridge, planner-cartesian, or a glob 'planner-*') is alive, "
                             "1 if not; prints nothing else (for health checks)")
    parser.add_argument("--window", type=float, default=DEFAULT_WINDOW_S, metavar="S",
                        help=f"how long to count messages for the rates, s (default: {DEFAULT_WINDOW_S:g})")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                        help=f"how long to wait for liveliness replies, s (default: {DEFAULT_TIMEOUT_S:g})")


def run(profile: Profile, args: argparse.Namespace) -> int:
    if args.window <= 0 or args.timeout <= 0:
        raise ValueError(f"--window ({args.window}) and --timeout ({args.timeout}) must be positive seconds")
    try:
        if args.check:
            return check(profile, args.check, args.timeout)
        print(format_report(collect(profile, args.window, args.timeout)))
        return 0
    except ConnectionError as exc:
        print(str(exc), file=sys.stderr)
        return 1


def _handler(args: argparse.Namespace) -> int:
    from nwr.services.profile import profile_for

    return run(profile_for(args), args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "status", help="live services, active planner, message rates and the last pain event",
        description="Show which services are alive (their liveliness tokens), the active planner and the bridge's "
                    "status, each key's message rate over a short window and the last pain event. With --check "
                    "SERVICE, exit 0 if that service is alive and 1 if not (compose health checks).",
    )
    add_arguments(p)
    p.set_defaults(handler=_handler)


def main(argv: list[str] | None = None) -> int:
    """``python -m nwr.services.tools.status``: ``nwr status`` without importing every service."""
    from nwr.common.launch import env_overrides
    from nwr.services.profile import profile_for

    parser = argparse.ArgumentParser(prog="python -m nwr.services.tools.status", description=__doc__.split("\n")[0])
    parser.add_argument("--profile", "-p", default=os.environ.get("NWR_PROFILE", "default"))
    add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    args.env_overrides = env_overrides(os.environ)
    try:
        return run(profile_for(args), args)
    except NwrError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
