"""What every service's wiring shares: how it hands out what it publishes.

A wiring (``services/<service>/wiring.py``) is the call order of one service
per input and per tick: no Zenoh, no threads, no clock (its time comes from
its journal, :mod:`nwr.common.journal`). It publishes through ``out(key,
message)`` and reports through ``diag(level, code, text)``; the live process
maps those onto Zenoh, lockstep onto the other wirings, ``nwr verify`` onto
a comparison with the recording.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

Out = Callable[[str, Any], None]  # (relative key, message)
Diag = Callable[[str, str, str], None]  # (level, code, readable message)


def no_diag(level: str, code: str, message: str) -> None:
    """A ``diag`` that drops every report (lockstep, where nobody listens)."""
