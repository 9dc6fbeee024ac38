"""Robot bridge core: the supervisor, pure.

Nothing here imports Zenoh or reads a clock: every input carries its time
(``now_ns``), so tests and replays drive it exactly.

:class:`BridgeCore` is the supervisor: every command passes the command check
(:func:`~nwr.services.bridge.checks.check_command`) against the envelope
(:class:`~nwr.services.bridge.envelope.Envelope`), and the accepted ones are
followed by its tracker (:class:`~nwr.services.bridge.tracking.Tracker`),
which gives one setpoint per control cycle within the envelope. The
supervisor watches the inputs (commands, skin, the active planner's
liveliness, the backend's faults), switches the active planner, and, when it
can no longer trust its inputs, has the tracker bring the arm to rest with a
jerk-limited (ruckig) stop whose distance and duration it reports.

:class:`BridgeCore` is built in layers, one concern each:
:class:`.status.Status` (the shared state, and the status derived from it)
<- :class:`.safety.SafetyModes` (the normal or reduced Cartesian limits) <-
:class:`.skin.SkinValidity` (fresh skin, blind pads, the newest contact) <-
:class:`.switching.Switching` (the active planner's liveliness, switches) <-
:class:`.faults.Faults` (the backend's faults, the reported state's check,
shutdown) <- :class:`.commands.Commands` (command acceptance) <-
:class:`BridgeCore` (the control cycle and the robot state). A layer calls
only its own methods and those of the layers below it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from nwr.common import messages as m
from nwr.common.errors import ConfigError
from nwr.services.bridge.cartesian import CartesianLimiter, Limits
from nwr.services.bridge.checks import Event, StateBounds
from nwr.services.bridge.commands import Commands, Verdict
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.faults import CLEAR_S
from nwr.services.bridge.skin import BLIND_REPORT_S, pad_validity
from nwr.services.bridge.status import REST_SPEED, BlindPolicy

# The names the wiring, the backends and the tests import from here, wherever they are defined.
__all__ = ["BLIND_REPORT_S", "CLEAR_S", "BlindPolicy", "BridgeCore", "Setpoint", "SetpointMode", "Verdict", "at_rest",
           "pad_validity"]

# A control step never integrates more than this, s: after a stall of the
# bridge's loop the arm is not teleported along a long step.
MAX_STEP_S = 0.05

SetpointMode = Literal["position", "velocity", "hold"]


@dataclass(frozen=True)
class Setpoint:
    """What the backend gets for one control cycle."""

    mode: SetpointMode  # "hold": the arm is at rest (backends end their stream)
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    h: float = 0.0  # the step it was computed over, s


class BridgeCore(Commands):
    """The bridge's supervisor: commands and inputs in, one setpoint per cycle out."""

    def __init__(
        self,
        env: Envelope,
        q0: np.ndarray,
        now_ns: int,
        *,
        active: str,
        n_pads: int,
        command_timeout_s: float = 0.02,
        skin_timeout_s: float = 0.12,
        seq_restart_gap: int = 500,
        period_s: float = 0.002,
        limiter: CartesianLimiter | None = None,
        reduced: Limits | None = None,
        task_range: tuple[np.ndarray, np.ndarray] | None = None,
        task_peak_m_s: float = 0.0,
        physical: tuple[np.ndarray, np.ndarray] | None = None,
        state_bounds: StateBounds | None = None,
        lag_s: float = 0.0,
        pad_names: tuple[str, ...] = (),
        blind_pad_s: float = 0.2,
        blind_pads: BlindPolicy = "reduced",
        entry_pads: tuple[int, ...] = (),
    ) -> None:
        """``physical``: the robot description's joint speed and acceleration limits (the reports are checked
        against them; default: the envelope's); ``state_bounds``: how far a report may stray
        (:class:`~nwr.services.bridge.checks.StateCheck`); ``lag_s``: the backend's following lag (its servo's
        time constant; 0 for the simulated arm); ``pad_names``: for the reports; ``blind_pad_s``: a pad invalid
        this long is blind; ``blind_pads``: what a blind pad does to the motion (``reduced``: the reduced
        Cartesian limits while any pad is blind; ``stop``: the skin counts as stale, as with no skin data);
        ``entry_pads``: on a taxel skin, each taxel's pad (a sample has one entry per taxel)."""
        q0 = np.asarray(q0, dtype=float)
        if q0.shape != (env.n,):
            raise ConfigError(f"initial pose has {q0.size} joints, the robot has {env.n}")
        if np.any(q0 < env.q_min) or np.any(q0 > env.q_max):
            raise ConfigError(f"initial pose {q0.tolist()} is outside the joint limits of the envelope")
        super().__init__(
            env, q0, now_ns, active=active, n_pads=n_pads, command_timeout_s=command_timeout_s,
            skin_timeout_s=skin_timeout_s, seq_restart_gap=seq_restart_gap, period_s=period_s, limiter=limiter,
            reduced=reduced, task_range=task_range, task_peak_m_s=task_peak_m_s, physical=physical,
            state_bounds=state_bounds, lag_s=lag_s, pad_names=pad_names, blind_pad_s=blind_pad_s,
            blind_pads=blind_pads, entry_pads=entry_pads,
        )
        self.last_step_ns = now_ns

    # -- the control cycle -----------------------------------------------------------
    def step(self, now_ns: int) -> Setpoint:
        """One control cycle at ``now_ns``: the setpoint within the envelope."""
        h = min(max((now_ns - self.last_step_ns) / 1e9, 0.0), MAX_STEP_S)
        self.last_step_ns = max(now_ns, self.last_step_ns)
        self._evaluate(now_ns)
        self._maybe_switch(now_ns)  # a pending switch while the outgoing planner is not commanding
        if h <= 0.0:
            return self._setpoint(0.0)
        tracker = self.tracker
        q_before = tracker.q.copy()
        if self.fault is not None or self.implausible:
            tracker.hold()
        elif tracker.stop is not None:
            tracker.stop_step(now_ns, h)
        elif self.status == "ok":
            clipped = tracker.track(h, self.last_step_ns, self.active)
            if clipped is not None:
                self._report_clip(clipped)
            if self.joining and self.handover is not None and self.handover.first_command_ns and not tracker.rejoining:
                self.joining = False  # the arm follows the incoming planner's stream
        else:
            tracker.hold()
        if not self.joining:  # the first motion of a handover does not widen where it may go
            self.reach.add(tracker.q)
        setpoint = self._setpoint(h)
        self.claims.command(setpoint.mode, q_before, setpoint.q, setpoint.dq, now_ns)
        return setpoint

    def _setpoint(self, h: float) -> Setpoint:
        tracker = self.tracker
        joints = tracker.joints  # (read once: the tracker's attributes are its parts')
        at_rest = not (np.abs(joints.dq) > REST_SPEED).any()
        stopped = tracker.stop is None or tracker.stop.done
        if self.fault is not None or self.implausible or (self.status != "ok" and stopped and at_rest):
            mode: SetpointMode = "hold"
        elif tracker.mode == "velocity":
            mode = "velocity"
        else:
            mode = "position"
        return Setpoint(mode, joints.q.copy(), joints.dq.copy(), joints.ddq.copy(), h)

    # -- output -----------------------------------------------------------------------
    def state(self, seq: int, now_ns: int, q: np.ndarray, dq: np.ndarray, backend: str,
              pose_stale: bool = False) -> m.RobotState:
        """The robot state to publish, with the measured joints ``q`` and ``dq`` (``pose_stale``: the last known)."""
        self.publish_now = False
        tracker = self.tracker
        return m.RobotState(
            seq=seq, stamp_ns=now_ns, q=q.tolist(), dq=dq.tolist(), status=self.status, owner=self.active,
            backend=backend, command_mode=tracker.mode, reflex_seq=self.reflex_seq, accepted=self.accepted,
            accepted_ns=self.accepted_ns, rejected=self.rejected, clipped=self.clipped,
            stopping=tracker.stop is not None and not tracker.stop.done, stop_distance=tracker.stop_distance.tolist(),
            stop_time_s=tracker.stop_time_s, skin_age_s=min(self.skin_age_s(now_ns), 1e9), detail=self.detail,
            pending_owner=self.pending.name if self.pending is not None else "", handover=self.handover,
            safety_mode=self.safety_mode, limited=tracker.limited,
            phase="REFLEX" if tracker.withdrawal else self.phase, pose_stale=pose_stale,
        )

    def release(self) -> None:
        """Drop the trajectory generator at shutdown (its objects must not outlive their module)."""
        self.tracker.release()

    def drain_events(self) -> list[Event]:
        events, self.events = self.events, []
        return events


def at_rest(dq: np.ndarray) -> bool:
    return not bool((np.abs(dq) > REST_SPEED).any())
