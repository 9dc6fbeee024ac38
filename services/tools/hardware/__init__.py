"""Stand-ins for the lab's hardware: the UR controller emulator that the unmodified ur_rtde talks to
(:mod:`.ur_emulator`: its sockets, sessions and dashboard), built from the RTDE protocol (:mod:`.rtde`), the
emulated arm (:mod:`.ur_arm`) and the controller that runs ur_rtde's control script (:mod:`.ur_controller`);
franky-sim's Franka served on loopback (:mod:`.franky_sim`). :func:`stand_in` runs one as a process of its own."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def stand_in(module: str, log_path: Path, *args: str) -> Iterator[subprocess.Popen[str]]:
    """``python -m MODULE ARGS`` in a process of its own, ready (its first line on stdout starts with ``ready``),
    then ended (SIGTERM, SIGKILL after 10 s; a caller may have ended it already). Its log (stderr) goes to
    ``log_path``; one that does not come up raises RuntimeError with what it printed and its log's tail."""
    with open(log_path, "w") as log:  # its log: a pipe nobody drains would block it
        process = subprocess.Popen([sys.executable, "-m", module, *args], stdout=subprocess.PIPE, stderr=log,
                                   text=True)
        try:
            assert process.stdout is not None
            line = process.stdout.readline()
            if not line.startswith("ready"):
                log.flush()
                raise RuntimeError(f"{module} did not start ({line.strip() or 'no ready line'}): "
                                   f"{Path(log_path).read_text()[-2000:]}")
            yield process
        finally:
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
            if process.stdout is not None:
                process.stdout.close()
