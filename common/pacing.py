"""The one pacing helper for every fixed-rate loop.

Sleeps to absolute deadlines (no drift), counts overruns, and summarises the
loop's timing at the end. An overrun by a few cycles is what an ordinary OS
does on a busy machine: counted, and summed up in one INFO line a minute. A
loop later than ``LATE_PERIODS`` cycles is warned about: the first at once,
those after it within the minute in one line with their count. While the
loop's service is still ``starting`` (it sets that off once its inputs flow:
the pipeline's other processes start meanwhile, and load the machine), an
overrun is counted apart and not warned about.
"""

from __future__ import annotations

import logging
import os
import threading
import time

import numpy as np

log = logging.getLogger(__name__)

# A loop later than this many cycles is warned about (the bridge's: 20 ms at 500 Hz, its command timeout); a loop
# late by fewer is what an ordinary OS does on a busy machine, counted and summed up at INFO.
LATE_PERIODS = 10
WINDOW_NS = 60_000_000_000  # overruns not warned about one by one are summed up once a minute


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

    def __init__(self, hz: float, name: str, *, keep: int = 4096, starting: bool = False) -> None:
        if not hz > 0:
            raise ValueError(f"rate of {name} must be positive, got {hz} Hz")
        self.name = name
        self.period_ns = round(1e9 / hz)
        self._next = time.monotonic_ns() + self.period_ns
        self._last = time.monotonic_ns()
        self.ticks = 0
        self.overruns = 0
        self.starting = starting  # the service is starting: overruns are counted apart, not warned about
        self.start_overruns = 0
        self._periods = np.zeros(keep)
        self._samples = 0  # periods recorded (one per wake: a wake may take several ticks)
        self._last_warning = -WINDOW_NS
        # Overruns since _window_start not reported one by one: how many, how many late, the worst (ns late).
        self._window_start = 0
        self._window_count = 0
        self._window_late = 0
        self._window_worst_ns = 0

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
            missed = -delay // self.period_ns + 1
            self._next += missed * self.period_ns
            self._overran(now, -delay, -delay > self.period_ns)
        now = time.monotonic_ns()
        self._record((now - self._last) / 1e6)
        self._last = now
        self.ticks += 1
        return stop is None or not stop.is_set()

    # -- loops that may sleep through cycles they can compute later -------------------
    def wait(self, stop: threading.Event | None = None, *, through: int = 0,
             wake: threading.Event | None = None) -> bool:
        """Sleep until the next deadline not yet taken, or ``through`` deadlines after it,
        or until ``wake`` is set; False when ``stop`` is set.

        Takes no deadline: :meth:`take` does, in the loop or in whichever
        thread needs the cycles stepped first (under the caller's lock).
        """
        delay = self._next + through * self.period_ns - time.monotonic_ns()
        if delay > 0:
            if wake is not None:
                if wake.wait(delay / 1e9):
                    wake.clear()
            else:
                time.sleep(delay / 1e9)
        return stop is None or not stop.is_set()

    def take(self, now_ns: int, limit: int | None = None) -> int:
        """Take the deadlines that have passed by ``now_ns`` (at most ``limit``); how many."""
        if now_ns < self._next:
            return 0
        n = (now_ns - self._next) // self.period_ns + 1
        if limit is not None:
            n = min(n, limit)
            if n <= 0:
                return 0
        self._next += n * self.period_ns
        self._record((now_ns - self._last) / n / 1e6)  # the mean period of the ticks taken
        self._last = now_ns
        self.ticks += n
        return n

    @property
    def next_ns(self) -> int:
        """The next deadline not yet taken, ns (``time.monotonic_ns``)."""
        return self._next

    def restart(self, now_ns: int) -> None:
        """Start the schedule afresh at ``now_ns`` (after a slow start-up; not an overrun)."""
        self._next = now_ns + self.period_ns
        self._last = now_ns

    def skip(self, now_ns: int) -> int:
        """Drop the deadlines that have passed untaken (a late loop: an overrun); how many."""
        n = 0 if now_ns < self._next else (now_ns - self._next) // self.period_ns + 1
        if n:
            late = now_ns - self._next + self.period_ns
            self._next += n * self.period_ns
            self._overran(now_ns, late, late > 2 * self.period_ns)
        return n

    def _overran(self, now_ns: int, late_ns: int, worth_saying: bool) -> None:
        self.overruns += 1
        if self.starting:
            self.start_overruns += 1
            return
        # A loop late by a few cycles is an ordinary OS's scheduling on a busy machine: counted, and summed up
        # once a minute at INFO. Later than LATE_PERIODS cycles it is a fault: the first warned about at once,
        # the rest of the minute summed up in one line.
        late = late_ns > LATE_PERIODS * self.period_ns
        if late and not self._window_late and now_ns - self._last_warning > WINDOW_NS:
            self._last_warning = now_ns
            log.warning("%s loop overran by %.1f ms (%d overruns so far)", self.name, late_ns / 1e6,
                        self.overruns - self.start_overruns)
        else:
            self._window_count += 1 if worth_saying or late else 0
            self._window_late += late
            self._window_worst_ns = max(self._window_worst_ns, late_ns)
        if not self._window_start:
            self._window_start = now_ns
        elif now_ns - self._window_start >= WINDOW_NS:
            self._report_window(now_ns)

    def _report_window(self, now_ns: int) -> None:
        """One line for the overruns not reported one by one since the window began: WARNING if any was late by
        more than LATE_PERIODS cycles, else INFO."""
        if self._window_count:
            log.log(logging.WARNING if self._window_late else logging.INFO,
                    "%s loop overran %d %s in the last %.0f s (%d by more than %d cycles), the worst by %.1f ms "
                    "(%d overruns so far)", self.name, self._window_count,
                    "time" if self._window_count == 1 else "times", (now_ns - self._window_start) / 1e9,
                    self._window_late, LATE_PERIODS, self._window_worst_ns / 1e6,
                    self.overruns - self.start_overruns)
        self._window_start, self._window_count, self._window_late, self._window_worst_ns = now_ns, 0, 0, 0

    def _record(self, period_ms: float) -> None:
        self._periods[self._samples % len(self._periods)] = period_ms
        self._samples += 1

    def summary(self) -> str:
        """The loop's timing (and a last line for the overruns not yet reported)."""
        if self._window_count:
            self._report_window(time.monotonic_ns())
        n = min(self._samples, len(self._periods))
        if n == 0:
            return f"{self.name}: no ticks"
        p = self._periods[:n]
        return (
            f"{self.name}: {self.ticks} ticks at {1e9 / self.period_ns:.0f} Hz, period p50 {np.median(p):.3f} ms "
            f"p99 {np.percentile(p, 99):.3f} ms worst {p.max():.3f} ms, {self.overruns} overruns"
            + (f" ({self.start_overruns} while starting)" if self.start_overruns else "")
        )
