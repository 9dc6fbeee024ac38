"""ROS 1 for the tests: whether it is here (NWR_REQUIRE_ROS=1: it must be), a private rosmaster on loopback,
and the scripts the system's Python runs with the real rospy / rosbag (tests/ros_scripts/)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

SYSTEM_PYTHON = "/usr/bin/python3"
SCRIPTS = Path(__file__).resolve().parent / "ros_scripts"
# The AIRSKIN message as the lab's ROS 1 skin node publishes it (as in the default profile).
AIRSKIN_TYPE = "airskin_msgs/AirskinStatus"
AIRSKIN_DEFINITION = "float32[] pressures"


def require(*modules: str, rosmaster: bool = False) -> None:
    """Skip unless the system's Python has ``modules`` (and rosmaster is on PATH); fail instead with
    NWR_REQUIRE_ROS=1 (CI)."""
    missing = []
    if not Path(SYSTEM_PYTHON).exists():
        missing.append(SYSTEM_PYTHON)
    else:
        for module in modules:
            proc = subprocess.run([SYSTEM_PYTHON, "-c", f"import {module}"], capture_output=True, text=True)
            if proc.returncode != 0:
                missing.append(f"{module} ({proc.stderr.strip().splitlines()[-1:]})")
    if rosmaster and shutil.which("rosmaster") is None:
        missing.append("rosmaster")
    if missing:
        why = f"ROS 1 is missing: {', '.join(missing)} (Debian: python3-rospy python3-rosbag python3-rosmaster ...)"
        if os.environ.get("NWR_REQUIRE_ROS") == "1":
            pytest.fail(why + "; NWR_REQUIRE_ROS=1 requires it")
        pytest.skip(why)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def ros_env(tmp_path: Path, port: int) -> dict[str, str]:
    """An environment whose ROS stays on loopback, on its own master, with its logs under tmp_path."""
    env = dict(os.environ)
    env.update(ROS_MASTER_URI=f"http://127.0.0.1:{port}", ROS_IP="127.0.0.1", ROS_HOSTNAME="127.0.0.1",
               ROS_HOME=str(tmp_path / "ros_home"), ROS_LOG_DIR=str(tmp_path / "ros_home" / "log"))
    return env


def wait_port(port: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return True
        except OSError:
            time.sleep(0.1)
    return False


@contextmanager
def rosmaster(tmp_path: Path) -> Iterator[tuple[dict[str, str], subprocess.Popen[bytes]]]:
    """A ``rosmaster --core`` of its own on a free loopback port: (its environment, its process)."""
    port = free_port()
    env = ros_env(tmp_path, port)
    log = (tmp_path / "rosmaster.log").open("wb")
    proc = subprocess.Popen(["rosmaster", "--core", "-p", str(port)], env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        assert wait_port(port, 20.0), (tmp_path / "rosmaster.log").read_text()
        yield env, proc
    finally:
        stop(proc)
        log.close()


def stop(proc: subprocess.Popen[bytes], timeout_s: float = 10.0) -> int | None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)
    return proc.returncode


def wait_for(condition: Any, timeout_s: float, every_s: float = 0.1) -> bool:
    """Whether ``condition()`` came true within ``timeout_s`` (a guard, not a measurement)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(every_s)
    return False
