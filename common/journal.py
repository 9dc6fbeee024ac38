"""A service's journal: what it received, in the order it handled it, and every clock reading it made.

Each service's wiring (``services/<service>/wiring.py``) takes its time from
a journal instead of a clock, and opens an entry (:meth:`Recording.begin`)
for every input it handles: a message (named by key, sequence number and
stamp: the message itself is in the recording), a tick of its loop, a
liveliness token, a measurement of the arm. Inputs, their order and the clock
readings are all a deterministic wiring needs to be re-run exactly: ``nwr
verify`` (:mod:`nwr.services.tools.recordings.verify`) feeds a recording's journal back
through the same wiring (:class:`Playback`) and compares what it publishes
with what was recorded.

- :class:`Recording`: the live services and lockstep runs; entries are
  taken in batches (:meth:`Recording.take`) and published on
  ``journal/<service>`` (:class:`Batcher`), recorded like any other channel.
- :class:`Playback`: ``nwr verify``; :class:`Divergence` when the wiring
  asks for another input or more clock readings than the live run did.
- :class:`Untracked`: a clock with nothing kept (the bench's lower bound).

Nothing here imports Zenoh or reads a clock of its own.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any, Protocol

from nwr.common import messages as m
from nwr.common.clock import Clock
from nwr.common.config import Profile
from nwr.common.errors import NwrError
from nwr.common.launch import encode_profile

Entry = m.JournalEntry
# A service's journal is published in batches this often, s (docs/verify.md).
JOURNAL_PERIOD_S = 0.1


class Divergence(NwrError):
    """A re-run wiring did something its journal says the live run did not."""


class Journal(Protocol):
    """What a wiring needs of its journal: an entry per input, and the time."""

    def begin(self, input: str, key: str = "", message: Any = None, *, arg: int = 0, text: str = "",
              data: Sequence[float] = ()) -> None: ...

    def now_ns(self) -> int: ...

    def discard(self) -> None: ...


class Recording:
    """Keeps an entry per input, with the clock readings its handler made.

    Not thread-safe: the service calls it under the lock that serialises its
    handlers, and takes batches under that lock too.
    """

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.entries: list[Entry] = []
        self._now: list[int] = []  # the current entry's readings
        self.count = 0  # entries kept so far

    def begin(self, input: str, key: str = "", message: Any = None, *, arg: int = 0, text: str = "",
              data: Sequence[float] = ()) -> None:
        self._now = []
        seq, stamp = (message.seq, message.stamp_ns) if message is not None else (-1, 0)
        self.entries.append(Entry(input, self._now, key, seq, stamp, arg, text, list(data)))
        self.count += 1

    def now_ns(self) -> int:
        t = self.clock.now_ns()
        self._now.append(t)
        return t

    def discard(self) -> None:
        """The current entry changed nothing (a tick with no cycle due): not kept."""
        if self.entries and self.entries[-1].now is self._now:
            self.entries.pop()
            self.count -= 1

    def take(self) -> list[Entry]:
        """The entries kept since the last take."""
        out, self.entries = self.entries, []
        return out


class Untracked:
    """A clock behind the journal's interface; nothing kept."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock

    def begin(self, input: str, key: str = "", message: Any = None, *, arg: int = 0, text: str = "",
              data: Sequence[float] = ()) -> None:
        pass

    def now_ns(self) -> int:
        return self.clock.now_ns()

    def discard(self) -> None:
        pass


class Playback:
    """Gives a re-run wiring its journal back: each ``begin`` opens the next entry, each ``now_ns`` its next reading."""

    def __init__(self, entries: Sequence[Entry]) -> None:
        self.entries = entries
        self.index = -1  # the entry being re-run
        self._readings: list[int] = []
        self._used = 0

    @property
    def current(self) -> Entry | None:
        return self.entries[self.index] if 0 <= self.index < len(self.entries) else None

    def peek(self) -> Entry | None:
        """The entry the next ``begin`` opens (None at the end)."""
        nxt = self.index + 1
        return self.entries[nxt] if nxt < len(self.entries) else None

    def begin(self, input: str, key: str = "", message: Any = None, *, arg: int = 0, text: str = "",
              data: Sequence[float] = ()) -> None:
        self.finish_entry()
        self.index += 1
        entry = self.current
        if entry is None:
            raise Divergence(f"the re-run handled an input ({input}) after the journal's last entry")
        if entry.input != input:
            raise Divergence(f"entry {self.index}: the re-run handled {input!r} where the live run handled "
                             f"{entry.input!r}")
        self._readings = entry.now
        self._used = 0

    def now_ns(self) -> int:
        if self._used >= len(self._readings):
            entry = self.current
            raise Divergence(f"entry {self.index} ({entry.input if entry else 'none'}): the re-run read the clock "
                             f"more often than the live run ({len(self._readings)} readings)")
        t = self._readings[self._used]
        self._used += 1
        return t

    def discard(self) -> None:
        entry = self.current
        raise Divergence(f"entry {self.index} ({entry.input if entry else 'none'}): the live run kept an entry the "
                         "re-run found had nothing to do")

    def finish_entry(self) -> None:
        """Checks that the current entry's handler used every reading the live one made."""
        if self.current is not None and self._used != len(self._readings):
            raise Divergence(f"entry {self.index} ({self.current.input}): the re-run read the clock "
                             f"{self._used} times, the live run {len(self._readings)}")


def service_config(profile: Profile, **params: Any) -> str:
    """The journal's ``config``: the effective profile and a service's own parameters, JSON."""
    return json.dumps({"profile": json.loads(encode_profile(profile)), "params": params}, sort_keys=True)


class Batcher:
    """One service run's journal as messages: a batch per call, numbered from 0, the config on the first."""

    def __init__(self, service: str, run_ns: int, config: str) -> None:
        self.service = service
        self.run_ns = run_ns
        self.config = config
        self.seq = 0
        self.bytes = 0  # encoded size published so far (the journal's cost)

    def batch(self, entries: list[Entry], stamp_ns: int, *, final: bool = False) -> m.Journal | None:
        """The next batch (None: nothing to send, unless it is the first or the final one)."""
        if not entries and not final and self.seq > 0:
            return None
        msg = m.Journal(self.seq, stamp_ns, self.service, self.run_ns, entries,
                        self.config if self.seq == 0 else "", final)
        self.seq += 1
        return msg
