"""A contact from the arm's own joint torques: the controller's estimated external torque (a Franka's
``tau_ext_hat_filtered``, ``RobotState.tau_ext``), beside the skin.

Pure: numbers in, a :class:`TorqueContact` out; the robot model (pinocchio,
:class:`~nwr.common.robot.RobotModel`) gives gravity and the pads' Jacobians.

The residual ``r``, the external torque on each joint, N m, after a
baseline model and a learnt offset:

- ``baseline = "none"``, ``r = tau_ext - offset``: a controller whose estimate
  is already external (a real Franka: its dynamics model removed, about zero
  at rest);
- ``baseline = "gravity"``, ``r = g(q) - tau_ext - offset``: a controller that
  reports the joint torque it applies (franky-sim 1.0.4 reports exactly its
  applied torque, ``tau_J``, as ``tau_ext_hat_filtered``: 22 N m on joint 4
  at the FR3's home is the arm's weight, not a push). The arm at rest,
  ``tau = g(q) - tau_push``; ``g`` the URDF's gravity torques (pinocchio);
- ``offset``, the no-contact residual learnt while the arm is untouched:
  the first ``tare_samples`` states after a start (or a gap in the state),
  then followed slowly (``follow``) while no contact is detected, never
  during one (so a sustained push does not become the baseline, as the skin
  gateway's pad baseline does not follow a press).

The detection: a per-joint threshold with hysteresis. A contact starts when
``|r_i| >= on_nm[i]`` on any joint, and ends once ``|r_i| < off_nm[i]`` on
every joint. Its onset is the first state over the threshold.

What the residual can say beyond onset. A push of ``f`` newtons at a pad's
point along minus its outward normal ``n`` puts ``tau = -J_p(q)^T n f`` on
the joints (``J_p`` the point's linear Jacobian). For each pad the least
squares ``f`` and the share of the residual that one push there leaves
unexplained give: the likeliest pad (the smallest unexplained share among
pads with ``f > 0``), its force estimate, N, and the share (0: the residual is
exactly such a push; near 1: no pad explains it). The joints distal to the
pushed link carry no torque from it, so pads on one link, or on links whose
Jacobians are alike at that pose, are told apart poorly: the share says how
well. A push on the base or the first link's axis is invisible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.common.robot import Pad, RobotModel

BASELINES = ("none", "gravity", "dynamics")
# Two states further apart than this give no acceleration (a gap: the arm taken as unaccelerated), s.
MAX_DIFF_S = 0.1


@dataclass(frozen=True)
class TorqueContact:
    """One robot state's verdict."""

    detected: bool
    onset: bool  # this state started the contact
    residual_nm: tuple[float, ...]  # r per joint, N m (zeros while taring)
    joint: int  # the joint whose |r_i| / on_nm[i] is largest (-1: none yet)
    ratio: float  # that largest |r_i| / on_nm[i]
    pad: int = -1  # the likeliest pad (-1: none, or not detected)
    force_n: float = 0.0  # its force estimate along minus the pad's normal, N
    unexplained: float = 1.0  # the share of |r| a push at that pad leaves unexplained (0-1)
    tared: bool = True  # False while the no-contact offset is still being learnt


