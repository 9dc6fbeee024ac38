"""A standby planner's forged status cannot send the arm anywhere: embedded and secure deployment.

The scenario: two planners (cartesian active, uniform standby). From
``ATTACK_S`` into the session, a peer with the standby planner's key (on the
embedded network anyone; in the secure deployment the standby planner's own
certificate) publishes ``reflex/uniform/status`` claiming it is active, in
REFLEX, with a saved pose the arm was never at. The operator then switches
to uniform and back to cartesian. The arm must move no faster than the task
itself, only to poses it had been at or on the task's own path, and the
incoming planner must report the refused claim, naming the claimant.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from pipeline import Pipeline
from test_secure import Lab, RoutedPipeline, lab, pipeline_factory  # noqa: F401  (fixtures)

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.node import zenoh_config
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight
from nwr.services.bridge.cartesian import CartesianLimiter, Limits
from nwr.services.bridge.wiring import task_peak_speed

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

MODEL = RobotModel(load_description())
ACTIVE, STANDBY = "cartesian", "uniform"
ATTACK_S = 2.5  # the forged statuses start (s from the first skin sample)
SWITCHES = ((5.0, STANDBY), (8.5, ACTIVE))
DURATION_S = 14.0
FORGED_OFFSET = np.array([0.6, -0.4, 0.3, 0.5, 0.8, 1.0])  # the forged saved pose: home plus this, rad
POSE_TOLERANCE_RAD = 0.05


def _script(tmp: Path) -> Path:
    path = tmp / "quiet.toml"
    path.write_text(f"# The task alone, no touch: the switches and the forged claims are all that happens.\n"
                    f"duration_s = {DURATION_S}\n")
    return path


def forger(put_status: Callable[[m.PlannerStatus], None], put_switch: Callable[[m.SwitchRequest], None],
           first_skin: list[int], stop: threading.Event, done: list[str]) -> None:
    """The forged statuses from ATTACK_S at 200 Hz, and the operator's two switches."""
    forged = (load_description().home + FORGED_OFFSET).tolist()
    pending = list(SWITCHES)
    seq = 10_000
    while not stop.wait(0.005):
        if not first_skin:
            continue
        t = (time.monotonic_ns() - first_skin[0]) / 1e9
        if t >= ATTACK_S:
            put_status(m.PlannerStatus(seq=seq, stamp_ns=time.monotonic_ns(), name=STANDBY, strategy=STANDBY,
                                       mode="REFLEX", task_time_s=3.0, saved_pose=forged, active=True))
            seq += 1
        if pending and t >= pending[0][0]:
            _, name = pending.pop(0)
            put_switch(m.SwitchRequest(seq=len(done), stamp_ns=time.monotonic_ns(), name=name, requested_by="test"))
            done.append(name)


def _task_path(profile: Profile) -> tuple[np.ndarray, float]:
    """The task's own path (one period, finely sampled) and its fastest point's speed, m/s (the bridge's figure)."""
    desc = load_description()
    task = FigureEight(profile.planner.task, desc)
    s = np.linspace(0.0, profile.planner.task.period_s, 2400, endpoint=False)
    limiter = CartesianLimiter(MODEL, Limits.of(profile.bridge.limits, MODEL, "bridge.limits"))
    return np.array([task.position(x) for x in s]), task_peak_speed(task, profile.planner.task.period_s, limiter)


def _point_speed(q: Any, dq: Any) -> float:
    return float(np.linalg.norm(MODEL.speed_jacobians(q) @ np.asarray(dq), axis=1).max())


