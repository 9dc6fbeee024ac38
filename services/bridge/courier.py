"""A robot controller's commands sent from a thread of their own: the bridge's control loop never waits on one.

A controller library may wait inside any command for the controller's answer (ur_rtde waits for its control
script's readiness, read through the controller's data stream, before every command, and for a stop's
acknowledgement after it). A data stream that freezes, or a controller that stops answering, would then hold the
control loop, and with it the robot state the bridge publishes, for as long as that lasts. The loop instead
*posts* its commands; one thread sends them, in order:

- a posted ``motion`` replaces any motion posted but not yet sent (the newest target is the one that counts), a
  ``kick`` (of the controller's watchdog) any kick not yet sent;
- a posted ``stop`` drops the motions not yet sent before it (they were never started);
- while a command is under way, nothing after it reaches the controller: no motion, no kick (a controller that
  watches the bridge stops the arm on its own once the kicks stay away).

The loop reads :meth:`Courier.busy_s` (how long the command under way has been), :meth:`idle`, and
:meth:`error` (a command that raised: the loop treats it as it treated the call's error before).

Without a thread (``threaded=False``: the tests' doubles, which answer at once), a posted command is sent at
once, in the caller, and its error raised there.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Literal

log = logging.getLogger(__name__)

Kind = Literal["motion", "stop", "kick"]


class Courier:
    """Sends posted commands from one thread, in order (see the module's docstring)."""

    def __init__(self, name: str, *, threaded: bool = True) -> None:
        self.name = name
        self._cv = threading.Condition()
        self._queue: list[tuple[Kind, Callable[[], Any]]] = []
        self._since: float | None = None  # when the command under way began (monotonic s); None: none is
        self._error: BaseException | None = None
        self._closed = False
        self.sent = 0
        self.replaced = 0  # motions and kicks a newer one replaced before they were sent
        self._thread: threading.Thread | None = None
        if threaded:
            self._thread = threading.Thread(target=self._run, name=name, daemon=True)
            self._thread.start()

    @property
    def threaded(self) -> bool:
        return self._thread is not None

    @property
    def closed(self) -> bool:
        return self._closed

    def post(self, kind: Kind, call: Callable[[], Any]) -> None:
        """Send ``call`` after what was posted before it (see the module's docstring for what replaces what)."""
        if self._thread is None:
            self.sent += 1
            call()
            return
        with self._cv:
            if kind in ("motion", "kick"):
                kept = [item for item in self._queue if item[0] != kind]
                self.replaced += len(self._queue) - len(kept)
                self._queue = kept
            elif kind == "stop":
                self._queue = [item for item in self._queue if item[0] != "motion"]
            self._queue.append((kind, call))
            self._cv.notify()

    def busy_s(self) -> float:
        """How long the command under way has been (0: none is)."""
        since = self._since
        return 0.0 if since is None else time.monotonic() - since

    def idle(self) -> bool:
        """Nothing under way and nothing waiting."""
        with self._cv:
            return self._since is None and not self._queue

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait until :meth:`idle` (at most ``timeout`` s); whether it is."""
        with self._cv:
            return self._cv.wait_for(lambda: self._since is None and not self._queue, timeout)

    def clear(self) -> None:
        """Drop what was posted and not yet sent (a connection that was lost: it is not sent on the next one)."""
        with self._cv:
            self._queue.clear()

    def error(self) -> BaseException | None:
        """The error a command raised since the last call (and what was waiting after it was dropped), or None."""
        with self._cv:
            error, self._error = self._error, None
            return error

    def close(self, timeout: float | None = None) -> None:
        """Send what is waiting, then end the thread (waited for at most ``timeout`` s)."""
        with self._cv:
            self._closed = True
            self._cv.notify()
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: bool(self._queue) or self._closed)
                if not self._queue:
                    return  # closed, and nothing left
                _, call = self._queue.pop(0)
                self._since = time.monotonic()
            try:
                call()
            except Exception as exc:  # noqa: BLE001 - handed to the loop, which knows what a failed command means
                with self._cv:
                    self._error = exc
                    self._queue.clear()  # nothing after a failed command: the loop decides what comes next
            finally:
                with self._cv:
                    self.sent += 1
                    self._since = None
                    self._cv.notify_all()
