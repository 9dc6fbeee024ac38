"""The one pacing helper for every fixed-rate loop.

Sleeps to absolute deadlines (no drift), counts overruns, warns about them
at a bounded rate, and summarises the loop's timing at the end.
"""

from __future__ import annotations

import logging
import os
import threading
import time

import numpy as np

log = logging.getLogger(__name__)


def realtime(priority: int, name: str) -> bool:
    """Run the calling thread under SCHED_FIFO at ``priority`` (1-99), as on a lab's real-time kernel.

    Threads started afterwards (Zenoh's, when the session is opened after this)
    inherit it. 0 leaves the scheduling alone. Fails soft: without the
    permission (CAP_SYS_NICE, or an rtprio limit: ``ulimit -r``), or on a
    system without SCHED_FIFO, a warning and the normal scheduler.
    """
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError) as exc:
        log.warning("%s: real-time scheduling (SCHED_FIFO, priority %d) is not permitted here (%s): running with "
                    "the normal scheduler; grant CAP_SYS_NICE or an rtprio limit (ulimit -r %d) to use it",
                    name, priority, exc, priority)
        return False
    log.info("%s: real-time scheduling, SCHED_FIFO priority %d", name, priority)
    return True


class Rate:
    """``for tick in Rate(500).run(stop): ...`` or ``rate.sleep()`` in a loop."""

    def __init__(self, hz: float, name: str, *, keep: int = 4096) -> None:
        if not hz > 0:
            raise ValueError(f"rate of {name} must be positive, got {hz} Hz")
        self.name = name
        self.period_ns = round(1e9 / hz)
        self._next = time.monotonic_ns() + self.period_ns
        self._last = time.monotonic_ns()
        self.ticks = 0
        self.overruns = 0
        self._periods = np.zeros(keep)
        self._last_warning = 0

    def sleep(self, stop: threading.Event | None = None) -> bool:
        """Sleep until the next deadline; False when ``stop`` is set."""
        now = time.monotonic_ns()
        delay = self._next - now
        if delay > 0:
            # time.sleep, not stop.wait: Event.wait allocates a lock per call,
            # and a delay is at most one period, so a stop is seen as soon.
            time.sleep(delay / 1e9)
            if stop is not None and stop.is_set():
                return False
            self._next += self.period_ns
        else:
            self.overruns += 1
            missed = -delay // self.period_ns + 1
            self._next += missed * self.period_ns
            if now - self._last_warning > 5_000_000_000 and delay < -self.period_ns:
                self._last_warning = now
                log.warning("%s loop overran by %.1f ms (%d overruns so far)", self.name, -delay / 1e6, self.overruns)
        now = time.monotonic_ns()
        self._periods[self.ticks % len(self._periods)] = (now - self._last) / 1e6
        self._last = now
        self.ticks += 1
        return stop is None or not stop.is_set()

    def summary(self) -> str:
        n = min(self.ticks, len(self._periods))
        if n == 0:
            return f"{self.name}: no ticks"
        p = self._periods[:n]
        return (
            f"{self.name}: {self.ticks} ticks at {1e9 / self.period_ns:.0f} Hz, period p50 {np.median(p):.3f} ms "
            f"p99 {np.percentile(p, 99):.3f} ms worst {p.max():.3f} ms, {self.overruns} overruns"
        )
