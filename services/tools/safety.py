"""``nwr safety reduced|normal``: switch the bridge's Cartesian limits at runtime (a UR's "reduced mode").

Puts a :class:`~nwr.common.messages.SafetyModeRequest` on ``control/safety``
(the LAN deployment lets only the operator's certificate put there); the
bridge switches at once and says so on ``robot/state`` (``safety_mode``).
The command waits for that. Without a mode it prints the mode in force.
"""

from __future__ import annotations

import argparse

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.node import Node
from nwr.services.profile import profile_for
from nwr.services.tools.switch import ask_the_bridge, requested_by


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)

    def request(last: m.RobotState | None, node: Node) -> m.SafetyModeRequest | None:
        if args.mode is None:
            return None  # only say which mode is in force
        return m.SafetyModeRequest(seq=0, stamp_ns=node.clock.now_ns(), mode=args.mode, requested_by=requested_by())

    ok, state, _ = ask_the_bridge(args, "safety", keys.CONTROL_SAFETY, request, lambda s: s.safety_mode == args.mode)
    if args.mode is None:
        if state is None:
            print("no robot state seen: is the bridge running? (`nwr status`)")
            return 1
        print(f"safety mode: {state.safety_mode} ({state.limited} control cycles scaled by the Cartesian limits)")
        return 0
    if not ok:
        mode = state.safety_mode if state is not None else "unknown (no robot state seen)"
        print(f"the bridge did not switch to {args.mode} within {args.timeout:.0f} s: it is in {mode}; "
              "see diag/bridge (may this certificate put on control/safety?)")
        return 1
    limits = profile.bridge.reduced if args.mode == "reduced" else profile.bridge.limits
    print(f"safety mode: {args.mode}: {limits.describe()}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("safety", help="switch the bridge's Cartesian limits: reduced or normal",
                       description="Switch the bridge to the profile's reduced Cartesian limits ([bridge.reduced]) "
                                   "or back to the normal ones ([bridge.limits]); without MODE, print the mode.")
    p.add_argument("mode", nargs="?", choices=("reduced", "normal"), help="the limits to switch to")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the bridge (default 5)")
    p.set_defaults(handler=_run)
