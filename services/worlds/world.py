"""What every world gives the pipeline: the arm as measured, the skin as sampled, on the world's own clock.

See :mod:`nwr.services.worlds` for what a world is. This module holds the
interface (:class:`World`) and the readings every world returns; it
imports no simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from nwr.services.worlds.skin import SkinSample


@dataclass(frozen=True, eq=False)
class ArmState:
    """The arm as its controller measures it, at world time ``time_ns``.

    ``q`` (rad) and ``dq`` (rad/s) per joint in the description's order;
    ``tau`` the joint torques the servos apply (N m, gravity compensation
    included); ``tau_external`` the torques the contacts put on the joints
    (N m: what a UR's or a Franka's external-torque estimate would read);
    ``q_command`` the command the servos were tracking (after clipping to
    the joint ranges).
    """

    time_ns: int
    q: np.ndarray
    dq: np.ndarray
    tau: np.ndarray
    tau_external: np.ndarray
    q_command: np.ndarray


class World(Protocol):
    """The arm, its skin and the people touching it, advanced one fixed step at a time.

    Single-threaded and deterministic: the same calls in the same order give
    bit-identical readings. Time is the world's own (``time_ns``, from 0),
    never the wall clock; a live adapter paces ``step`` against a clock.
    """

    @property
    def time_ns(self) -> int: ...

    @property
    def timestep_ns(self) -> int: ...

    def step(self, q_command: np.ndarray, dq_command: np.ndarray | None = None) -> None:
        """Advance one time step with the arm's servos tracking ``q_command`` (rad) and, if given, ``dq_command``
        (rad/s)."""
        ...

    def arm(self) -> ArmState:
        """The arm now."""
        ...

    def skin(self) -> list[SkinSample]:
        """The skin samples delivered since the last call, oldest first."""
        ...
