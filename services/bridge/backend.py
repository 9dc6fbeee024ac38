"""The robot behind one small interface, and the simulated arm.

Every backend (``sim`` here, ``ur_rtde`` in :mod:`nwr.services.bridge.backends.ur_rtde`)
does the same four things, lerobot-style:

- ``connect()`` / ``disconnect()``: take and release the robot (disconnect
  leaves it at rest and is safe to call twice);
- ``get_observation()``: the measured joints and any fault of the robot;
- ``send_action(setpoint)``: pass a setpoint through :func:`guard` (the pure
  last check: finite, within the joint limits, a step the speed limit allows)
  and send it; returns what was really sent;
- ``pacer(rate_hz)``: the object whose ``sleep(stop)`` paces the control
  loop (the UR's own ``initPeriod`` / ``waitPeriod`` for ur_rtde).
"""

from __future__ import annotations

import logging
import math
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from nwr.common import messages as m
from nwr.common.errors import SafetyError
from nwr.common.pacing import Rate
from nwr.common.taxels import TaxelSkin
from nwr.services.bridge.core import Setpoint
from nwr.services.bridge.envelope import Envelope

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Observation:
    """The robot as measured, and its fault if it has one."""

    q: np.ndarray
    dq: np.ndarray
    fault: m.RobotStatus | None = None  # protective_stop, emergency_stop, script_not_running, robot_reflex, ...
    detail: str = ""
    stamp_s: float | None = None  # the controller's own time of the report, s (None: the bridge's clock times it)
    tau_ext: np.ndarray | None = None  # the controller's estimated external torque per joint, N m (None: it has none)


class Pacer(Protocol):
    ticks: int
    starting: bool  # the bridge has no skin yet: overruns are start-up, not warned about

    def sleep(self, stop: threading.Event | None = None) -> bool: ...

    def summary(self) -> str: ...


def guard(env: Envelope, previous: np.ndarray, setpoint: Setpoint, dt: float) -> tuple[Setpoint, str | None]:
    """The last check before a backend: what may really be sent, and why it differs.

    The core already keeps every setpoint within the envelope, so this never
    binds unless the core has a bug; it exists so that no bug can reach the
    arm. Non-finite setpoints raise :class:`SafetyError` (nothing sensible can
    be sent). Position setpoints are clipped into the joint limits and to the
    step the speed limit allows since ``previous`` (over the setpoint's own
    step ``h``, at least ``dt``); velocity setpoints to the speed limits.
    Per joint, in floats (every 2 ms cycle: numpy's per-call overhead would
    cost more than the checks).
    """
    q_in, dq_in = setpoint.q.tolist(), setpoint.dq.tolist()
    if not (all(map(math.isfinite, q_in)) and all(map(math.isfinite, dq_in))):
        raise SafetyError(f"non-finite setpoint q={q_in} dq={dq_in}: not sent")
    span = max(setpoint.h, dt)
    position = setpoint.mode == "position"
    prev = previous.tolist()
    q_out, dq_out = list(q_in), list(dq_in)
    worst, worst_i, worst_step = 0.0, -1, 0.0
    for i, (q_min, q_max, v_max, _a_max, _k) in enumerate(env.per_joint):
        step = v_max * span * 1.5 + 1e-9  # half a cycle of timing slack
        dq = min(max(dq_in[i], -v_max), v_max)
        q = min(max(min(max(q_in[i], prev[i] - step), prev[i] + step), q_min), q_max) if position else q_in[i]
        off = abs(q - q_in[i]) + abs(dq - dq_in[i])
        if off > worst:
            worst, worst_i, worst_step = off, i, step
        q_out[i], dq_out[i] = q, dq
    if worst_i < 0:
        return setpoint, None
    i = worst_i
    why = (f"{setpoint.mode} setpoint of joint {env.joints[i]} (q {q_in[i]:.5f} rad, dq {dq_in[i]:.4f} "
           f"rad/s) outside the envelope (q in [{env.q_min[i]:.3f}, {env.q_max[i]:.3f}], step {worst_step:.5f} rad "
           f"from {prev[i]:.5f}, v_max {env.v_max[i]:.3f} rad/s): clipped")
    return Setpoint(setpoint.mode, np.array(q_out), np.array(dq_out), setpoint.ddq, setpoint.h), why


