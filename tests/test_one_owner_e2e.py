"""One robot, one pipeline: a second pipeline on a robot whose keys a live one drives refuses to start, clearly;
a service its own launcher restarts is not refused; another robot name runs beside it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nwr.common.config import ZenohSection
from nwr.common.node import Node

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

PORT = 18750  # a mesh of its own, away from the other end-to-end tests
# Guards, not measurements: how long to wait for something that must happen before calling the test failed.
WAIT_S = 60.0


def nwr(profile: Path, *args: str, env: dict[str, str] | None = None, timeout: float = 60.0) \
        -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), *args],
                          capture_output=True, text=True, timeout=timeout, env={**os.environ, **(env or {})})


def owners_until(node: Node, done: object, what: str) -> list:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        found = node.owners()
        if done(found):  # type: ignore[operator]
            return found
        time.sleep(0.2)
    pytest.fail(f"{what} within {WAIT_S:.0f} s (owners: {node.owners()})")


def test_a_second_pipeline_on_a_driven_robot_refuses_and_a_restart_of_its_own_does_not(tmp_path: Path) -> None:
    profile = tmp_path / "profile.toml"
    profile.write_text(f'[zenoh]\nbase_port = {PORT}\n')
    with (tmp_path / "first.log").open("wb") as log:
        first = subprocess.Popen([sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "up"],
                                 stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        with Node("test", "ur10e", ZenohSection(base_port=PORT), token=False) as node:
            found = owners_until(node, lambda o: {x.service for x in o} >= {"bridge", "gain", "gateway"},
                                 "the first pipeline's services were not alive")
            instance = found[0].instance
            assert all(o.instance == instance for o in found), found

            # A second `nwr demo` with the same settings refuses before it starts anything.
            demo = nwr(profile, "demo", "--no-record")
            assert demo.returncode != 0
            assert "already driven by another pipeline" in demo.stderr and "bridge (pipeline" in demo.stderr, \
                demo.stderr[-2000:]
            # A bridge started alone refuses too, in one line naming the live one.
            alone = nwr(profile, "run", "bridge")
            assert alone.returncode == 2, alone.stderr[-2000:]
            assert f"its bridge (pipeline {instance}" in alone.stderr, alone.stderr[-2000:]

            # The first pipeline's own bridge, killed, is restarted by its launcher and not refused.
            bridge = next(o for o in found if o.service == "bridge")
            os.kill(bridge.pid, signal.SIGKILL)
            again = owners_until(node, lambda o: any(x.service == "bridge" and x.pid != bridge.pid for x in o),
                                 "the killed bridge was not restarted")
            assert next(o for o in again if o.service == "bridge").instance == instance

            # Another robot name on the same machine runs beside it.
            with (tmp_path / "other.log").open("wb") as log:
                other = subprocess.Popen([sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "run",
                                          "gain"], env={**os.environ, "NWR_ROBOT": "other"}, stdout=log,
                                         stderr=subprocess.STDOUT)
            try:
                with Node("test", "other", ZenohSection(base_port=PORT), token=False) as beside:
                    owners_until(beside, lambda o: [x.service for x in o] == ["gain"],
                                 "a gain estimator on robot 'other' did not start")
            finally:
                other.send_signal(signal.SIGINT)
                assert other.wait(20) == 0
    finally:
        first.send_signal(signal.SIGINT)
        try:
            first.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(first.pid, signal.SIGKILL)
            first.wait()
