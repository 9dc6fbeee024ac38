"""A hostile ROS 1 skin (every value NaN, every value in Pa, messages of 3 values) in front of the real
pipeline: the arm never runs on a skin it cannot read. The figures are printed (pytest -s) before they are
checked: the fastest point of the arm while the skin lies, the time to detection and the status reported."""

from __future__ import annotations

import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from pipeline import Pipeline
from ros_support import AIRSKIN_DEFINITION, AIRSKIN_TYPE, SCRIPTS, SYSTEM_PYTHON, require, rosmaster, stop

from nwr.common import keys
from nwr.common.robot import RobotModel, load_description

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

N_VALUES = 11
HOSTILE_S = 2.0  # how long each hostile skin lasts
MODEL = RobotModel(load_description())
# Guards, not measurements: how long to wait for something that must happen before calling the test failed.
WAIT_S = 120.0


def peak_speed(state: Any) -> float:
    """The fastest point of the arm the bridge's limits watch (pads, elbow, flange), m/s."""
    return float(np.linalg.norm(MODEL.speed_jacobians(np.asarray(state.q)) @ np.asarray(state.dq), axis=1).max())


def test_a_hostile_ros1_skin_never_keeps_the_arm_running_on_what_it_cannot_read(tmp_path: Path, pipeline: Pipeline
                                                                                ) -> None:
    require("rospy", "genpy", rosmaster=True)
    pipeline.configure('[gateway]\nsource = "ros1"\nrate_hz = 30.0\n')
    states: list[tuple[float, Any]] = []  # (arrival, monotonic s; state)
    diags: list[tuple[float, Any]] = []
    lock = threading.Lock()

    def on_state(sample: zenoh.Sample) -> None:
        with lock:
            states.append((time.monotonic(), keys.codec(keys.ROBOT_STATE).decode(sample.payload.to_bytes())))

    def on_diag(sample: zenoh.Sample) -> None:
        with lock:
            diags.append((time.monotonic(), keys.codec("diag/x").decode(sample.payload.to_bytes())))

    mode = tmp_path / "mode"
    figures: dict[str, dict[str, Any]] = {}
    with rosmaster(tmp_path) as (env, _master):
        pub_log = (tmp_path / "publisher.log").open("wb")
        publisher = subprocess.Popen(
            [SYSTEM_PYTHON, str(SCRIPTS / "airskin_publisher.py"), "/bullet_ros/airskin_status", AIRSKIN_TYPE,
             AIRSKIN_DEFINITION, str(N_VALUES), "0", "0.0", str(tmp_path / "no-press"), "30.0", str(mode)],
            env=env, stdout=pub_log, stderr=subprocess.STDOUT)
        pipeline.start("up", "up", "--no-record", env=env)
        try:
            with pipeline.session() as session:
                subs = [session.declare_subscriber(keys.key("ur10e", keys.ROBOT_STATE), on_state),
                        session.declare_subscriber(keys.key("ur10e", "diag/*"), on_diag)]

                def moving_ok() -> bool:  # the task runs on a good skin
                    with lock:
                        recent = [s for t, s in states[-25:]]
                    return len(recent) == 25 and all(s.status == "ok" for s in recent) \
                        and max(peak_speed(s) for s in recent) > 0.02

                pipeline.wait_until(moving_ok, WAIT_S, "the task running on a good skin")
                for name in ("nan", "pa", "short"):
                    mode.write_text(name)
                    t0 = time.monotonic()
                    time.sleep(HOSTILE_S)
                    mode.unlink()
                    t1 = time.monotonic()
                    with lock:
                        during = [(t - t0, s) for t, s in states if t0 <= t <= t1]
                        codes = sorted({d.code for t, d in diags if t0 <= t <= t1 + 0.2})
                    held = [(t, s) for t, s in during if s.status != "ok" or s.safety_mode == "reduced"]
                    detected = held[0][0] if held else None
                    late = [peak_speed(s) for t, s in during if detected is not None and t >= detected + 0.5]
                    figures[name] = {
                        "detected_s": detected,
                        "statuses": sorted({s.status for t, s in during}),
                        "safety_modes": sorted({s.safety_mode for t, s in during}),
                        "peak_m_s": max((peak_speed(s) for t, s in during), default=0.0),
                        "peak_after_detection_m_s": max(late, default=None),
                        "codes": codes,
                    }
                    pipeline.wait_until(moving_ok, 30.0, f"the task to resume after {name}: {figures[name]}")
                for sub in subs:
                    sub.undeclare()
        finally:
            code = pipeline.stop("up")
            stop(publisher)
            pub_log.close()
    for name, f in figures.items():
        print(f"hostile skin {name}: {f}")
    assert code == 0, pipeline.log("up")[-5000:]
    for name in ("nan", "pa"):  # no valid pad: the skin is stale, the task held, the arm at rest
        f = figures[name]
        assert f["detected_s"] is not None and f["detected_s"] < 0.5, f
        assert "stale_skin" in f["statuses"], f
        assert f["peak_after_detection_m_s"] is not None and f["peak_after_detection_m_s"] < 0.005, f
    assert "ros1_units" in figures["pa"]["codes"], figures["pa"]
    short = figures["short"]  # 7 pads blind: the reduced limits while they are
    assert short["detected_s"] is not None and short["detected_s"] < 0.6, short
    assert "reduced" in short["safety_modes"] and "skin_blind_pad" in short["codes"], short