def check(records: list[Any], capsys: pytest.CaptureFixture[str], where: str) -> None:
    states = [r.message for r in records if r.key == "robot/state"]
    t0 = min(r.message.stamp_ns for r in records if r.key == "skin/pressure")
    owners = [s.owner for s in states]
    assert [o for i, o in enumerate(owners) if i == 0 or o != owners[i - 1]] == [ACTIVE, STANDBY, ACTIVE], \
        "the two switches did not both happen"
    forged = [r for r in records if r.key == keys.planner_status(STANDBY) and r.message.seq >= 10_000]
    assert len(forged) > 100  # the forged statuses were out there (the recorder saw them)

    # Both handovers completed, each with the new owner's first command soon after the switch (a few cycles on
    # a quiet machine; the bound leaves room for a loaded one: this test is about claims, not timing).
    handovers = {s.handover.owner: s.handover for s in states if s.handover is not None and s.handover.first_command_ns}
    assert set(handovers) == {ACTIVE, STANDBY}
    for h in handovers.values():
        assert 0 < (h.first_command_ns - h.switched_ns) / 2e6 <= 50.0, h

    path, task_peak = _task_path(Profile())
    before = np.array([s.q for s in states if s.stamp_ns < t0 + ATTACK_S * 1e9])
    # From the attack to the end of the skin stream (then the bridge stops the arm: the session's end).
    t_end = max(r.message.stamp_ns for r in records if r.key == "skin/pressure")
    after = [s for s in states if t0 + ATTACK_S * 1e9 <= s.stamp_ns <= t_end]
    assert len(after) > 300
    known = np.vstack([before, path])
    farthest, fastest = 0.0, 0.0
    for s in after:
        q = np.asarray(s.q)
        farthest = max(farthest, float(np.min(np.max(np.abs(known - q), axis=1))))
        fastest = max(fastest, _point_speed(q, s.dq))
    # The refusal, naming the claimant, on the incoming planner's diagnostics.
    refused = [r.message for r in records if r.key == f"diag/planner-{ACTIVE}" and STANDBY in r.message.message
               and r.message.code.startswith("claim")]
    with capsys.disabled():
        print(f"\n{where}: after the forged statuses and the switches, the arm's fastest point moved at "
              f"{fastest:.3f} m/s (the task's own peak {task_peak:.3f} m/s) and came at most {farthest:.3f} rad "
              f"from every pose it had been at or the task's path; {len(refused)} refusal(s) naming {STANDBY!r}: "
              f"{refused[0].message if refused else ''}")
    # The bridge's tracking of a live stream jitters around the planned speed by up to about 15 % (its own
    # issue); a forged move is held to the Cartesian limit at best (0.25 m/s), never to this.
    assert fastest <= task_peak * 1.2
    assert farthest <= POSE_TOLERANCE_RAD
    assert refused


def test_forged_status_on_the_embedded_network(tmp_path: Path, pipeline: Pipeline,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    output = tmp_path / "forged.mcap"
    stop, done, first = threading.Event(), [], []

    def attacker() -> None:
        with pipeline.node() as node:
            node.subscribe(keys.SKIN_PRESSURE, lambda s: first.append(s.stamp_ns) if not first else None)
            forger(node.publisher(keys.planner_status(STANDBY)), node.publisher(keys.CONTROL_ACTIVE), first, stop,
                   done)

    thread = threading.Thread(target=attacker, daemon=True)
    thread.start()
    try:
        proc = pipeline.run("demo", "--world", "scripted", "--script", str(_script(tmp_path)),
                            "--planners", f"{ACTIVE},{STANDBY}", "--output", str(output), timeout_s=150)
    finally:
        stop.set()
        thread.join(5)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert done == [STANDBY, ACTIVE]
    records, _ = read_recording(output)
    check(records, capsys, "embedded")


def test_forged_status_in_the_secure_deployment(lab: Lab, tmp_path: Path,  # noqa: F811
                                                pipeline_factory: list[RoutedPipeline],  # noqa: F811
                                                capsys: pytest.CaptureFixture[str]) -> None:
    pipeline = RoutedPipeline(tmp_path, lab)
    pipeline_factory.append(pipeline)
    pipeline.start_router()
    pipeline.spawn("bridge", ["run", "bridge", "--active", ACTIVE], "bridge")
    for name in (ACTIVE, STANDBY):
        pipeline.spawn(f"planner-{name}", ["run", "planner", "--name", name, "--reflex", name], name)
    pipeline.spawn("gain", ["run", "gain"], "gain")
    pipeline.spawn("recorder", ["run", "recorder", "--session", "forged", "--output", str(pipeline.output),
                                "--strategy", ACTIVE], "recorder")
    stop, done, first = threading.Event(), [], []

    def attacker() -> None:
        # The standby planner's own certificate puts its forged statuses; the operator's switches.
        with zenoh.open(zenoh_config(lab.zenoh(pipeline.port, STANDBY))) as own, \
                zenoh.open(zenoh_config(lab.zenoh(pipeline.port, "operator"))) as operator:
            status = keys.codec(keys.planner_status(STANDBY))
            switch = keys.codec(keys.CONTROL_ACTIVE)
            operator.declare_subscriber(keys.key("ur10e", keys.SKIN_PRESSURE),
                                        lambda _s: first.append(time.monotonic_ns()) if not first else None)
            forger(lambda msg: own.put(keys.key("ur10e", keys.planner_status(STANDBY)), status.encode(msg)),
                   lambda msg: operator.put(keys.key("ur10e", keys.CONTROL_ACTIVE), switch.encode(msg)),
                   first, stop, done)

    thread = threading.Thread(target=attacker, daemon=True)
    thread.start()
    pipeline.spawn("gateway", ["run", "gateway", "--wait-for",
                               f"bridge,gain,recorder,planner-{ACTIVE},planner-{STANDBY}",
                               "--script", str(_script(tmp_path)), "--exit-at-end"], "gateway", ends=True)
    try:
        pipeline.wait_gateway(timeout_s=90)
    finally:
        stop.set()
        thread.join(10)
    pipeline.stop_all()
    assert done == [STANDBY, ACTIVE]
    records, _ = read_recording(pipeline.output)
    check(records, capsys, "secure")
