"""Each pad's effective mass and the impact force a collision at its speed would cause (ISO/TS 15066, PFL).

Per pad, from the arm's joint positions q and speeds dq (the robot state):

    v   = J dq                          the pad point's velocity (J its 3 x n translational Jacobian)
    u   = v / |v|                       its direction of motion; the pad's outward normal where |v| < rest speed
    m   = 1 / (u^T J M^-1 J^T u)        the arm's effective mass along u (M the joint-space mass matrix)
    F   = |v| sqrt(k) / sqrt(1/m + 1/m_H)

k and m_H are the effective spring constant and mass of the body region the
pad would meet (ISO/TS 15066, power and force limiting: the transfer of the
relative kinetic energy ``E = F^2 / 2k`` with the reduced mass
``mu = (1/m + 1/m_H)^-1``); Rustler et al., "adaptive sensitivity" (arXiv
2409.20184) compute the same per AIRSKIN pad. A pad at rest predicts F = 0.

Bad input gets a defined, conservative answer and never a NaN: no robot
state, a stale one or one the bridge does not vouch for, a non-finite or
wrong-sized state, a mass matrix that is not positive definite or is
ill-conditioned: every pad is *unknown* (``Impact.basis`` names why), with
its predicted force set to its region's limit, so that the gain model makes
it its most sensitive. A pad whose direction cannot load the arm at all (u
orthogonal to every column of J: ``u^T J M^-1 J^T u = 0``) has an infinite
effective mass: its force is then that of the person's own mass,
``|v| sqrt(k m_H)``, and its reported mass :data:`MASS_CAP_KG`.

Pure: numpy, the robot model and Structs in, numbers out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nwr.common import messages as m
from nwr.common.config import BodyRegion, EffectiveMassSection
from nwr.common.errors import ConfigError
from nwr.common.robot import Pad, RobotModel

# Why an Impact is what it is: computed from the state, or the conservative answer's reason.
MEASURED = "state"
NO_STATE = "no_state"
STALE_STATE = "stale_state"  # older than state_timeout_s, or the bridge's last known pose (pose_stale)
NON_FINITE_STATE = "non_finite_state"  # q or dq not finite, or not one value per joint
ILL_CONDITIONED = "ill_conditioned"  # the mass matrix not positive definite, or its condition above MAX_CONDITION
REASONS = (NO_STATE, STALE_STATE, NON_FINITE_STATE, ILL_CONDITIONED)

# Beyond this condition number M^-1 is numerically meaningless (the UR10e's is ~1e4 in every pose: its wrist's
# small inertias); a real arm's never comes near it: a corrupt model or state does.
MAX_CONDITION = 1e10
# The effective mass reported where u^T Lambda^-1 u vanishes (an infinite mass), kg; the force uses the limit.
MASS_CAP_KG = 1e6


@dataclass(frozen=True)
class Impact:
    """One prediction for every pad, in pad id order."""

    basis: str  # MEASURED, else one of REASONS (every pad unknown)
    mass_kg: np.ndarray  # effective mass along u, kg (0 where unknown, at most MASS_CAP_KG)
    speed_m_s: np.ndarray  # the pad point's speed, m/s (0 where unknown)
    force_n: np.ndarray  # the predicted impact force, N (the region's limit where unknown)
    ratio: np.ndarray  # force / the region's transient limit, in [0, 1] (1 where unknown)

    @property
    def known(self) -> bool:
        return self.basis == MEASURED


def inverse_masses(mass_matrix: np.ndarray, jacobians: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """``u_p^T J_p M^-1 J_p^T u_p`` per pad p (1/kg): ``jacobians`` (P, 3, n), ``directions`` (P, 3) unit.

    ``mass_matrix`` must be symmetric positive definite (:func:`well_conditioned`)."""
    projected = np.einsum("pi,pij->pj", directions, jacobians)  # J_p^T u_p, (P, n)
    solved = np.linalg.solve(mass_matrix, projected.T)  # M^-1 J_p^T u_p, (n, P)
    return np.maximum(0.0, np.einsum("pj,jp->p", projected, solved))  # >= 0 up to rounding


def impact_forces(speed: np.ndarray, inverse_mass: np.ndarray, k_n_m: np.ndarray, mass_h_kg: np.ndarray) -> np.ndarray:
    """``F = v sqrt(k) / sqrt(1/m + 1/m_H)`` per pad, N (``inverse_mass`` = 1/m, 0 for an infinite m)."""
    return speed * np.sqrt(k_n_m) / np.sqrt(inverse_mass + 1.0 / mass_h_kg)


def well_conditioned(mass_matrix: np.ndarray) -> bool:
    """Whether M is finite, symmetric positive definite and its condition number at most MAX_CONDITION."""
    if not np.isfinite(mass_matrix).all():
        return False
    eig = np.linalg.eigvalsh(mass_matrix)
    return bool(eig[0] > 0.0 and eig[-1] <= MAX_CONDITION * eig[0])


def pad_regions(cfg: EffectiveMassSection, pads: tuple[Pad, ...]) -> list[tuple[str, BodyRegion]]:
    """The body region each pad meets (its name and values), in pad order; ConfigError for a pad or region the
    profile names that does not exist."""
    names = {p.name for p in pads}
    unknown = sorted(set(cfg.pad_regions) - names)
    if unknown:
        raise ConfigError(f"gain.effective_mass.pad_regions names pads {unknown} that the skin does not have "
                          f"(pads: {sorted(names)})")
    out = []
    for pad in pads:
        region = cfg.pad_regions.get(pad.name, cfg.default_region)
        values = cfg.regions.get(region)
        if values is None:
            raise ConfigError(f"gain.effective_mass: pad {pad.name} meets body region {region!r}, which "
                              f"gain.effective_mass.regions does not have ({', '.join(sorted(cfg.regions))})")
        out.append((region, values))
    return out


class ImpactModel:
    """Predicts every pad's effective mass and impact force from a robot state (see the module's docstring)."""

    def __init__(self, cfg: EffectiveMassSection, robot: RobotModel) -> None:
        pads = robot.desc.pads
        regions = pad_regions(cfg, pads)
        self.regions = tuple(name for name, _ in regions)
        self.k = np.array([r.k_n_m for _, r in regions])
        self.mass_h = np.array([r.mass_kg for _, r in regions])
        self.limit = np.array([r.transient_n for _, r in regions])
        self.rest_speed = cfg.rest_speed_m_s
        self.timeout_ns = round(cfg.state_timeout_s * 1e9)
        self.robot = robot
        self.n = len(pads)
        self.nq = robot.nq
        self._unknown: dict[str, Impact] = {}
        self._latest: Impact | None = None  # the newest robot state's prediction
        self._stamp_ns = 0  # that state's stamp

    def unknown(self, basis: str) -> Impact:
        """The conservative answer (every pad at its region's limit), naming why."""
        found = self._unknown.get(basis)
        if found is None:
            zero = np.zeros(self.n)
            found = self._unknown[basis] = Impact(basis, zero, zero, self.limit.copy(), np.ones(self.n))
        return found

    def at(self, q: np.ndarray, dq: np.ndarray) -> Impact:
        """The prediction for joint positions ``q`` (rad) and speeds ``dq`` (rad/s)."""
        q = np.asarray(q, dtype=float)
        dq = np.asarray(dq, dtype=float)
        if q.shape != (self.nq,) or dq.shape != (self.nq,) or not (np.isfinite(q).all() and np.isfinite(dq).all()):
            return self.unknown(NON_FINITE_STATE)
        mass_matrix = self.robot.mass_matrix(q)
        if not well_conditioned(mass_matrix):
            return self.unknown(ILL_CONDITIONED)
        jacobians = self.robot.pad_jacobians(q)
        velocity = jacobians @ dq  # (P, 3)
        speed = np.linalg.norm(velocity, axis=1)
        moving = speed >= self.rest_speed
        directions = self.robot.pad_normals(q)
        directions[moving] = velocity[moving] / speed[moving, None]
        inverse = inverse_masses(mass_matrix, jacobians, directions)
        speed = np.where(moving, speed, 0.0)
        force = impact_forces(speed, inverse, self.k, self.mass_h)
        mass = np.where(inverse > 1.0 / MASS_CAP_KG, 1.0 / np.maximum(inverse, 1.0 / MASS_CAP_KG), MASS_CAP_KG)
        if not (np.isfinite(force).all() and np.isfinite(mass).all()):  # cannot happen for a finite SPD M
            return self.unknown(ILL_CONDITIONED)
        return Impact(MEASURED, mass, speed, force, np.minimum(1.0, force / self.limit))

    def update(self, state: m.RobotState) -> None:
        """Take a new robot state: its prediction is made now, off the skin sample's path (:meth:`predict`)."""
        self._stamp_ns = state.stamp_ns
        self._latest = self.unknown(STALE_STATE) if state.pose_stale else self.at(
            np.asarray(state.q, dtype=float), np.asarray(state.dq, dtype=float))

    def predict(self, now_ns: int) -> Impact:
        """The newest robot state's prediction at ``now_ns`` (no state yet, or one older than
        ``state_timeout_s``: unknown)."""
        if self._latest is None:
            return self.unknown(NO_STATE)
        if now_ns - self._stamp_ns > self.timeout_ns:
            return self.unknown(STALE_STATE)
        return self._latest


def speed_scale_allowed(model: ImpactModel, qs: np.ndarray, dqs: np.ndarray) -> tuple[float, int, int]:
    """How much faster (or slower: < 1) a motion through the poses ``qs`` at speeds ``dqs`` (rows) may run before
    any pad's predicted impact force reaches its region's limit: ``min over samples and pads of limit / F``
    (F grows in proportion to the speed along the same path; m does not change). Also the sample and pad
    that bind. ``inf`` for a motion that predicts no force at all."""
    best, where = np.inf, (-1, -1)
    for i, (q, dq) in enumerate(zip(qs, dqs)):
        impact = model.at(q, dq)
        if not impact.known:
            raise ValueError(f"sample {i}: no prediction ({impact.basis})")
        with np.errstate(divide="ignore"):
            scale = np.where(impact.force_n > 0, model.limit / np.where(impact.force_n > 0, impact.force_n, 1.0),
                             np.inf)
        pad = int(np.argmin(scale))
        if scale[pad] < best:
            best, where = float(scale[pad]), (i, pad)
    return best, where[0], where[1]
