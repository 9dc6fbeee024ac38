"""The real processes over Zenoh on loopback: a short scripted session, checked from its recording."""

from __future__ import annotations

import threading
import time

import msgspec
import pytest
import zenoh
from pipeline import SHORT_SCRIPT, Pipeline

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import GainSection, ZenohSection
from nwr.common.launch import load_script
from nwr.common.node import zenoh_config
from nwr.common.recordings import read_recording
from nwr.common.robot import load_description
from nwr.services.gain.core import GainEstimator
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.verify import verify

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

def intruder(stop: threading.Event, counts: dict[str, int], cfg: ZenohSection, owner: str) -> None:
    """Publishes garbage and a foreign planner's commands into the running pipeline."""
    with zenoh.open(zenoh_config(cfg)) as session:
        pressure = session.declare_publisher(keys.key("ur10e", keys.SKIN_PRESSURE))
        command = session.declare_publisher(keys.key("ur10e", keys.robot_command("intruder")))
        # The active planner's own key: without the secure router anyone may put there.
        spoofed = session.declare_publisher(keys.key("ur10e", keys.robot_command(owner)))
        foreign = m.VelocityCommand(seq=0, stamp_ns=0, owner="intruder", dq=[3.0] * 6, trace=m.Trace(0, 0))
        nan = m.PositionCommand(seq=0, stamp_ns=0, owner=owner, q=[float("nan")] * 6, trace=m.Trace(0, 0))
        time.sleep(3.0)
        while not stop.wait(0.5):
            pressure.put(b"\x92\x01garbage")
            command.put(msgspec.msgpack.encode(foreign))
            spoofed.put(msgspec.msgpack.encode(nan))
            counts["sent"] += 1


@pytest.mark.parametrize("reflex", ["cartesian", "uniform", "location", "cartesian-smooth"])
def test_scripted_session_end_to_end(tmp_path, pipeline: Pipeline, reflex):
    port = pipeline.port
    output = tmp_path / "session.mcap"
    stop = threading.Event()
    counts = {"sent": 0}
    thread = threading.Thread(target=intruder, args=(stop, counts, pipeline.zenoh, reflex), daemon=True)
    thread.start()
    try:
        # The scripted world: the peaks below are the script's (the physics world's: tests/test_physics_e2e.py).
        proc = pipeline.run("demo", "--world", "scripted", "--script", str(SHORT_SCRIPT), "--output", str(output),
                            "--reflex", reflex, timeout_s=120)
    finally:
        stop.set()
        thread.join(5)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    assert "all 4 scripted touches as expected" in proc.stdout, log
    assert counts["sent"] > 5

    records, metadata = read_recording(output)
    assert metadata["session"]["robot"] == "ur10e"
    assert f'"base_port":{port}' in metadata["session"]["profile"]
    desc = load_description()
    touches = analysis.summarize(records, desc)
    script = load_script(str(SHORT_SCRIPT))
    estimator = GainEstimator(GainSection(), desc.pads)
    assert len(touches) == len(script.touch)
    for touch, scripted in zip(touches, script.touch):
        assert touch.name == scripted.pad
        assert touch.peak_hpa == pytest.approx(scripted.peak_hpa, abs=0.5)
        level, gain = estimator.gain(touch.pad, scripted.peak_hpa)
        if gain > 0:
            assert touch.reflex_seq > 0, touch
            assert touch.onset_latency_ms is not None and 0 < touch.onset_latency_ms < 1000
            assert touch.withdrawal_mm is not None and touch.withdrawal_mm > 1.0, touch  # moved away
            if reflex.startswith("cartesian"):
                # The joint-space reflexes move far: within the Cartesian limits their returns take seconds, and
                # this short script's next touch and end come first (tests/test_limits.py has them in full).
                assert touch.resumed_after_s is not None and touch.resumed_after_s < 5.0
                assert touch.return_error_rad is not None and touch.return_error_rad < 5e-3  # at the saved pose
        else:
            assert touch.reflex_seq == 0, touch

    # The task went on after the last reflex (a joint-space reflex is still on its way back).
    status = [r.message for r in records if r.key.startswith("reflex/") and r.key.endswith("/status")]
    last_reflex = max(i for i, s in enumerate(status) if s.mode == "REFLEX")
    if reflex.startswith("cartesian"):
        after = [s for s in status[last_reflex:] if s.mode == "TASK"]
        assert after and after[-1].task_time_s > after[0].task_time_s + 1.0
    else:
        assert any(s.mode == "RETURNING" for s in status[last_reflex:])

    # Every command that moved the arm carries the trace of a real skin sample.
    skin_seqs = {r.message.seq for r in records if r.key == "skin/pressure"}
    commands = [r.message for r in records if r.key == keys.robot_command(reflex) and r.message.owner == reflex]
    assert {type(c) for c in commands if c.phase == "REFLEX"} == {
        m.VelocityCommand if reflex.startswith("cartesian") else m.PositionCommand}
    traced = {c.trace.seq for c in commands if c.trace.seq >= 0}
    assert traced and traced <= skin_seqs

    # Hostile input was reported, not obeyed.
    diags = [r.message for r in records if r.key.startswith("diag/")]
    codes = {(d.service, d.code) for d in diags}
    assert ("gain", "decode_error") in codes
    assert ("bridge", "command_rejected") in codes
    states = [r.message for r in records if r.key == "robot/state"]
    assert max(s.rejected for s in states) > 5
    # The intruder's 3 rad/s never reached the arm: no reflex or task of this
    # script moves wrist 3, which the intruder drives at 3 rad/s.
    assert max(abs(s.dq[5]) for s in states) < 0.5

    # Every service re-runs from its journal to the same outputs, bit for bit,
    # the intruder's commands (journaled, refused) included.
    results = verify(output)
    assert {r.service for r in results} == {"gateway", "gain", "bridge", f"planner-{reflex}"}
    assert all(r.verdict == "identical" for r in results), [r.format() for r in results]
