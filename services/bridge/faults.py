"""Faults: the backend's (a protective stop, ...), the bridge's own disbelief of the reported state, shutdown.

The controller stops the arm by itself in a fault; the bridge takes the
measured pose as its own, and waits for fresh commands once the fault is
cleared. The reported joint state is a claim, checked
(:class:`~.checks.StateCheck`) against the commands and physics before
anything adopts it: a report not believed is the bridge's own fault,
``state_implausible``, which stops the arm (the backend's controlled stop)
and holds it until the reports have shown it at rest where it was stopped
for :data:`CLEAR_S`. A shutdown stops the arm for good (a controlled stop,
then hold).

:class:`Faults` owns the check of the reports and, while they are not
believed, where the arm should be held and since when the reports agree.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.services.bridge.checks import Event, StateBounds, StateCheck
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.switching import Switching

# A state_implausible fault clears once the reports have shown the arm at rest (every joint slower than
# CLEAR_SPEED_RAD_S, rad/s), where the bridge stopped it, for this long, s.
CLEAR_S = 1.0
CLEAR_SPEED_RAD_S = 0.01


class Faults(Switching):
    """The backend's faults, the check of the reported joint state, and the stop for good."""

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, *, period_s: float,
                 physical: tuple[np.ndarray, np.ndarray] | None, state_bounds: StateBounds | None, lag_s: float,
                 **below: Any) -> None:
        super().__init__(env, q0, now_ns, period_s=period_s, **below)
        # The reported joint state is a claim (StateCheck): a report not believed is the bridge's own fault,
        # state_implausible (its reason: ``implausible``), which holds the arm until the reports show it at rest
        # where the bridge stopped it (within ``hold_margin``) for CLEAR_S.
        v_phys, a_phys = physical if physical is not None else (env.v_max, env.a_max)
        self.claims = StateCheck(env.joints, v_phys, a_phys, q0, now_ns, bounds=state_bounds, period_s=period_s,
                                 tau_s=lag_s)
        self.lag_s = lag_s
        self.hold_q = q0.copy()
        self.hold_margin = np.zeros(env.n)
        self.plausible_since: int | None = None

    def on_fault(self, fault: m.RobotStatus | None, detail: str, q: np.ndarray, now_ns: int) -> None:
        """The backend's fault (protective stop, ...) or None once it is cleared.

        The controller stops the arm by itself in a fault; the core takes the
        measured pose as its own and waits for fresh commands afterwards.
        """
        if fault == self.fault:
            return
        self.tracker.restart(q)
        self.claims.reset(q, now_ns)
        self.last_command_ns = 0
        if fault is None:
            self.events.append(Event("info", "robot_recovered",
                                     f"robot recovered from {self.fault}: waiting for commands", every_s=0.0))
        else:
            # a change of the controller's state: each one is heard, however soon after the last of its code
            # (a program stopped 0.3 s after an emergency stop's restart, say)
            self.events.append(Event("error", fault, f"robot in {fault}: {detail}", every_s=0.0))
        self.fault = fault
        self.fault_detail = detail
        self._evaluate(now_ns)

    def observe(self, q: np.ndarray, dq: np.ndarray, now_ns: int, stamp_s: float | None = None) -> bool:
        """The reported joint state: checked (:class:`StateCheck`) before anything adopts it.

        A report believed is passed to the tracker (in velocity mode the integrated command follows it); one not
        believed stops the arm (``state_implausible``: the backend's own controlled stop) and holds it until the
        reports show it at rest where the bridge stopped it for CLEAR_S. True: that fault has just cleared and
        the bridge starts over from ``q`` (the backend must resync). ``stamp_s``: the controller's time of the
        report, if it has one (how far apart two reports are, whenever they arrive).
        """
        if self.fault is not None:
            return False
        if self.implausible:
            return self._maybe_clear(np.asarray(q, dtype=float), np.asarray(dq, dtype=float), now_ns)
        why = self.claims.observe(q, dq, now_ns, stamp_s)
        if why is not None:
            self._not_believed(why, now_ns)
            return False
        self.tracker.observe(q)
        return False

    def _not_believed(self, why: str, now_ns: int) -> None:
        claims = self.claims
        self.implausible = why
        self.plausible_since = None
        # Where the arm should come to rest: the backend's controlled stop from the commanded speed (at the
        # slowest joint's a_max, as ur_rtde's servoStop / speedStop), on top of the following error allowed.
        v = claims.speed
        a_stop = float(np.min(self.env.a_max))
        b = claims.bounds
        self.hold_q = claims.expected.copy()
        self.hold_margin = b.error_rad + (b.lag_s + self.lag_s) * v + v * v / (2.0 * a_stop)
        self.events.append(Event("error", "state_implausible",
                                 f"the robot's reported state is not believed: {why}: stopping the arm (the "
                                 "controller's own stop) and holding it until the reports show it at rest where "
                                 "it was stopped", every_s=0.0))
        self._evaluate(now_ns)

    def _maybe_clear(self, q: np.ndarray, dq: np.ndarray, now_ns: int) -> bool:
        """While ``state_implausible``: clear it once the reports have shown the arm at rest near where it was
        stopped for CLEAR_S."""
        ok = (q.shape == self.hold_q.shape and dq.shape == self.hold_q.shape and bool(np.isfinite(q).all())
              and bool(np.isfinite(dq).all()) and not (np.abs(dq) > CLEAR_SPEED_RAD_S).any()
              and not (np.abs(q - self.hold_q) > self.hold_margin).any())
        if not ok:
            self.plausible_since = None
            return False
        if self.plausible_since is None:
            self.plausible_since = now_ns
        if now_ns - self.plausible_since < round(CLEAR_S * 1e9):
            return False
        self.events.append(Event("info", "state_plausible",
                                 f"the robot's reported state is believed again (at rest, within "
                                 f"{float(np.max(np.abs(q - self.hold_q))):.4f} rad of where it was stopped, for "
                                 f"{CLEAR_S:g} s): waiting for commands", every_s=0.0))
        self.implausible = ""
        self.plausible_since = None
        self.tracker.restart(q)
        self.claims.reset(q, now_ns)
        self.last_command_ns = 0
        self._evaluate(now_ns)
        return True

    def request_stop(self, now_ns: int, reason: str) -> None:
        """Stop for good (shutdown): a controlled stop, then hold."""
        self.shutdown = True
        self.detail = reason
        self._evaluate(now_ns)
