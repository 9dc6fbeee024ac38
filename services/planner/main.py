"""Reflex planner process: skin/pain + robot/state -> robot/command/<name> and reflex/<name>/status."""

from __future__ import annotations

import argparse
import logging
import sys
import threading

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import STRATEGIES, Profile
from nwr.common.node import Node
from nwr.common.pacing import Rate, realtime
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.core import Planner

log = logging.getLogger(__name__)

# A pain message's handler waits for the GIL while the control loop runs
# Python (the Cartesian stream's Jacobian, the retreat check): switch at least
# this often, s (Python's default is 5 ms, more than the whole reflex budget).
SWITCH_INTERVAL_S = 0.0005


def planner_service(name: str) -> str:
    return f"planner-{name}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--name", help="planner instance name (overrides planner.name)")
    parser.add_argument("--reflex", choices=STRATEGIES, help="reflex strategy (overrides planner.strategy)")


def run(profile: Profile, args: argparse.Namespace) -> int:
    cfg = profile.planner
    if args.name:
        cfg.name = args.name
    if args.reflex:
        cfg.strategy = args.reflex
    desc = load_description(profile.robot.description or None)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    realtime(cfg.realtime_priority, "planner")  # before the session: Zenoh's threads inherit it
    planner = Planner(cfg, desc, RobotModel(desc))
    lock = threading.Lock()
    # The control loop sleeps through the cycles the task's plan covers
    # (Planner.quiet_cycles) and steps them when it wakes; an event that needs
    # the planner's state of the moment steps the ones due first (catch_up),
    # and wakes the loop when the planner must step every cycle again.
    rate = Rate(cfg.rate_hz, "planner")
    wake = threading.Event()

    def catch_up(now: int) -> None:
        for _ in range(rate.take(now, limit=planner.quiet_cycles)):
            planner.step(now)  # a planned cycle: no command

    def wake_if_needed() -> None:
        if planner.quiet_cycles == 0:
            wake.set()
    # Each planner instance has its own liveliness token and diagnostics key,
    # alive/planner-<name> and diag/planner-<name>: the bridge watches the
    # token of the active one.
    with Node(planner_service(cfg.name), profile.robot.name, profile.zenoh, listen_slot="planner") as node:
        node.install_signal_handlers()
        send = node.publisher(keys.robot_command(cfg.name))
        send_status = node.publisher(keys.planner_status(cfg.name))
        send_decision = node.publisher(keys.planner_decision(cfg.name))

        def on_state(state: m.RobotState) -> None:
            q = m.as_array(state.q)
            if q.shape != planner.q.shape:
                node.diag("warning", "bad_state", f"robot state has {q.size} joints, the robot has {planner.q.size}")
                return
            with lock:
                now = node.clock.now_ns()
                catch_up(now)
                planner.on_state(q, following=state.owner == cfg.name and state.status == "ok",
                                 dq=m.as_array(state.dq), owner=state.owner, now_ns=now)
                if planner.changed:
                    send_status(planner.status(node.clock.now_ns()))
                wake_if_needed()

        # The retreat check (a few ms of kinematics per reflex) runs in a thread
        # of its own, on its own model, outside the lock: neither the next pain
        # message nor the control loop waits for it. Updates that arrive while
        # it runs coalesce into one check of the newest reflex.
        assess_pending = threading.Event()
        check_model = RobotModel(desc)

        def check_retreats() -> None:
            while not node.stop.is_set():
                if not assess_pending.wait(0.1):
                    continue
                assess_pending.clear()
                with lock:
                    check = planner.retreat_check()
                if check is None:
                    continue
                try:
                    assessment = check.run(check_model)
                except Exception as exc:  # a failed check must not end the checks of later reflexes
                    log.exception("retreat check of reflex %d failed", check.reflex.seq)
                    node.diag("error", "retreat_check_failed", f"retreat check of reflex {check.reflex.seq}: {exc!r}")
                    continue
                with lock:
                    # Published with the reflex on the control loop's next status.
                    planner.apply_retreat(check, assessment)

        checker = threading.Thread(target=check_retreats, name="retreat-check", daemon=True)
        checker.start()

        def on_pain(pain: m.SkinPain) -> None:
            # The event path: a reflex starts the moment its pain message arrives.
            received = node.clock.now_ns()
            with lock:
                catch_up(received)
                try:
                    command = planner.on_pain(pain, node.clock.now_ns())
                except ValueError as exc:
                    node.diag("warning", "bad_pain", str(exc))
                    return
                decided = node.clock.now_ns()
                if command is not None:
                    send(command)
                # After the command: noting the decision costs the reflex nothing.
                send_decision(planner.decision(pain, received, decided, command))
                if command is not None:
                    assess_pending.set()  # the retreat check, in its own thread
                if planner.changed:
                    send_status(planner.status(node.clock.now_ns()))
                wake_if_needed()

        def on_peer_status(status: m.PlannerStatus) -> None:
            with lock:
                planner.on_peer_status(status, node.clock.now_ns())  # inactive only: it never sleeps then

        # The reflex path's input and the arm's state run on Zenoh's network
        # thread (direct: no hand-off to a Python thread). The statuses may not:
        # this planner's own status, put while the lock is held, comes back to
        # this process through that subscription, in the putting thread.
        node.subscribe(keys.ROBOT_STATE, on_state, direct=True)
        node.subscribe(keys.planner_status("*"), on_peer_status)
        node.subscribe(keys.SKIN_PAIN, on_pain, direct=True)
        log.info("planner %r (%s) at %.0f Hz", cfg.name, planner.strategy_name, cfg.rate_hz)
        status_every = max(1, round(cfg.rate_hz / cfg.status_rate_hz))
        status_tick = 0
        with lock:
            rate.restart(node.clock.now_ns())  # not the deadlines that passed while the session opened
        try:
            while True:
                with lock:
                    quiet = planner.quiet_cycles
                if not rate.wait(node.stop, through=quiet, wake=wake if quiet else None):
                    break
                with lock:
                    now = node.clock.now_ns()
                    due = rate.take(now, limit=planner.quiet_cycles + 1)
                    if due == 0:
                        continue  # woken early, or an event stepped the cycles due
                    rate.skip(now)  # cycles beyond those are lost to a late loop (motion slows, never jumps)
                    for _ in range(due):
                        command = planner.step(now)
                        if command is not None:
                            send(command)
                    if planner.changed or rate.ticks - status_tick >= status_every:
                        status_tick = rate.ticks
                        send_status(planner.status(now))
        finally:
            node.stop.set()
            checker.join(1.0)
            log.info(rate.summary())
            log.info("%d reflexes, %d resynchronisations", planner.reflex_count, planner.resyncs)
    return 0
