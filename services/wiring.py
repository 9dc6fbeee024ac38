"""What every service's wiring shares: how it hands out what it publishes.

A wiring (``services/<service>/wiring.py``) is the call order of one service
per input and per tick: no Zenoh, no threads, no clock (its time comes from
its journal, :mod:`nwr.common.journal`). It publishes through ``out(key,
message)`` and reports through ``diag(level, code, text)`` (repeats of a code
within ``every_s`` are counted, not sent: ``every_s=0`` for a change of state
that must always be heard); the live process
maps those onto Zenoh, lockstep onto the other wirings, ``nwr verify`` onto
a comparison with the recording.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

Out = Callable[[str, Any], None]  # (relative key, message)


class Diag(Protocol):
    def __call__(self, level: str, code: str, message: str, *, every_s: float = 1.0) -> None:
        """Report (level, code, readable message); repeats of the code within ``every_s`` are rate limited."""


def no_diag(level: str, code: str, message: str, *, every_s: float = 1.0) -> None:
    """A ``diag`` that drops every report (lockstep, where nobody listens)."""
