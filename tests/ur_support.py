"""The UR controller emulator as a process for the tests (tests/test_ur_emulator.py, tests/test_ur_bridge_e2e.py).

ur_rtde reaches a controller only on its fixed ports (RTDE 30004, dashboard
29999, script 30003): one emulator at a time, on 127.0.0.1.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

UR_PORTS = (30004, 29999, 30003)
EMULATOR_PRIORITY = 30  # SCHED_FIFO


def skip_unless_free(*extra: int) -> None:
    """Skip the test where a port the emulator needs is taken on 127.0.0.1 (ur_rtde cannot use others)."""
    for port in (*UR_PORTS, *extra):
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", port)) == 0:
                pytest.skip(f"port {port} on 127.0.0.1 is in use (the emulator needs {UR_PORTS} and {extra})")


@contextlib.contextmanager
def emulator_process(log_path: Path, *args: str) -> Iterator[subprocess.Popen[str]]:
    """``python -m nwr.services.tools.hardware.ur_emulator --host 127.0.0.1 --realtime-priority 30 ARGS``, ready (it
    printed ``ready``), then ended."""
    log = open(log_path, "w")  # its log: a pipe nobody drains would block it
    # The controller real-time (where permitted): a real one is a machine of its own, and an emulator starved beside
    # the loaded pipeline trips its own watchdog (docs/bridge.md).
    process = subprocess.Popen([sys.executable, "-m", "nwr.services.tools.hardware.ur_emulator", "--host", "127.0.0.1",
                                "--realtime-priority", str(EMULATOR_PRIORITY), *args], stdout=subprocess.PIPE,
                               stderr=log, text=True)
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        assert line.startswith("ready"), line
        yield process
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()
        log.close()
