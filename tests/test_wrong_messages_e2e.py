"""One bad message must not stop the pipeline: every kind of wrong-but-decodable message, into a running ``nwr up``.

A peer on the embedded network (as a buggy peer of another version, or
anyone on a lab PC's LAN) publishes each message of ``wrong_messages.py``
on its key, three times; then one service is killed. Checked: no service
exits, no traceback, the killed one is restarted and the others never
stopped, the arm kept its owner and its limits, every refusal was reported
on the refusing service's diag key, and the recording stays readable.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh
from pipeline import Pipeline, alive
from wrong_messages import catalogue

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import load_profile
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

FORGED_SEQ = 10**6  # the peer's messages count from here: the pipeline's own never get there in a test
TOLERANCE = 0.01


def test_wrong_messages_on_every_key_and_a_killed_service(tmp_path: Path, pipeline: Pipeline) -> None:
    output = tmp_path / "session.mcap"
    desc = load_description()
    active = load_profile().bridge.active_planner
    wanted = {"bridge", f"planner-{active}", "gain", "gateway"}
    pipeline.start("up", "up", "--output", str(output))
    try:
        with pipeline.session() as session:
            pipeline.wait_alive(session, wanted, 60.0)
            time.sleep(2.0)  # the arm on its task
            wrong = catalogue(desc, active=active, seq=FORGED_SEQ, stamp_ns=time.monotonic_ns())
            publishers: dict[str, zenoh.Publisher] = {}
            for k in range(3):
                for i, w in enumerate(wrong):
                    pub = publishers.get(w.key)
                    if pub is None:
                        pub = publishers[w.key] = session.declare_publisher(keys.key("ur10e", w.key))
                    message = w.message
                    if message.seq == FORGED_SEQ:
                        message = msgspec.structs.replace(message, seq=FORGED_SEQ + 100 * k + i)
                    pub.put(keys.codec(w.key).encode(message))
                    time.sleep(0.01)
            time.sleep(1.0)
            assert wanted <= alive(session), "a service died of a wrong message"
            # Kill the gain estimator: nwr up restarts it, the others keep running.
            gain = subprocess.run(["pgrep", "-f", f"{pipeline.profile} .*run gain"], capture_output=True,
                                  text=True)
            pids = [int(p) for p in gain.stdout.split()]
            assert len(pids) == 1, gain
            os.kill(pids[0], signal.SIGKILL)
            time.sleep(0.5)
            assert "gain" not in alive(session)
            pipeline.wait_alive(session, wanted, 30.0, "the killed service restarted")
            time.sleep(2.0)
    finally:
        code = pipeline.stop("up")
    log = pipeline.log("up")
    assert code == 0, log
    assert "Traceback" not in log, log
    assert "gain exited unexpectedly" in log and "restarted gain" in log, log
    exited = [line for line in log.splitlines() if "exited unexpectedly" in line]
    assert len(exited) == 1, exited  # the killed one only

    records, _ = read_recording(output)
    # Every refusal reported by the refusing service, once per cause (rate-limited), not per message.
    diags = [r.message for r in records if r.key.startswith("diag/")]
    refusals = [d for d in diags if d.code.startswith("refused_")]
    for service in ("bridge", f"planner-{active}", "gain", "gateway"):
        assert any(d.service == service for d in refusals), (service, {d.service for d in refusals})
    assert len(refusals) < 3 * len(wrong)
    assert any(d.code == "unfit_for_mcap" for d in diags)  # the recorder kept what MCAP's record cannot hold

    # The arm: the bridge's own states (the forged ones are in the recording too) kept owner and limits.
    model = RobotModel(desc)
    limits = load_profile().bridge.limits
    states = [r.message for r in records if r.key == keys.ROBOT_STATE and r.message.seq < FORGED_SEQ
              and r.message.backend == "sim" and len(r.message.q) == len(desc.joints)]
    states = [s for s in states if isinstance(s, m.RobotState) and np.all(np.abs(s.q) < 10)]
    assert len(states) > 100
    # On the embedded network a command put on the active planner's own key, with a seq ahead of the
    # planner's, is that planner's for the bridge (only the secure deployment's access control tells them
    # apart): "velocity 1e6 rad/s" (phase REFLEX) is obeyed, clipped and held to the withdrawal's limit, and
    # the arm slows from it to the task's. Every point stays within the bridge's hardest bound.
    for s in states:
        assert s.owner == active, s
        speed = float(np.linalg.norm(model.speed_jacobians(s.q) @ np.asarray(s.dq), axis=1).max())
        assert speed <= limits.withdrawal_speed_m_s + TOLERANCE, (s.stamp_ns, speed)
    assert states[-1].safety_mode == "normal"
    assert any(s.status == "ok" and max(abs(v) for v in s.dq) > 1e-3 for s in states[-50:]), "the task stopped"
