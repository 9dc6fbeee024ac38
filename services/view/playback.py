"""Play, pause, seek and speed over a recording's timeline (pure: times come in as arguments).

The timeline is the sorted log times of the view's output for a recording
(:func:`nwr.services.view.core.timeline`). :class:`Player` maps wall time to
log time: while playing, log time advances at ``speed`` times wall time from
an anchor set at every play, seek and speed change; paused, it stands still.
``advance(now)`` returns the slice of the timeline that has become due.
"""

from __future__ import annotations

import math
from typing import Literal

from nwr.services.view.core import index_at

Status = Literal["playing", "paused", "ended"]
MIN_SPEED = 0.01
MAX_SPEED = 100.0


def clamp_speed(speed: float) -> float:
    if math.isnan(speed) or speed < MIN_SPEED:
        return MIN_SPEED
    return min(float(speed), MAX_SPEED)


class Player:
    def __init__(self, times: list[int], *, speed: float = 1.0) -> None:
        if not times:
            raise ValueError("the recording has no message the view can show: nothing to play")
        if any(b < a for a, b in zip(times, times[1:])):
            raise ValueError("timeline times must be sorted")
        self.times = times
        self.start_ns = times[0]
        self.end_ns = times[-1]
        self.status: Status = "paused"
        self.speed = clamp_speed(speed)
        self.position = 0  # index of the next output to emit
        self._log_anchor = self.start_ns  # log time at the wall anchor
        self._wall_anchor = 0

    def current_time(self, now_ns: int) -> int:
        if self.status != "playing":
            return self._log_anchor
        return min(self.end_ns, self._log_anchor + round((now_ns - self._wall_anchor) * self.speed))

    def _anchor(self, now_ns: int) -> None:
        self._log_anchor = self.current_time(now_ns)
        self._wall_anchor = now_ns

    def play(self, now_ns: int) -> None:
        if self.status == "ended":
            return  # seek first to play again
        self._anchor(now_ns)
        self.status = "playing"

    def pause(self, now_ns: int) -> None:
        if self.status == "playing":
            self._anchor(now_ns)
            self.status = "paused"

    def set_speed(self, speed: float, now_ns: int) -> None:
        self._anchor(now_ns)
        self.speed = clamp_speed(speed)

    def seek(self, log_ns: int, now_ns: int) -> tuple[int, int]:
        """Jump to ``log_ns`` (clamped to the recording); returns the slice of outputs
        of the last ``period`` before it is the caller's to re-send (see adapter)."""
        target = max(self.start_ns, min(int(log_ns), self.end_ns))
        self._log_anchor = target
        self._wall_anchor = now_ns
        self.position = index_at(self.times, target)
        if self.status == "ended":
            self.status = "paused"
        return self.position, target

    def advance(self, now_ns: int) -> tuple[int, int]:
        """The outputs now due, as ``[start, stop)`` indexes; ends playback after the last."""
        if self.status != "playing":
            return self.position, self.position
        start = self.position
        stop = index_at(self.times, self.current_time(now_ns))
        self.position = stop
        if stop >= len(self.times):
            self._log_anchor = self.end_ns
            self.status = "ended"
        return start, stop

    def wait_s(self, now_ns: int, cap_s: float = 0.02) -> float:
        """How long the adapter may sleep before the next output is due (at most ``cap_s``)."""
        if self.status != "playing" or self.position >= len(self.times):
            return cap_s
        ahead = (self.times[self.position] - self.current_time(now_ns)) / self.speed / 1e9
        return max(0.0, min(cap_s, ahead))
