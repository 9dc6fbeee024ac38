"""The gateway's skin sources: where a run's skin samples come from, behind one interface.

- :class:`SimulatedSkin`: the gateway's own wiring on a touch script, open
  or closed loop against the run's arm (the live gateway, ``nwr demo --fast``);
- :class:`RecordedSkin`: a recording's samples, as recorded (open loop);
- :class:`ResimulatedSkin`: a simulated session's samples with their touches
  re-simulated against the run's arm (``nwr replay --fast --resimulate``,
  :class:`nwr.services.gateway.core.Resimulator`).

Lockstep (:mod:`nwr.services.pipeline.lockstep`) and the bench's lower bound
take their samples from one of these; each sample is made with the arm where
the newest robot state puts it (:data:`Pose`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile
from nwr.common.journal import Journal
from nwr.common.launch import TouchScript
from nwr.common.robot import RobotModel
from nwr.services.gateway.core import Resimulator, touch_message
from nwr.services.gateway.wiring import GatewayWiring
from nwr.services.wiring import Out, no_diag

Emit = Callable[[str, Any, int], None]  # (relative key, message, simulated time ns)
Pose = tuple[np.ndarray, int]  # the arm's joint positions as the newest robot state gives them, and its stamp


class SkinSource:
    """The skin samples of a run, in stamp order."""

    origin_ns: int | None = None  # when a source that is the gateway starts its script clock
    def __len__(self) -> int:
        raise NotImplementedError

    def stamp(self, i: int) -> int:
        """Stamp of the ``i``-th sample, ns."""
        raise NotImplementedError

    def wiring(self, clock: ManualClock, journal: Journal, out: Out) -> GatewayWiring | None:
        """The gateway's wiring, for a source that is the gateway (its samples go to ``out``)."""
        return None

    def take(self, i: int, pose: Pose, emit: Emit) -> m.SkinPressure | None:
        """The ``i``-th sample, made with the arm at ``pose`` (emits what it makes); None: the wiring published it."""
        raise NotImplementedError

    def extend_to(self, end_ns: int) -> None:
        """Go on making samples until ``end_ns``, if this source can (recorded samples end where they end)."""


class RecordedSkin(SkinSource):
    """Recorded samples, delivered as they are (open loop); the caller has them already, nothing is emitted."""

    def __init__(self, samples: Iterable[m.SkinPressure]) -> None:
        self.samples = sorted(samples, key=lambda s: s.stamp_ns)

    def __len__(self) -> int:
        return len(self.samples)

    def stamp(self, i: int) -> int:
        return self.samples[i].stamp_ns

    def take(self, i: int, pose: Pose, emit: Emit) -> m.SkinPressure | None:
        return self.samples[i]


class ResimulatedSkin(RecordedSkin):
    """Recorded samples of the simulated skin, their touches re-simulated against the run's arm."""

    def __init__(self, samples: Iterable[m.SkinPressure], resimulator: Resimulator, model: RobotModel) -> None:
        super().__init__(samples)
        self.resimulator = resimulator
        self.model = model
        self.touch_seq = 0

    def take(self, i: int, pose: Pose, emit: Emit) -> m.SkinPressure | None:
        res = self.resimulator
        q, pose_stamp = pose
        sample, started = res.apply(self.samples[i], self.model.pad_points(q), self.model.pad_normals(q))
        for touch in started:  # the ground truth of this run: the touches met the pads where this arm had them
            emit(keys.SKIN_TOUCH, touch_message(self.touch_seq, sample.stamp_ns, res.origin_ns, touch,
                                                self.model.desc.pads[touch.pad].name, res.touches, q,
                                                pose_stamp), sample.stamp_ns)
            self.touch_seq += 1
        emit(keys.SKIN_PRESSURE, sample, sample.stamp_ns)
        return sample


class SimulatedSkin(SkinSource):
    """The simulated skin on a touch script at ``gateway.rate_hz``: the gateway's own wiring.

    Its script clock starts at ``origin_ns``; the samples are stamped every
    sample period from one period after it until the script's end (the
    sample at or after ``duration_s`` is the last, as ``--exit-at-end``), or
    on at rest until :meth:`extend_to` (as the live gateway goes on until the
    launcher has stopped the arm). Like the live gateway, it sees the arm
    where the newest robot state puts it.
    """

    def __init__(self, profile: Profile, script: TouchScript, model: RobotModel | None = None,
                 origin_ns: int = 10**9) -> None:
        self.profile = profile
        self.script = script
        self.origin_ns: int = origin_ns
        self.period = 1e9 / profile.gateway.rate_hz
        self.stamps: list[int] = []
        k = 1
        while True:
            self.stamps.append(origin_ns + round(k * self.period))
            if (self.stamps[-1] - origin_ns) / 1e9 >= script.duration_s:
                break
            k += 1
        self.gateway: GatewayWiring | None = None

    def extend_to(self, end_ns: int) -> None:
        k = len(self.stamps) + 1
        while (stamp := self.origin_ns + round(k * self.period)) <= end_ns:
            self.stamps.append(stamp)
            k += 1

    def __len__(self) -> int:
        return len(self.stamps)

    def stamp(self, i: int) -> int:
        return self.stamps[i]

    def wiring(self, clock: ManualClock, journal: Journal, out: Out) -> GatewayWiring:
        t = clock.t_ns
        clock.t_ns = self.origin_ns
        self.gateway = GatewayWiring(self.profile, journal=journal, out=out, diag=no_diag, script=self.script)
        self.gateway.origin()
        clock.t_ns = t
        return self.gateway

    def take(self, i: int, pose: Pose, emit: Emit) -> m.SkinPressure | None:
        assert self.gateway is not None, "SimulatedSkin.wiring() first"
        self.gateway.tick()
        return None
