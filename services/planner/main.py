"""Reflex planner process: skin/pain + robot/state -> robot/command/<name> and reflex/<name>/status."""

from __future__ import annotations

import argparse
import logging
import sys
import threading

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.door import Door
from nwr.common.node import Node, relabel_logging
from nwr.common.pacing import realtime
from nwr.common.robot import RobotModel
from nwr.services.planner import strategies
from nwr.services.planner.wiring import PlannerWiring
from nwr.services.wiring import subscribe

log = logging.getLogger(__name__)

# A pain message's handler waits for the GIL while the control loop runs
# Python (the Cartesian stream's Jacobian, the retreat check): switch at least
# this often, s (Python's default is 5 ms, more than the whole reflex budget).
SWITCH_INTERVAL_S = 0.0005


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--name", help="planner instance name (overrides planner.name)")
    parser.add_argument("--reflex", choices=strategies.names(), help="reflex strategy (overrides planner.strategy)")


# Consecutive failed cycles after which the planner withdraws its liveliness token: the bridge
# then holds the arm (planner_lost) until a cycle succeeds again and the token is back.
FAULT_AFTER_CYCLES = 25


class Failing:
    """The planner's failed control cycles: reported once per kind, escalated when they repeat."""

    def __init__(self, node: Node) -> None:
        self.node = node
        self.consecutive = 0
        self.total = 0
        self.kinds: set[str] = set()
        self.faulted = False

    def failed(self, exc: Exception) -> None:
        self.consecutive += 1
        self.total += 1
        kind = type(exc).__name__
        if kind not in self.kinds:  # one traceback per kind, then counts on diag/planner-<name>
            self.kinds.add(kind)
            log.error("a control cycle failed: no command this cycle, starting again from the arm's state",
                      exc_info=exc)
        self.node.diag("error", "cycle_failed", f"a control cycle failed ({self.total} so far): {exc!r}")
        if self.consecutive >= FAULT_AFTER_CYCLES and not self.faulted:
            self.faulted = True
            self.node.withdraw_token()
            self.node.diag("error", "planner_fault", f"{self.consecutive} control cycles in a row failed: "
                           "liveliness withdrawn, the bridge holds the arm until a cycle succeeds", every_s=0.0)

    def ok(self) -> None:
        self.consecutive = 0
        if self.faulted:
            self.faulted = False
            self.node.declare_token()
            self.node.diag("info", "planner_recovered", "control cycles succeed again: liveliness back", every_s=0.0)


def run(profile: Profile, args: argparse.Namespace) -> int:
    cfg = profile.planner
    if args.name:
        cfg.name = args.name
    if args.reflex:
        cfg.strategy = args.reflex
    strategies.check(cfg.strategy)  # before the session: a profile naming no strategy fails at once
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    realtime(cfg.realtime_priority, "planner")  # before the session: Zenoh's threads inherit it
    lock = threading.Lock()
    wake = threading.Event()
    # Each planner instance has its own liveliness token, diagnostics and
    # journal keys, alive/planner-<name> and so on: the bridge watches the
    # token of the active one.
    relabel_logging(keys.planner_service(cfg.name))  # several planners run at once: each line says which
    with Node(keys.planner_service(cfg.name), profile.robot.name, profile.zenoh, listen_slot="planner",
              token=False, door=Door.of(profile), exclusive=True) as node:
        node.install_signal_handlers()
        wiring = node.wire(PlannerWiring, profile, lock)
        planner = wiring.planner
        rate = wiring.rate

        # The control loop sleeps through the cycles the task's plan covers
        # (Planner.quiet_cycles) and steps them when it wakes; an event that
        # needs the planner's state of the moment steps the ones due first,
        # and wakes the loop when the planner must step every cycle again.
        def wake_if_needed() -> None:
            if planner.quiet_cycles == 0:
                wake.set()

        # The retreat check (a few ms of kinematics per reflex) runs in a thread
        # of its own, on its own model, outside the lock: neither the next pain
        # message nor the control loop waits for it. Updates that arrive while
        # it runs coalesce into one check of the newest reflex.
        assess_pending = threading.Event()
        check_model = RobotModel(planner.desc)

        def check_retreats() -> None:
            while not node.stop.is_set():
                if not assess_pending.wait(0.1):
                    continue
                assess_pending.clear()
                with lock:
                    check = wiring.retreat_take()
                if check is None:
                    continue
                try:
                    assessment = check.run(check_model)
                except Exception as exc:  # a failed check must not end the checks of later reflexes
                    log.exception("retreat check of reflex %d failed", check.reflex.seq)
                    node.diag("error", "retreat_check_failed", f"retreat check of reflex {check.reflex.seq}: {exc!r}")
                    continue
                with lock:
                    wiring.retreat_apply(check, assessment)  # published with the reflex on the next status

        checker = threading.Thread(target=check_retreats, name="retreat-check", daemon=True)
        checker.start()

        def after_pain(command: m.Command | None) -> None:
            if command is not None:
                assess_pending.set()  # the retreat check, in its own thread
            wake_if_needed()

        # The reflex path's input and the arm's state run on Zenoh's network
        # thread (direct: no hand-off to a Python thread); the statuses not
        # (PlannerWiring.on_peer_status). A status never wakes the loop: an
        # inactive planner never sleeps.
        subscribe(node, wiring, lock, then={"pain": after_pain, "state": lambda _: wake_if_needed()})
        node.declare_token()  # alive once subscribed: the gateway starts on it, and no pain message is lost
        log.info("planner %r (%s) at %.0f Hz", cfg.name, planner.strategy.name, cfg.rate_hz)
        failing = Failing(node)
        try:
            while True:
                with lock:
                    quiet = planner.quiet_cycles
                if not rate.wait(node.stop, through=quiet, wake=wake if quiet else None):
                    break
                with lock:
                    wiring.tick()
                    failure = wiring.failure
                if failure is not None:
                    failing.failed(failure)
                else:
                    failing.ok()
        finally:
            node.stop.set()
            checker.join(1.0)
            log.info(rate.summary())
            log.info("%d reflexes started from the task, %d restarted by a new or stronger contact, %d planned in "
                     "shadow while standby; %d resynchronisations", planner.started, planner.restarted,
                     planner.shadowed, planner.resyncs)
    return 0
