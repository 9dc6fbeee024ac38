"""One robot, one pipeline: a second pipeline on a robot whose keys a live one drives refuses to start, clearly;
a service its own launcher restarts is not refused; another robot name runs beside it."""

from __future__ import annotations

import os
import signal
from collections.abc import Callable

import pytest
from pipeline import WAIT_S, Pipeline

from nwr.common import keys
from nwr.common.node import Node

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def owners_until(pipeline: Pipeline, node: Node, done: Callable[[list[keys.Owner]], bool], what: str
                 ) -> list[keys.Owner]:
    return pipeline.wait_until(lambda: found if done(found := node.owners()) else None, WAIT_S, what, every_s=0.2)


def test_a_second_pipeline_on_a_driven_robot_refuses_and_a_restart_of_its_own_does_not(pipeline: Pipeline) -> None:
    pipeline.start("first", "up")
    with pipeline.node() as node:
        found = owners_until(pipeline, node, lambda o: {x.service for x in o} >= {"bridge", "gain", "gateway"},
                             "the first pipeline's services alive")
        instance = found[0].instance
        assert all(o.instance == instance for o in found), found

        # A second `nwr demo` with the same settings refuses before it starts anything.
        demo = pipeline.run("demo", "--no-record", timeout_s=60)
        assert demo.returncode != 0
        assert "already driven by another pipeline" in demo.stderr and "bridge (pipeline" in demo.stderr, \
            demo.stderr[-2000:]
        # A bridge started alone refuses too, in one line naming the live one.
        alone = pipeline.run("run", "bridge", timeout_s=60)
        assert alone.returncode == 2, alone.stderr[-2000:]
        assert f"its bridge (pipeline {instance}" in alone.stderr, alone.stderr[-2000:]

        # The first pipeline's own bridge, killed, is restarted by its launcher and not refused.
        bridge = next(o for o in found if o.service == "bridge")
        os.kill(bridge.pid, signal.SIGKILL)
        again = owners_until(pipeline, node, lambda o: any(x.service == "bridge" and x.pid != bridge.pid for x in o),
                             "the killed bridge restarted")
        assert next(o for o in again if o.service == "bridge").instance == instance

        # Another robot name on the same machine runs beside it.
        pipeline.start("other", "run", "gain", env={**os.environ, "NWR_ROBOT": "other"})
        with pipeline.node("other") as beside:
            owners_until(pipeline, beside, lambda o: [x.service for x in o] == ["gain"],
                         "a gain estimator on robot 'other'")
        assert pipeline.stop("other", grace_s=20) == 0
