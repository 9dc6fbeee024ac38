"""``nwr bench --strategies``: what each reflex strategy costs the planner per control cycle, in this process.

Every strategy's planner core (:class:`~nwr.services.planner.core.Planner`,
the same code the live planner runs) is taken through the same touches: every
pad of the robot at the survey script's three gains (0.175, 0.58, 1), from
poses along the task's figure-eight. For each touch the reflex's onset (the
pain message that starts it, :meth:`Planner.on_pain`) and every control cycle
of its motion (:meth:`Planner.step` while the mode is REFLEX) are timed with
``time.perf_counter_ns``. The retreat check, which the live planner runs off
the event path on its own thread, is not part of a cycle and not timed.

The figures: median, 99th percentile and maximum per cycle, the median as a
ratio to the Cartesian reflex's (the baseline, measured in the same process,
interleaved touch by touch), and the p99 as a share of the control period
(2 ms at 500 Hz). Wall-clock figures on a shared machine: read the ratios.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight
from nwr.services.planner import strategies
from nwr.services.planner.core import Planner
from nwr.services.planner.wiring import planner_profile

BASELINE = "cartesian"
GAINS = (0.175, 0.58, 1.0)  # the survey script's 9, 15 and 25 hPa
POSES_S = (0.0, 2.0, 4.5)  # task times of the poses the touches start from, s
MAX_REFLEX_S = 4.0  # a position-mode reflex's motion is timed for at most this long


def _contact(desc: Any, pad: int, gain: float) -> m.Contact:
    info = desc.pads[pad]
    return m.Contact(pad=pad, name=info.name, region=info.region, change_hpa=20.0, level=4, gain=gain)


def _planner(profile: Profile, strategy: str, desc: Any, model: RobotModel, q: np.ndarray) -> tuple[Planner, int]:
    """A planner of ``strategy`` running its task at pose ``q`` (its first cycles done), and the time, ns."""
    cfg = planner_profile(profile, strategy=strategy, name=strategy).planner
    planner = Planner(cfg, desc, model)
    planner.on_state(q.copy(), following=True)
    t = 0
    period = round(1e9 / cfg.rate_hz)
    for _ in range(round(10.0 * cfg.rate_hz)):
        t += period
        planner.step(t)
        if planner.mode == "TASK":
            break
    return planner, t


def touch(profile: Profile, strategy: str, pad: int, gain: float, q: np.ndarray, desc: Any,
          model: RobotModel) -> tuple[int, list[int]]:
    """One touch: the onset's cost and every reflex cycle's, ns."""
    planner, t = _planner(profile, strategy, desc, model, q)
    period = round(1e9 / planner.cfg.rate_hz)
    n = len(desc.pads)
    gains = [0.0] * n
    gains[pad] = gain
    pain = m.SkinPain(seq=1, stamp_ns=t, trace=m.Trace(1, t - 1000), model="continuous", level=[1] * n,
                      gain=gains, strongest=_contact(desc, pad, gain))
    start = time.perf_counter_ns()
    planner.on_pain(pain, t)
    onset = time.perf_counter_ns() - start
    cycles: list[int] = []
    for _ in range(round(MAX_REFLEX_S * planner.cfg.rate_hz)):
        if planner.mode != "REFLEX":
            break
        t += period
        start = time.perf_counter_ns()
        planner.step(t)
        cycles.append(time.perf_counter_ns() - start)
    return onset, cycles


def run(profile: Profile, print_row: Callable[[dict[str, Any]], None] = lambda _row: None,
        names: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
    """One row per strategy (the baseline first): cycles timed, per-cycle and onset figures, us."""
    desc = load_description(profile.robot.description or None)
    model = RobotModel(desc)
    task = FigureEight(profile.planner.task, desc)
    chosen = names or strategies.names()
    order = (BASELINE, *[s for s in chosen if s != BASELINE])
    cycles: dict[str, list[int]] = {s: [] for s in order}
    onsets: dict[str, list[int]] = {s: [] for s in order}
    for s_task in POSES_S:
        q = task.position(s_task)
        for pad in range(len(desc.pads)):
            for gain in GAINS:
                for strategy in order:  # interleaved: the machine's load falls on every strategy alike
                    onset, timed = touch(profile, strategy, pad, gain, q, desc, model)
                    onsets[strategy].append(onset)
                    cycles[strategy] += timed
    period_us = 1e6 / profile.planner.rate_hz
    base = float(np.median(np.asarray(cycles[BASELINE], dtype=float) / 1e3))
    rows = []
    for strategy in order:
        c = np.asarray(cycles[strategy], dtype=float) / 1e3
        o = np.asarray(onsets[strategy], dtype=float) / 1e3
        row = {
            "strategy": strategy, "cycles": int(c.size), "cycle p50 us": float(np.median(c)),
            "cycle p99 us": float(np.percentile(c, 99)), "cycle max us": float(c.max()),
            "p50 / cartesian": float(np.median(c)) / base, "p99 / period": float(np.percentile(c, 99)) / period_us,
            "onset p50 us": float(np.median(o)), "onset max us": float(o.max()),
        }
        rows.append(row)
        print_row(row)
    return rows
