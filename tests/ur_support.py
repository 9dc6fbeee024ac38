"""The UR controller emulator as a process for the tests (tests/test_ur_emulator.py, tests/test_ur_bridge_e2e.py).

ur_rtde reaches a controller only on its fixed ports (RTDE 30004, dashboard
29999, script 30003): one emulator at a time, on 127.0.0.1.
"""

from __future__ import annotations

import contextlib
import socket
import subprocess
from pathlib import Path

import pytest

from nwr.services.tools.hardware import stand_in

UR_PORTS = (30004, 29999, 30003)
EMULATOR_PRIORITY = 30  # SCHED_FIFO


def skip_unless_free(*extra: int) -> None:
    """Skip the test where a port the emulator needs is taken on 127.0.0.1 (ur_rtde cannot use others)."""
    for port in (*UR_PORTS, *extra):
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", port)) == 0:
                pytest.skip(f"port {port} on 127.0.0.1 is in use (the emulator needs {UR_PORTS} and {extra})")


def emulator_process(log_path: Path, *args: str) -> contextlib.AbstractContextManager[subprocess.Popen[str]]:
    """``python -m nwr.services.tools.hardware.ur_emulator --host 127.0.0.1 --realtime-priority 30 ARGS``, ready (it
    printed ``ready``), then ended."""
    # The controller real-time (where permitted): a real one is a machine of its own, and an emulator starved beside
    # the loaded pipeline trips its own watchdog (docs/bridge.md).
    return stand_in("nwr.services.tools.hardware.ur_emulator", log_path, "--host", "127.0.0.1",
                    "--realtime-priority", str(EMULATOR_PRIORITY), *args)
