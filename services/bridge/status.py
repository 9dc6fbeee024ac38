"""What every concern of the bridge's supervisor shares, and the status it derives from it.

:class:`Status` is the base of :class:`~.core.BridgeCore`: the envelope, the
tracker (:class:`~.tracking.Tracker`: the commanded joint state, the command
it follows, the controlled stop), the active planner and whether it is alive,
the phase and seq of the command followed, when the last command, skin
sample and pain message came, the blind pads, the backend's fault and the
bridge's own (``state_implausible``), the status, and the events to report.
:meth:`Status._evaluate` sets the status from them (``ok``, ``idle``, or why
the arm is held) and starts the tracker's controlled stop on entering a
stopping one; every input that changes them ends with it.

The concerns build on it, each in its own module and each a layer of the
supervisor's class: :mod:`.safety`, :mod:`.skin`, :mod:`.switching`,
:mod:`.faults`, :mod:`.commands`, then :mod:`.core`.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from nwr.common import messages as m
from nwr.services.bridge.cartesian import CartesianLimiter
from nwr.services.bridge.checks import Event
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.tracking import Tracker

# Below this speed (rad/s) on every joint a stopped arm counts as at rest.
REST_SPEED = 1e-6

BlindPolicy = Literal["reduced", "stop"]
# Statuses during which the bridge brings the arm to rest and holds it.
STOPPING_STATUSES = frozenset({"stale_command", "stale_skin", "planner_lost", "stopped"})


class Status:
    """The supervisor's shared state, and the status it derives from it."""

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, *, active: str, n_pads: int,
                 command_timeout_s: float, skin_timeout_s: float, period_s: float, limiter: CartesianLimiter | None,
                 pad_names: tuple[str, ...], blind_pads: BlindPolicy) -> None:
        self.env = env
        self.active = active
        self.n_pads = n_pads
        self.command_timeout_ns = round(command_timeout_s * 1e9)
        self.skin_timeout_ns = round(skin_timeout_s * 1e9)
        # The commanded joint state, the command it follows, the controlled stop.
        self.tracker = Tracker(env, q0, now_ns, period_s=period_s, limiter=limiter)
        # The pads blind now (:mod:`.skin`), named in the reports, and what a blind pad does to the motion.
        self.pad_names = pad_names if len(pad_names) == n_pads else tuple(str(i) for i in range(n_pads))
        self.blind_policy: BlindPolicy = blind_pads
        self.blind: frozenset[int] = frozenset()
        # The command being followed: its phase, and the last one accepted.
        self.phase: m.Mode = "TASK"
        self.last_seq: int | None = None
        self.last_command_ns = 0
        # Inputs.
        self.planner_alive = False
        self.planner_seen = False
        self.last_skin_ns: int | None = None
        # The planner acts on skin/pain, not on skin/pressure: once pain
        # messages flow, their staleness (a dead gain estimator) stops the task too.
        self.last_pain_ns: int | None = None
        self.fault: m.RobotStatus | None = None
        self.fault_detail = ""
        # The bridge's own fault, state_implausible (:mod:`.faults`): why the reported state is not believed.
        self.implausible = ""
        # Output state.
        self.status: m.RobotStatus = "idle"
        self.detail = "waiting for the first command"
        self.shutdown = False
        self.events: list[Event] = []
        self.publish_now = False  # something others must learn at once (a switch)

    def _evaluate(self, now_ns: int) -> None:
        """Set the status from the inputs; start a controlled stop on entering a stopping one."""
        pain_stale = self.last_pain_ns is not None and now_ns - self.last_pain_ns > self.skin_timeout_ns
        skin_stale = self.last_skin_ns is None or now_ns - self.last_skin_ns > self.skin_timeout_ns or pain_stale
        status: m.RobotStatus
        if self.fault is not None:
            status, detail = self.fault, self.fault_detail
        elif self.implausible:
            status, detail = "state_implausible", self.implausible
        elif self.shutdown:
            status, detail = "stopped", self.detail or "stopped"
        elif not self.planner_alive and self.planner_seen:
            status, detail = "planner_lost", f"planner {self.active!r} lost its liveliness token"
        elif not self.planner_alive or self.last_command_ns == 0:
            status = "idle"
            detail = (f"waiting for planner {self.active!r}" if not self.planner_alive
                      else "waiting for the first command")
        elif now_ns - self.last_command_ns - self.tracker.covered_ns > self.command_timeout_ns:
            status = "stale_command"
            detail = f"no command for more than {self.command_timeout_ns / 1e6:.0f} ms"
            if self.tracker.covered_ns:
                detail += f" past the {self.tracker.covered_ns / 1e6:.0f} ms the last one planned ahead"
        elif (skin_stale or (self.blind and self.blind_policy == "stop")) and self.phase != "REFLEX":
            status = "stale_skin"
            if not skin_stale:
                pads = ", ".join(self.pad_names[i] for i in sorted(self.blind))
                age = f"pad(s) {pads} blind (bridge.blind_pads = stop)"
            elif self.last_skin_ns is None:
                age = "no skin data yet"
            elif pain_stale and self.last_pain_ns is not None and now_ns - self.last_skin_ns <= self.skin_timeout_ns:
                age = f"pain data {(now_ns - self.last_pain_ns) / 1e6:.0f} ms old (is the gain estimator running?)"
            else:
                age = f"skin data {(now_ns - self.last_skin_ns) / 1e6:.0f} ms old"
            detail = f"{age} (limit {self.skin_timeout_ns / 1e6:.0f} ms): {self.phase} motion held"
        else:
            status, detail = "ok", ""
        if status != self.status:
            tracker = self.tracker
            moving = bool(np.any(np.abs(tracker.dq) > REST_SPEED))
            if status in STOPPING_STATUSES or (status == "idle" and moving):
                failed = tracker.begin_stop(now_ns)
                if failed is not None:
                    self.events.append(failed)
                if status != "stopped":
                    # Before the first skin sample the skin is starting (the gateway starts last): not a fault.
                    starting = status == "stale_skin" and self.last_skin_ns is None
                    self.events.append(Event(
                        "info" if starting else "warning", status,
                        f"{detail}: decelerating to rest within the limits (stopping distance up to "
                        f"{float(np.max(np.abs(tracker.stop_distance))):.4f} rad, {tracker.stop_time_s:.3f} s) "
                        "and holding",
                    ))
            elif status == "ok" and tracker.stop is not None:
                tracker.stop = None  # follow again, from wherever the stop has brought the arm
                tracker.begin_rejoin()  # ... and never faster than the stream itself: no catch-up
                if self.status != "idle":
                    self.events.append(Event("info", "resumed", f"following {self.active!r} again after {self.status}"))
        self.status, self.detail = status, detail
