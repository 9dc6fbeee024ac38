"""When a new or stronger contact may (re)start a reflex: debounce, hysteresis and rate limits.

A reflex storm is a reflex restarted at every sample: a pad that flickers
between pressed and not pressed (each press a "new contact"), or a forged
skin stream. The paper's rule, "update the reflex on a new or stronger
contact", stays; this module decides what is new and how often (docs/reflexes.md,
"Restarts"), on the planner's injected clock (the time the pain message was
received), never on the message's own stamp, which a forged stream sets.

- A pad's touch begins at its first sample with a gain and ends once its gain
  has been 0 for ``gap_s``: a press after a shorter gap is the same touch
  (time hysteresis), counted as a flicker.
- A token bucket per pad and one over every pad limit the (re)starts; a
  contact ``escalate_at_once`` stronger than the current reflex passes the
  pad's own bucket without spending its tokens (the gain is at most 1, and
  the overall bucket still applies). A start from the task is never refused
  (it stops the task) but spends tokens like any other.
- A new contact refused by a bucket stays pending until it restarts the
  reflex or its touch ends: the next pain message that shows it tries again.

Pure: numbers in, booleans and diagnostics (level, code, message) out; each diagnostic is also logged.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from nwr.common.config import RestartSection

log = logging.getLogger(__name__)

NEVER_NS = np.iinfo(np.int64).min // 2
# A pad's flicker or refused restarts are reported once, then at most this often (per pad and kind), ns.
NOTE_EVERY_NS = 10_000_000_000


class Bucket:
    """A token bucket: ``burst`` tokens, one more every ``interval_s``."""

    def __init__(self, burst: int, interval_s: float) -> None:
        self.burst = float(burst)
        self.interval_ns = interval_s * 1e9
        self.tokens = float(burst)
        self.at_ns: int | None = None

    def available(self, now_ns: int) -> bool:
        if self.at_ns is not None and now_ns > self.at_ns:
            self.tokens = min(self.burst, self.tokens + (now_ns - self.at_ns) / self.interval_ns)
        if self.at_ns is None or now_ns > self.at_ns:
            self.at_ns = now_ns
        return self.tokens >= 1.0

    def take(self) -> None:
        self.tokens = max(0.0, self.tokens - 1.0)


class Restarts:
    def __init__(self, cfg: RestartSection, pads: list[str]) -> None:
        n = len(pads)
        self.cfg = cfg
        self.pads = pads
        self.gap_ns = round(cfg.gap_s * 1e9)
        self.window_ns = round(cfg.flicker_window_s * 1e9)
        self.last_on_ns = np.full(n, NEVER_NS, dtype=np.int64)  # each pad's last sample with a gain
        self.pending = np.zeros(n, dtype=bool)  # a new contact refused by a rate limit, not yet served
        self.buckets = [Bucket(cfg.pad_burst, cfg.pad_interval_s) for _ in range(n)]
        self.overall = Bucket(cfg.burst, cfg.interval_s)
        self.presses: list[deque[int]] = [deque(maxlen=cfg.flicker_presses) for _ in range(n)]
        self.again = np.zeros(n, dtype=np.int64)  # presses within a touch since the last flicker report
        self.refused = np.zeros(n, dtype=np.int64)  # restarts refused since the last report
        self.flickers = 0  # presses within a touch, in all (a flicker is one touch)
        self.refusals = 0  # restarts refused by a rate limit, in all
        self.notes: list[tuple[str, str, str]] = []
        self._noted: dict[tuple[str, int], int] = {}

    def observe(self, previous: np.ndarray, gains: np.ndarray, now_ns: int) -> np.ndarray:
        """One pain message's gains (``previous``: the last message's): the pads whose touch begins now."""
        on = gains > 0.0
        pressed = on & ~(previous > 0.0)
        ongoing = now_ns - self.last_on_ns < self.gap_ns
        new = pressed & ~ongoing
        self.last_on_ns[on] = now_ns
        self.pending &= on | ongoing  # a touch that has ended is served: nothing pending
        for pad in np.flatnonzero(pressed & ongoing).tolist():
            self._pressed_again(pad, now_ns)
        return new

    def _pressed_again(self, pad: int, now_ns: int) -> None:
        self.flickers += 1
        self.again[pad] += 1
        presses = self.presses[pad]
        presses.append(now_ns)
        if len(presses) < self.cfg.flicker_presses or now_ns - presses[0] > self.window_ns:
            return
        cfg = self.cfg
        if self._note("pad_flicker", pad, now_ns,
                      f"pad {self.pads[pad]} flickers: pressed again {len(presses)} times within "
                      f"{(now_ns - presses[0]) / 1e9:.3f} s, each after less than planner.restarts.gap_s "
                      f"({cfg.gap_s:g} s) without gain; taken as one touch, which does not restart the reflex. "
                      f"A faulty pad or connection, or a forged skin stream ({int(self.again[pad])} such presses "
                      "since the last report)"):
            self.again[pad] = 0

    def admit(self, pad: int, gain: float, current: float, now_ns: int, *, new: bool, force: bool = False) -> bool:
        """Whether a new (``new``) or stronger contact on ``pad`` may (re)start the reflex now; ``force``: a start
        from the task, which is never refused (it spends the tokens all the same)."""
        bucket = self.buckets[pad]
        escalates = gain >= current + self.cfg.escalate_at_once  # outside the pad's budget: the gain is at most 1
        pad_ok = bucket.available(now_ns) or escalates
        overall_ok = self.overall.available(now_ns)
        if force or (pad_ok and overall_ok):
            if force or bucket.tokens >= 1.0:
                bucket.take()
            self.overall.take()
            self.pending[pad] = False
            return True
        if new:
            self.pending[pad] = True
        self.refusals += 1
        self.refused[pad] += 1
        cfg = self.cfg
        limit = (f"pad {self.pads[pad]}'s rate limit (planner.restarts.pad_burst = {cfg.pad_burst}, one more every "
                 f"pad_interval_s = {cfg.pad_interval_s:g} s)" if not pad_ok else
                 f"the overall rate limit (planner.restarts.burst = {cfg.burst}, one more every interval_s = "
                 f"{cfg.interval_s:g} s)")
        if self._note("reflex_rate_limited", pad, now_ns,
                      f"a {'new' if new else 'stronger'} contact on pad {self.pads[pad]} (G = {gain:.3f}, the "
                      f"reflex's {current:.3f}) waits to restart the reflex: {limit}; the first pain message that "
                      "still shows it once allowed restarts it, one planner.restarts.escalate_at_once "
                      f"({cfg.escalate_at_once:g}) stronger than the reflex at once ({int(self.refused[pad])} "
                      "waited since the last report): a long escalating press, a faulty pad or a forged skin "
                      "stream"):
            self.refused[pad] = 0
        return False

    def _note(self, code: str, pad: int, now_ns: int, message: str) -> bool:
        """A warning about ``pad``: the first, then at most every NOTE_EVERY_NS; whether it was given."""
        last = self._noted.get((code, pad))
        if last is not None and now_ns - last < NOTE_EVERY_NS:
            return False
        self._noted[(code, pad)] = now_ns
        log.warning("%s", message)
        self.notes.append(("warning", code, message))
        return True
