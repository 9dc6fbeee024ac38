"""``nwr safety reduced|normal``: switch the bridge's Cartesian limits at runtime (a UR's "reduced mode").

Puts a :class:`~nwr.common.messages.SafetyModeRequest` on ``control/safety``
(the LAN deployment lets only the operator's certificate put there); the
bridge switches at once and says so on ``robot/state`` (``safety_mode``).
The command waits for that. Without a mode it prints the mode in force.
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


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    limits = profile.bridge.reduced if args.mode == "reduced" else profile.bridge.limits
    done = threading.Event()
    seen: dict[str, m.RobotState] = {}

    def on_state(state: m.RobotState) -> None:
        seen["last"] = state
        if state.safety_mode == args.mode:
            done.set()

    with Node("safety", profile.robot.name, profile.zenoh, token=False) as node:
        node.subscribe(keys.ROBOT_STATE, on_state)
        time.sleep(0.5)  # let the session connect and the subscriber see a state
        if args.mode is None:
            last = seen.get("last")
            if last is None:
                print("no robot state seen: is the bridge running? (`nwr status`)")
                return 1
            print(f"safety mode: {last.safety_mode} ({last.limited} control cycles scaled by the Cartesian limits)")
            return 0
        done.clear()
        node.publisher(keys.CONTROL_SAFETY)(m.SafetyModeRequest(
            seq=0, stamp_ns=node.clock.now_ns(), mode=args.mode,
            requested_by=f"{getpass.getuser()}@{socket.gethostname()}"))
        if not done.wait(args.timeout):
            state = seen.get("last")
            mode = state.safety_mode if state is not None else "unknown (no robot state seen)"
            print(f"the bridge did not switch to {args.mode} within {args.timeout:.0f} s: it is in {mode}; "
                  "see diag/bridge (may this certificate put on control/safety?)")
            return 1
    print(f"safety mode: {args.mode}: every point at most {limits.speed_m_s} m/s "
          f"({limits.withdrawal_speed_m_s} m/s withdrawing), momentum at most {limits.momentum_kg_m_s} kg m/s")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("safety", help="switch the bridge's Cartesian limits: reduced or normal",
                       description="Switch the bridge to the profile's reduced Cartesian limits ([bridge.reduced]) "
                                   "or back to the normal ones ([bridge.limits]); without MODE, print the mode.")
    p.add_argument("mode", nargs="?", choices=("reduced", "normal"), help="the limits to switch to")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the bridge (default 5)")
    p.set_defaults(handler=_run)
