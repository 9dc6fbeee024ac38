"""``nwr switch NAME``: make another running planner the active one.

Puts a :class:`~nwr.common.messages.SwitchRequest` on ``control/active``;
the bridge carries it out as soon as no reflex or return is under way and
says so on ``robot/state`` (``owner``, ``handover``). The command waits for
that and prints how long the handover took.
"""

from __future__ import annotations

import argparse
import getpass
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.node import Node
from nwr.services.profile import profile_for

CYCLE_S = 0.002
SWITCH_REJECTED = "switch_rejected"  # the bridge's diagnostic code when it refuses a switch (bridge/core.py)
# Long enough for a new session to connect and its subscriber to see a robot state (50 Hz).
CONNECT_S = 0.5


def ask_the_bridge(args: argparse.Namespace, service: str, key: str,
                   request: Callable[[m.RobotState | None, Node], Any | None],
                   done: Callable[[m.RobotState], bool],
                   refused: Callable[[m.Diagnostic], bool] | None = None,
                   ) -> tuple[bool, m.RobotState | None, m.Diagnostic | None]:
    """Watch robot/state, put ``request(last state, node)`` on ``key`` (None: put nothing), wait until ``done``,
    or until the bridge says on diag/bridge that it ``refused`` the request.

    Returns whether ``done`` held within ``args.timeout`` s (at once if nothing was put), the last state seen and
    the bridge's refusal, if it refused.
    """
    profile = profile_for(args)
    finished = threading.Event()
    seen: list[m.RobotState] = []
    refusal: list[m.Diagnostic] = []
    asked, achieved = threading.Event(), threading.Event()

    def on_state(state: m.RobotState) -> None:
        seen[:] = [state]
        if done(state):
            achieved.set()
            finished.set()

    def on_diag(diag: m.Diagnostic) -> None:
        if asked.is_set() and refused is not None and refused(diag):
            refusal[:] = [diag]
            finished.set()

    with Node(service, profile.robot.name, profile.zenoh, token=False) as node:
        node.subscribe(keys.ROBOT_STATE, on_state)
        if refused is not None:
            node.subscribe(keys.diag("bridge"), on_diag)
        time.sleep(CONNECT_S)
        message = request(seen[0] if seen else None, node)
        if message is None:
            return True, seen[0] if seen else None, None
        finished.clear()
        achieved.clear()
        asked.set()
        node.publisher(key)(message)
        finished.wait(args.timeout)
        return achieved.is_set() and not refusal, seen[0] if seen else None, refusal[0] if refusal else None


def requested_by() -> str:
    return f"{getpass.getuser()}@{socket.gethostname()}"


def _run(args: argparse.Namespace) -> int:
    already = False

    def request(last: m.RobotState | None, node: Node) -> m.SwitchRequest | None:
        nonlocal already
        if last is not None and last.owner == args.name:
            already = True
            return None
        return m.SwitchRequest(seq=0, stamp_ns=node.clock.now_ns(), name=args.name, requested_by=requested_by())

    ok, state, refusal = ask_the_bridge(args, "switch", keys.CONTROL_ACTIVE, request, lambda s: (
        s.handover is not None and s.handover.owner == args.name and s.handover.first_command_ns > 0),
        refused=lambda d: d.code == SWITCH_REJECTED and repr(args.name) in d.message)
    if already:
        print(f"planner {args.name!r} is already active")
        return 0
    if refusal is not None:
        print(f"the bridge refused: {refusal.message}")
        return 1
    if not ok or state is None or state.handover is None:
        pending = f", pending: {state.pending_owner!r}" if state is not None and state.pending_owner else ""
        owner = state.owner if state is not None else "unknown (no robot state seen)"
        print(f"switch to {args.name!r} not done within {args.timeout:.0f} s: active is {owner}{pending}; "
              f"see diag/bridge (is the planner running? `nwr status`)")
        return 1
    h = state.handover
    print(f"active planner: {h.owner!r} (was {h.previous!r}); "
          f"switched {(h.switched_ns - h.requested_ns) / 1e6:.1f} ms after the request, "
          f"first command {(h.first_command_ns - h.requested_ns) / 1e6:.1f} ms after it "
          f"({(h.first_command_ns - h.requested_ns) / 1e9 / CYCLE_S:.1f} control cycles)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("switch", help="make another running planner the active one",
                       description="Ask the bridge to follow planner NAME. The switch waits for a reflex in progress "
                                   "and its return to end, then happens between two commands.")
    p.add_argument("name", help="planner name (as given with `nwr run planner --name`)")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the switch (default 10)")
    p.set_defaults(handler=_run)
