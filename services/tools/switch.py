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

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import profile_for
from nwr.common.node import Node

CYCLE_S = 0.002


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    done = threading.Event()
    seen: dict[str, m.RobotState] = {}

    def on_state(state: m.RobotState) -> None:
        seen["last"] = state
        if state.handover is not None and state.handover.owner == args.name and state.handover.first_command_ns:
            done.set()

    with Node("switch", profile.robot.name, profile.zenoh, token=False) as node:
        node.subscribe(keys.ROBOT_STATE, on_state)
        publish = node.publisher(keys.CONTROL_ACTIVE)
        time.sleep(0.5)  # let the session connect and the subscriber see a state
        last = seen.get("last")
        if last is not None and last.owner == args.name:
            print(f"planner {args.name!r} is already active")
            return 0
        publish(m.SwitchRequest(seq=0, stamp_ns=node.clock.now_ns(), name=args.name,
                                requested_by=f"{getpass.getuser()}@{socket.gethostname()}"))
        if not done.wait(args.timeout):
            state = seen.get("last")
            pending = f", pending: {state.pending_owner!r}" if state is not None and state.pending_owner else ""
            owner = state.owner if state is not None else "unknown (no robot state seen)"
            print(f"switch to {args.name!r} not done within {args.timeout:.0f} s: active is {owner}{pending}; "
                  f"see diag/bridge (is the planner running? `nwr status`)")
            return 1
        h = seen["last"].handover
        assert h is not None
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
