"""Skin from contact: each pad's pressure change from the normal force on its cushion, sampled like the real skin.

The pressure model
------------------
An AIRSKIN pad is a closed air volume under a shell: pressing it with a
normal force ``F`` spread over the shell raises the air pressure until the
pressure over the shell's effective area carries the force,
``dP = F / A_eff``. The shell and the air's compression stop it rising
without bound, so the change saturates smoothly toward ``P_sat``::

    dP = P_sat * tanh(F / (A_eff * P_sat))        (hPa; F in N, A_eff in m^2 -> Pa / 100)

The paper gives pressures, never forces, so ``A_eff`` is calibrated on what
its participants did ("touch the center of the active pads with one finger
using varying pressure levels"): with ``A_eff = 125 cm^2`` and ``P_sat = 80
hPa`` the paper's thresholds fall at finger forces a person would call a
light touch, a press, a firm press and a hard press::

    PL 2 from  2 hPa:  2.5 N      PL 3 from 6 hPa:   7.5 N  (reflexes start)
    PL 4 from 12 hPa: 15.1 N      G = 1 from 20 hPa: 25.5 N  (a finger's plausible push, 50 N: 37 hPa)

:func:`force_for_pressure` inverts it (what a scripted pressure means as a
finger's force). The model has no dependence on where on the pad the force
acts, on the contact area or on the pad's speed: the paper names all three
as what makes the real mapping hard; they are left out on purpose.

Sampling
--------
:class:`SkinSampler` samples every pad at the skin's rate (AIRSKIN: about
25 Hz) on the world's step clock (at the first step at or after each
period; a period that is a whole number of steps gives an even rate): each
sample the mean of the pressure over the steps since the last one (the
device's averaging between readings: a contact lost for a step dims a
sample, never blanks it), or the pressure at the sample's step
(``mean=False``, as recordings made before the mean); it adds
white noise (a seeded generator: the
same seed gives the same noise), and delivers each sample ``latency_s``
after it was taken, as absolute pressures over a per-pad no-contact
baseline (what a device reports; the gateway tracks the baseline itself).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

HPA_PER_PA = 0.01


def pressure_from_force(force_n: np.ndarray | float, area_m2: np.ndarray | float,
                        saturation_hpa: float) -> np.ndarray:
    """A pad's pressure change (hPa) under a normal force ``force_n`` (N) on its cushion (see the module)."""
    linear = np.asarray(force_n, dtype=float) / np.asarray(area_m2, dtype=float) * HPA_PER_PA
    return saturation_hpa * np.tanh(linear / saturation_hpa)


def force_for_pressure(change_hpa: float, area_m2: float, saturation_hpa: float) -> float:
    """The normal force (N) that gives a pressure change ``change_hpa``; ValueError at or beyond saturation."""
    if not 0.0 <= change_hpa < saturation_hpa:
        raise ValueError(f"a pressure change of {change_hpa} hPa is outside [0, {saturation_hpa}) hPa, "
                         "the range the pad's model reaches")
    return saturation_hpa * math.atanh(change_hpa / saturation_hpa) / HPA_PER_PA * area_m2


@dataclass(frozen=True, eq=False)
class SkinSample:
    """One sample of every pad, in pad id order, as the device reports it.

    ``taken_ns`` is the world time the pads were sampled, ``delivered_ns``
    the time the sample reaches its reader (``taken_ns`` + latency).
    ``absolute_hpa`` is what the device reports (baseline + change + noise);
    ``change_hpa`` the noise-free change the contact forces made (the ground
    truth a recording can keep beside it).
    """

    seq: int
    taken_ns: int
    delivered_ns: int
    absolute_hpa: np.ndarray
    change_hpa: np.ndarray


class SkinSampler:
    """Samples the pads at a fixed rate on the world's clock, with noise and latency; deterministic per seed."""

    def __init__(self, n_pads: int, *, rate_hz: float, latency_s: float, noise_hpa: float, base_hpa: float,
                 spread_hpa: float, seed: int, mean: bool = True) -> None:
        self.period_ns = round(1e9 / rate_hz)
        self.latency_ns = round(latency_s * 1e9)
        self.noise_hpa = noise_hpa
        self._rng = np.random.default_rng(seed)
        # Pads differ by up to +-spread at rest (each is its own closed volume).
        self.baseline_hpa = base_hpa + spread_hpa * (2.0 * self._rng.random(n_pads) - 1.0)
        self.baseline_hpa.flags.writeable = False
        self._next_ns = self.period_ns  # the first sample one period in
        self._seq = 0
        self._pending: deque[SkinSample] = deque()
        self.mean = mean
        self._sum = np.zeros(n_pads)  # the pressure summed over the steps since the last sample
        self._steps = 0

    def observe(self, now_ns: int, change_hpa: np.ndarray) -> SkinSample | None:
        """The pads' pressure changes at one world step (every step, in order); the sample taken, if due."""
        if self.mean:
            self._sum += change_hpa
            self._steps += 1
        if not self.due(now_ns):
            return None
        if self.mean:
            change_hpa = self._sum / self._steps
            self._sum = np.zeros_like(self._sum)
            self._steps = 0
        return self.take(now_ns, change_hpa)

    def due(self, now_ns: int) -> bool:
        """Whether a sample is due at world time ``now_ns``."""
        return now_ns >= self._next_ns

    def take(self, now_ns: int, change_hpa: np.ndarray) -> SkinSample:
        """Sample the pads' pressure changes at ``now_ns`` (call when :meth:`due`); queued for delivery."""
        change = np.array(change_hpa, dtype=float)
        noise = self._rng.normal(0.0, self.noise_hpa, change.shape) if self.noise_hpa > 0.0 else 0.0
        sample = SkinSample(self._seq, now_ns, now_ns + self.latency_ns, self.baseline_hpa + change + noise, change)
        self._seq += 1
        while self._next_ns <= now_ns:
            self._next_ns += self.period_ns
        self._pending.append(sample)
        return sample

    def delivered(self, now_ns: int) -> list[SkinSample]:
        """The samples that have reached their reader by ``now_ns``, oldest first, each once."""
        out: list[SkinSample] = []
        while self._pending and self._pending[0].delivered_ns <= now_ns:
            out.append(self._pending.popleft())
        return out