class Backend(ABC):
    """One robot: simulated or real."""

    name: str = "?"
    # The following lag of the arm behind position setpoints (a first-order time constant), s: the bridge's
    # model of where the arm should be (checks.StateCheck). The simulated arm is where its setpoint put it.
    lag_s: float = 0.0
    # A world the bridge hosts (physics): it takes the touch script's touches (on_touch) and advances each cycle.
    touched: bool = False

    def __init__(self, env: Envelope, dt: float) -> None:
        self.env = env
        self.dt = dt
        self.guarded = 0  # setpoints the guard had to change (a core bug if ever > 0)
        self.last_sent: np.ndarray | None = None

    @abstractmethod
    def connect(self) -> None: ...

    @abstractmethod
    def disconnect(self) -> None: ...

    @abstractmethod
    def get_observation(self) -> Observation: ...

    def send_action(self, setpoint: Setpoint) -> Setpoint:
        """Guard the setpoint and send it; returns what was really sent."""
        previous = self.last_sent if self.last_sent is not None else self.get_observation().q
        sent, why = guard(self.env, previous, setpoint, self.dt)
        if why is not None:
            self.guarded += 1
            log.error("%s (this is a bug of the bridge core: please report it)", why)
        self._send(sent)
        self.last_sent = sent.q
        return sent

    @abstractmethod
    def _send(self, setpoint: Setpoint) -> None: ...

    def advance(self, now_ns: int) -> list[tuple[str, Any]]:
        """A hosted world steps up to the bridge time ``now_ns`` (each cycle, before the observation); what it
        published meanwhile, (key, message) pairs. An arm that moves on its own: nothing."""
        return []

    def on_touch(self, touch: m.SkinTouch, now_ns: int) -> str | None:
        """A touch of the touch script reaches a hosted world at ``now_ns``; why it was refused, or None."""
        return f"the {self.name} backend hosts no world: touch {touch.seq} ignored"

    def use_skin(self, skin: TaxelSkin) -> None:
        """The profile's skin is this taxel skin (before the first :meth:`advance`): a hosted world publishes its
        samples; an arm whose skin is not the bridge's (every other backend) has nothing to do."""
        return None

    def wind_down(self, timeout_s: float) -> bool:
        """The control loop has ended (the arm stopped, :meth:`disconnect` to come): wait (at most ``timeout_s``)
        until what was sent has reached the robot and been answered (a backend that sends from a thread of its
        own), and keep a controller that watches the bridge fed until :meth:`disconnect`; whether everything
        was answered. The bridge's last state comes after."""
        return True

    def resync(self, q: np.ndarray) -> None:
        """The core restarted from the measured pose ``q`` (after a fault)."""
        self.last_sent = np.asarray(q, dtype=float).copy()

    def pacer(self, rate_hz: float) -> Pacer:
        return Rate(rate_hz, "bridge", starting=True)


class SimBackend(Backend):
    """An ideal arm: it is wherever the last setpoint put it."""

    name = "sim"

    def __init__(self, env: Envelope, dt: float, q0: np.ndarray) -> None:
        super().__init__(env, dt)
        self.q = np.asarray(q0, dtype=float).copy()
        self.dq = np.zeros_like(self.q)
        self.connected = False
        self.holding = True

    def connect(self) -> None:
        self.connected = True

    def disconnect(self) -> None:
        self.dq[:] = 0.0
        self.connected = False

    def get_observation(self) -> Observation:
        return Observation(self.q.copy(), self.dq.copy())

    def _send(self, setpoint: Setpoint) -> None:
        self.q = setpoint.q.copy()
        self.dq = setpoint.dq.copy() if setpoint.mode != "hold" else np.zeros_like(self.q)
        self.holding = setpoint.mode == "hold"
