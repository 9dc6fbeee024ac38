"""``nwr verify`` on live sessions: every strategy, and a planner killed (SIGKILL) and restarted mid-session."""

from __future__ import annotations

import signal
import time

import pytest
from pipeline import SHORT_SCRIPT, Pipeline

from nwr.services.tools.recordings.verify import verify

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def test_every_strategy_and_a_killed_planner_verify_bit_for_bit(tmp_path, pipeline: Pipeline):
    output = tmp_path / "killed.mcap"
    strategies = ["cartesian-smooth", "location", "uniform", "whole-arm"]  # cartesian: tests/test_e2e.py
    pipeline.start("recorder", "run", "recorder", "--output", str(output))
    with pipeline.node() as node:
        assert not node.wait_for(["recorder"], 30.0)
        pipeline.start("bridge", "run", "bridge", "--active", strategies[0])
        for name in strategies:
            pipeline.start(name, "run", "planner", "--name", name, "--reflex", name)
        pipeline.start("gain", "run", "gain")
        assert not node.wait_for(["bridge", "gain", *(f"planner-{s}" for s in strategies)], 30.0)
        pipeline.start("gateway", "run", "gateway", "--script", str(SHORT_SCRIPT), "--exit-at-end", ends=True)
        time.sleep(5.0)  # past the first reflex (2.0 s of the script is the first touch)
        active = strategies[0]
        pipeline.stop(active, sig=signal.SIGKILL, grace_s=10)  # the active planner dies without a word
        time.sleep(1.0)  # the bridge holds the arm; then the planner is back and takes over
        pipeline.start(active, "run", "planner", "--name", active, "--reflex", active)
        assert not node.wait_for([f"planner-{active}"], 30.0)
    assert pipeline.wait("gateway", 60) == 0
    time.sleep(2.0)  # the last return
    pipeline.stop_all(sig=signal.SIGTERM, grace_s=20)  # the recorder last: it was started first

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