@dataclass
class TorqueDetector:
    """Per-joint thresholds with hysteresis on the external-torque residual (the module's docstring)."""

    model: RobotModel
    on_nm: np.ndarray
    off_nm: np.ndarray
    baseline: str = "gravity"
    tare_samples: int = 25
    follow: float = 0.002  # the offset's share of each no-contact residual (an exponential average)
    _offset: np.ndarray = field(init=False)
    _tare_sum: np.ndarray = field(init=False)
    _tared: int = field(init=False, default=0)
    _active: bool = field(init=False, default=False)
    _last_dq: np.ndarray = field(init=False)
    _last_ns: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        n = self.model.nq
        self.on_nm = np.asarray(self.on_nm, dtype=float)
        self.off_nm = np.asarray(self.off_nm, dtype=float)
        if self.on_nm.shape != (n,) or self.off_nm.shape != (n,):
            raise ValueError(f"on_nm and off_nm need {n} values (one per joint), got {self.on_nm.shape} and "
                             f"{self.off_nm.shape}")
        if not (np.isfinite(self.on_nm).all() and (self.off_nm > 0).all() and (self.off_nm <= self.on_nm).all()):
            raise ValueError(f"thresholds need 0 < off_nm <= on_nm, finite: on {self.on_nm}, off {self.off_nm}")
        if self.baseline not in BASELINES:
            raise ValueError(f"baseline {self.baseline!r} is not one of {BASELINES}")
        if self.tare_samples < 1 or not 0.0 <= self.follow < 1.0:
            raise ValueError(f"tare_samples {self.tare_samples} must be >= 1 and follow {self.follow} in [0, 1)")
        self._offset = np.zeros(n)
        self._tare_sum = np.zeros(n)
        self._last_dq = np.zeros(n)

    @property
    def active(self) -> bool:
        return self._active

    def reset(self) -> None:
        """Learn the offset again (a new connection, a gap in the state): no contact until then."""
        self._tared = 0
        self._tare_sum[:] = 0.0
        self._active = False
        self._last_ns = 0

    def update(self, q: np.ndarray, tau_ext: np.ndarray, dq: np.ndarray | None = None,
               stamp_ns: int = 0) -> TorqueContact:
        """One robot state (joint positions, rad; estimated external torques, N m; with the dynamics baseline its
        velocities, rad/s, and stamp). Non-finite input: ValueError (the caller's door refuses it first)."""
        q = np.asarray(q, dtype=float)
        tau = np.asarray(tau_ext, dtype=float)
        n = self.model.nq
        if tau.shape != (n,) or not np.isfinite(tau).all():
            raise ValueError(f"tau_ext needs {n} finite values, got {tau}")
        # A controller that reports its own torque moves the arm against gravity and against the push alike:
        # the external torque is what its torque lacks of the motion's.
        if self.baseline == "dynamics":
            v = np.zeros(n) if dq is None else np.asarray(dq, dtype=float)
            if v.shape != (n,) or not np.isfinite(v).all():
                raise ValueError(f"dq needs {n} finite values, got {v}")
            dt = (stamp_ns - self._last_ns) / 1e9
            acc = (v - self._last_dq) / dt if self._last_ns and 0 < dt <= MAX_DIFF_S else np.zeros(n)
            self._last_dq, self._last_ns = v, stamp_ns
            raw = self.model.inverse_dynamics(q, v, acc) - tau
        elif self.baseline == "gravity":
            raw = self.model.gravity_torques(q) - tau
        else:
            raw = tau.copy()
        if self._tared < self.tare_samples:
            self._tare_sum += raw
            self._tared += 1
            if self._tared == self.tare_samples:
                self._offset = self._tare_sum / self.tare_samples
            return TorqueContact(False, False, (0.0,) * n, -1, 0.0, tared=False)
        r = raw - self._offset
        ratios = np.abs(r) / self.on_nm
        joint = int(np.argmax(ratios))
        started = False
        if self._active:
            self._active = bool((np.abs(r) >= self.off_nm).any())
        elif ratios[joint] >= 1.0:
            self._active = started = True
        if not self._active:
            self._offset += self.follow * r  # slow drift (temperature, a payload's estimate) only, never a push
            return TorqueContact(False, False, tuple(r.tolist()), joint, float(ratios[joint]))
        pad, force, unexplained = self.locate(q, r)
        return TorqueContact(True, started, tuple(r.tolist()), joint, float(ratios[joint]), pad, force, unexplained)

    def locate(self, q: np.ndarray, r: np.ndarray) -> tuple[int, float, float]:
        """The pad whose push (along minus its normal) best explains ``r``: its index, force, N, and the share
        of ``|r|`` left unexplained; (-1, 0, 1) when no pad's push explains any of it."""
        norm = float(np.linalg.norm(r))
        if norm == 0.0:
            return -1, 0.0, 1.0
        jac = self.model.pad_jacobians(q)  # (pads, 3, nq)
        normals = self.model.pad_normals(q)  # (pads, 3)
        per_newton = -np.einsum("pk,pkj->pj", normals, jac)  # the joint torque of 1 N along -n at each pad
        best, best_force, best_left = -1, 0.0, 1.0
        for pad, a in enumerate(per_newton):
            aa = float(a @ a)
            if aa < 1e-12:
                continue  # a pad whose push no joint feels at this pose
            force = float(a @ r) / aa
            if force <= 0.0:
                continue
            left = float(np.linalg.norm(r - force * a)) / norm
            if left < best_left:
                best, best_force, best_left = pad, force, left
        return best, best_force, best_left if math.isfinite(best_left) else 1.0


def blind_fallback(pain: m.SkinPain, valid: list[bool], contact: TorqueContact, pads: tuple[Pad, ...],
                   full_force_n: float, pl3_gain: float) -> m.SkinPain:
    """``pain`` with the pad ``contact`` locates given the torque's gain where the skin is blind there.

    Only a detected contact located on a pad that is invalid in the skin sample (``valid[pad]`` False) counts:
    where the skin sees, the skin decides. Its gain is ``min(1, force / full_force_n)`` (PL 4 from
    ``pl3_gain`` up, PL 3 below), never lower than what the skin gave the pad; it becomes the strongest
    contact when its gain is the highest, and ``torque_pads`` names it. Otherwise ``pain`` unchanged.
    """
    pad = contact.pad
    if not contact.detected or pad < 0 or pad >= len(valid) or valid[pad]:
        return pain
    gain = min(1.0, contact.force_n / full_force_n)
    if not gain > pain.gain[pad]:
        return pain
    level = 4 if gain >= pl3_gain else 3
    gains = list(pain.gain)
    levels = list(pain.level)
    gains[pad], levels[pad] = gain, level
    strongest = pain.strongest
    if strongest is None or gain > strongest.gain:
        p = pads[pad]
        strongest = m.Contact(pad=pad, name=p.name, region=p.region, change_hpa=0.0, level=level, gain=gain)
    return msgspec.structs.replace(pain, gain=gains, level=levels, strongest=strongest,
                                   torque_pads=sorted({*pain.torque_pads, pad}))
