"""The bridge's safety envelope: the per-joint limits it enforces, pure.

:class:`Envelope` holds the joint limits the bridge enforces: the robot
description's, scaled by the profile's fractions and tightened by its
per-joint lists (never loosened), as :func:`make_envelope` builds them. The
command check (:mod:`.checks`), the tracker (:mod:`.tracking`) and the
backends' last guard (:mod:`.backend`) all work within it.

:func:`stop_extent` and :func:`brake` describe one joint's time-optimal
jerk-limited stop from any speed and acceleration: how far it goes, and
where it is one control cycle into it. The tracker keeps every joint able to
make that stop before its limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nwr.common.errors import ConfigError


@dataclass(frozen=True, eq=False)
class Envelope:
    """Per-joint limits the bridge enforces, rad, rad/s, rad/s^2, rad/s^3."""

    joints: tuple[str, ...]
    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    a_max: np.ndarray
    j_max: np.ndarray
    position_jump_rad: float = 0.1  # from the stream's last target, or the arm's pose when a stream starts

    @property
    def n(self) -> int:
        return len(self.joints)

    @property
    def per_joint(self) -> tuple[tuple[float, float, float, float, float], ...]:
        """(q_min, q_max, v_max, a_max, k) of each joint as floats, computed once.

        ``k = a_max / (2 j_max)`` as in :meth:`braking_speed`. The tracker's
        per-cycle arithmetic runs on these: on six joints, plain float
        arithmetic costs a fraction of numpy's per-call overhead, and gives the
        same IEEE double results.
        """
        cached = self.__dict__.get("_per_joint")
        if cached is None:
            k = self.a_max / (2.0 * self.j_max)
            cached = tuple(zip(self.q_min.tolist(), self.q_max.tolist(), self.v_max.tolist(), self.a_max.tolist(),
                               k.tolist()))
            object.__setattr__(self, "_per_joint", cached)
        return cached

    def describe(self) -> str:
        """The envelope as a table, printed when the bridge starts."""
        rows = [f"{'joint':<22s} {'q_min':>8s} {'q_max':>8s} {'v_max':>7s} {'a_max':>7s} {'j_max':>7s}"]
        for i, name in enumerate(self.joints):
            rows.append(
                f"{name:<22s} {self.q_min[i]:8.3f} {self.q_max[i]:8.3f} {self.v_max[i]:7.3f} "
                f"{self.a_max[i]:7.2f} {self.j_max[i]:7.1f}"
            )
        rows.append(f"position targets farther than {self.position_jump_rad} rad from the arm are rejected")
        return "\n".join(rows)

    def braking_speed(self, distance: np.ndarray) -> np.ndarray:
        """Highest speed from which a jerk-limited stop ends within ``distance``.

        Solves v^2 / (2 a) + v a / (2 j) = d: the distance of a stop from
        constant speed that ramps its deceleration up to a at the jerk limit.
        """
        d = np.maximum(distance, 0.0)
        a, k = self.a_max, self.a_max / (2.0 * self.j_max)
        return a * (np.sqrt(k**2 + 2.0 * d / a) - k)


def make_envelope(
    joints: tuple[str, ...],
    description: dict[str, np.ndarray],
    *,
    speed_fraction: float = 1.0,
    acceleration_fraction: float = 1.0,
    jerk_fraction: float = 1.0,
    tighter: dict[str, list[float]] | None = None,
    position_jump_rad: float = 0.1,
) -> Envelope:
    """The envelope from the robot description's limits and the profile's tightening.

    ``description`` holds ``q_min``, ``q_max``, ``v_max``, ``a_max``, ``j_max``.
    ``tighter`` may hold the same names (empty lists = keep the description's);
    a value looser than the description's raises :class:`ConfigError`.
    """
    n = len(joints)
    fractions = {"v_max": speed_fraction, "a_max": acceleration_fraction, "j_max": jerk_fraction}
    limits: dict[str, np.ndarray] = {}
    for name in ("q_min", "q_max", "v_max", "a_max", "j_max"):
        base = np.asarray(description[name], dtype=float).copy()
        if base.shape != (n,):
            raise ConfigError(f"robot description: {name} has {base.size} values, the robot has {n} joints")
        value = base * fractions.get(name, 1.0)
        given = (tighter or {}).get(name) or []
        if given:
            extra = np.asarray(given, dtype=float)
            if extra.shape != (n,) or not np.all(np.isfinite(extra)):
                raise ConfigError(f"bridge.{name} must have {n} finite values (one per joint), got {given}")
            looser = extra < base if name == "q_min" else extra > base
            if np.any(looser):
                i = int(np.argmax(looser))
                raise ConfigError(
                    f"bridge.{name}[{i}] = {extra[i]} is looser than the robot description's {base[i]} "
                    f"for {joints[i]}: the profile may only tighten the limits"
                )
            value = np.maximum(value, extra) if name == "q_min" else np.minimum(value, extra)
        limits[name] = value
    if np.any(limits["q_min"] >= limits["q_max"]):
        i = int(np.argmax(limits["q_min"] >= limits["q_max"]))
        raise ConfigError(f"bridge: q_min {limits['q_min'][i]} >= q_max {limits['q_max'][i]} for {joints[i]}")
    for name in ("v_max", "a_max", "j_max"):
        if np.any(limits[name] <= 0):
            raise ConfigError(f"bridge.{name} must be positive for every joint, got {limits[name].tolist()}")
    for value in limits.values():
        value.setflags(write=False)
    return Envelope(joints, position_jump_rad=position_jump_rad, **limits)


def clip(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``np.clip(a, lo, hi)`` for ``lo <= hi``, as the two ufuncs it is made of.

    The same values (np.clip is defined as this), without the dispatch
    overhead that dominates on six joints in every 2 ms cycle.
    """
    return np.minimum(np.maximum(a, lo), hi)



# ------------------------------------------------------------------------------ one joint's stop


def _stop_phases(v: float, a: float, a_max: float, j_max: float) -> tuple[float, list[tuple[float, float]]]:
    """The time-optimal stop to rest (speed and acceleration 0) from ``v``, ``a``: the direction it is computed in
    (+1 or -1: the profile is for ``sign * v``, ``sign * a``) and its phases (jerk, duration).

    Deceleration at most ``a_max`` (more only while it ramps down from beyond
    it), jerk at most ``j_max``. From the direction of motion: ramp the
    deceleration up to ``a_p`` at the jerk limit, hold it, ramp it back to 0,
    where ``a_p = sqrt(j v + a^2 / 2)`` (at most ``a_max``) is what ends at
    rest. A joint already decelerating harder than that (``j v < a^2 / 2``)
    cannot stop without reversing a little: it ramps its acceleration up
    through 0 to ``sqrt(a^2 / 2 - j v)`` and back, ending at rest.
    """
    sign = 1.0 if v > 0.0 or (v == 0.0 and a >= 0.0) else -1.0
    v, a, j = sign * v, sign * a, j_max
    energy = j * v + 0.5 * a * a  # invariant while the jerk is -j
    if a < 0.0 and energy < a * a:
        peak = math.sqrt(max(0.5 * a * a - j * v, 0.0))
        return sign, [(j, (peak - a) / j), (-j, peak / j)]
    peak = math.sqrt(energy)
    hold = 0.0
    if peak > a_max:
        peak = a_max
        hold = max((v + a * a / (2.0 * j) - a_max * a_max / j) / a_max, 0.0)
    return sign, [(-j, max(a + peak, 0.0) / j), (0.0, hold), (j, peak / j)]


def _integrate(x: float, v: float, a: float, jerk: float, t: float) -> tuple[float, float, float]:
    return (x + v * t + 0.5 * a * t * t + jerk * t * t * t / 6.0, v + a * t + 0.5 * jerk * t * t, a + jerk * t)


def stop_extent(v: float, a: float, a_max: float, j_max: float) -> tuple[float, float]:
    """The lowest and highest displacement (lo <= 0 <= hi, rad) along one joint's time-optimal stop from ``v``, ``a``.

    Within a phase the position turns back only where the speed crosses 0, so
    the phase ends and those crossings are all the extremes there are.
    """
    sign, phases = _stop_phases(v, a, a_max, j_max)
    x, v, a = 0.0, sign * v, sign * a
    lo = hi = 0.0
    for jerk, t in phases:
        if t <= 0.0:
            continue
        if jerk != 0.0:  # where v + a s + jerk s^2 / 2 = 0 within the phase
            disc = a * a - 2.0 * jerk * v
            if disc >= 0.0:
                root = math.sqrt(disc)
                for s in ((-a - root) / jerk, (-a + root) / jerk):
                    if 0.0 < s < t:
                        xs = _integrate(x, v, a, jerk, s)[0]
                        lo, hi = min(lo, xs), max(hi, xs)
        x, v, a = _integrate(x, v, a, jerk, t)
        lo, hi = min(lo, x), max(hi, x)
    return (lo, hi) if sign > 0.0 else (-hi, -lo)


def brake(v: float, a: float, h: float, a_max: float, j_max: float) -> tuple[float, float, float]:
    """Displacement, speed and acceleration of one joint ``h`` s into its time-optimal stop from ``v``, ``a``.

    Taken one cycle at a time, the stop is the same stop: from where it
    brings the joint, the rest of it is what :func:`stop_extent` computes.
    """
    sign, phases = _stop_phases(v, a, a_max, j_max)
    x, v, a = 0.0, sign * v, sign * a
    left = h
    for jerk, t in phases:
        step = min(t, left)
        if step > 0.0:
            x, v, a = _integrate(x, v, a, jerk, step)
            left -= step
    if left > 0.0:  # at rest before the cycle ends
        v = a = 0.0
    return sign * x, sign * v, sign * a
