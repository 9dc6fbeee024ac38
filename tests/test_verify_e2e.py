"""``nwr verify`` on live sessions: every strategy, and a planner killed (SIGKILL) and restarted mid-session."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nwr.common.config import ZenohSection
from nwr.common.node import Node
from nwr.services.tools.recordings.verify import verify

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

SCRIPT = Path(__file__).parent / "data" / "short.toml"
PORT = 17950


def nwr(profile: Path, *args: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def test_every_strategy_and_a_killed_planner_verify_bit_for_bit(tmp_path):
    profile = tmp_path / "profile.toml"
    profile.write_text(f'[zenoh]\nbase_port = {PORT}\n[recorder]\ndirectory = "{tmp_path}"\n')
    output = tmp_path / "killed.mcap"
    strategies = ["cartesian-smooth", "location", "uniform", "whole-arm"]  # cartesian: tests/test_e2e.py
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        procs["recorder"] = nwr(profile, "run", "recorder", "--output", str(output))
        with Node("test", "ur10e", ZenohSection(base_port=PORT), token=False) as node:
            assert not node.wait_for(["recorder"], 30.0)
            procs["bridge"] = nwr(profile, "run", "bridge", "--active", strategies[0])
            for name in strategies:
                procs[name] = nwr(profile, "run", "planner", "--name", name, "--reflex", name)
            procs["gain"] = nwr(profile, "run", "gain")
            assert not node.wait_for(["bridge", "gain", *(f"planner-{s}" for s in strategies)], 30.0)
            procs["gateway"] = nwr(profile, "run", "gateway", "--script", str(SCRIPT), "--exit-at-end")
            time.sleep(5.0)  # past the first reflex (2.0 s of the script is the first touch)
            active = strategies[0]
            procs[active].send_signal(signal.SIGKILL)  # the active planner dies without a word
            procs[active].wait(10)
            time.sleep(1.0)  # the bridge holds the arm; then the planner is back and takes over
            procs[active] = nwr(profile, "run", "planner", "--name", active, "--reflex", active)
            assert not node.wait_for([f"planner-{active}"], 30.0)
        assert procs["gateway"].wait(60) == 0
        time.sleep(2.0)  # the last return
    finally:
        for name in [n for n in procs if n != "recorder"] + ["recorder"]:
            if procs[name].poll() is None:
                procs[name].send_signal(signal.SIGTERM)
                procs[name].wait(20)

    results = verify(output)
    lines = [r.format() for r in results]
    runs = {(r.service, r.run, r.runs) for r in results}
    active = strategies[0]
    assert (f"planner-{active}", 1, 2) in runs and (f"planner-{active}", 2, 2) in runs, lines
    assert {r.service for r in results} == {"gateway", "gain", "bridge", *(f"planner-{s}" for s in strategies)}
    assert all(r.verdict == "identical" for r in results), lines
    for run in (1, 2):
        planner = next(r for r in results if r.service == f"planner-{active}" and r.run == run)
        assert planner.outputs[f"robot/command/{active}"] > 100, planner.format()
