"""Injectable clocks. Cores take time from message stamps or from one of these.

``MonotonicClock`` reads ``time.monotonic_ns()``: on Linux one clock shared by
every process of the machine, so stamps from different services compare
directly. ``ManualClock`` is for tests and lockstep replay.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    def now_ns(self) -> int: ...


class MonotonicClock:
    def now_ns(self) -> int:
        return time.monotonic_ns()


class ManualClock:
    def __init__(self, start_ns: int = 0) -> None:
        self.t_ns = start_ns

    def now_ns(self) -> int:
        return self.t_ns

    def advance(self, seconds: float) -> None:
        self.t_ns += round(seconds * 1e9)
