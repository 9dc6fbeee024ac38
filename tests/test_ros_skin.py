"""The gateway's ROS 1 skin source: the pad mapping (pure), the wiring's samples, and a real rosmaster + rospy
publisher into ``nwr up`` (the pain reaches skin/pain for the mapped pad, and the arm withdraws)."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from ros_support import AIRSKIN_DEFINITION, AIRSKIN_TYPE, SCRIPTS, SYSTEM_PYTHON, require, rosmaster, stop, wait_for

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile, ZenohSection
from nwr.common.errors import ConfigError
from nwr.common.journal import Playback, Recording
from nwr.common.node import zenoh_config
from nwr.common.recordings import read_recording
from nwr.common.robot import load_description
from nwr.common.skinmap import ABSOLUTE_RANGE_HPA, map_values, pad_map
from nwr.services import cli
from nwr.services.gateway.sources import ros1
from nwr.services.gateway.sources.ros1 import ROS1_DEFAULT_PADS, Ros1Skin, settings_of
from nwr.services.gateway.wiring import GatewayWiring
from nwr.services.profile import load_profile

PADS = [p.name for p in load_description().pads]
N_VALUES = 11


def default_map() -> Any:
    return pad_map(ROS1_DEFAULT_PADS, PADS)


def rest(n: int = N_VALUES) -> list[float]:
    return [1000.0 + i for i in range(n)]


# -- the mapping ---------------------------------------------------------------------------------------------------

def test_the_default_mapping_puts_eleven_values_onto_the_ten_pads() -> None:
    pmap = default_map()
    assert (pmap.n_values, pmap.n_pads) == (11, 10)
    assert pmap.unused_indices() == [10] and pmap.unmapped_pads() == []
    assert pmap.describe() == ["device indices [10] are mapped to no pad (their values are ignored)"]
    assert pmap.table()[:2] == [(0, "shoulder_back"), (1, "shoulder_outer")] and pmap.table()[10] == (10, "")
    mapped = map_values(rest(), pmap)
    assert mapped.problems == {}
    assert mapped.absolute_hpa.tolist() == rest()[:10] and mapped.valid.all()


@pytest.mark.parametrize("index", range(N_VALUES))
@pytest.mark.parametrize("pad", PADS)
def test_a_press_on_any_index_reaches_exactly_the_pad_mapped_to_it(index: int, pad: str) -> None:
    mapping = [""] * N_VALUES
    mapping[index] = pad
    pmap = pad_map(mapping, PADS)
    values = rest()
    values[index] += 30.0
    mapped = map_values(values, pmap)
    expected = np.full(len(PADS), np.nan)
    expected[PADS.index(pad)] = values[index]
    np.testing.assert_array_equal(mapped.absolute_hpa, expected)
    assert pmap.unmapped_pads() == [p for p in PADS if p != pad]
    assert pmap.unused_indices() == [i for i in range(N_VALUES) if i != index]
    assert mapped.problems == {}  # the mapping's gaps are reported once, not with every message


def test_a_permuted_mapping_and_scale_and_offset() -> None:
    order = list(reversed(PADS)) + [""]
    pmap = pad_map(order, PADS, scale_hpa=0.01, offset_hpa=3.0)  # the device reports Pa, 3 hPa below absolute
    values = [101000.0 + 100 * i for i in range(N_VALUES)]
    mapped = map_values(values, pmap)
    for i, name in enumerate(order[:10]):
        assert mapped.absolute_hpa[PADS.index(name)] == pytest.approx(values[i] * 0.01 + 3.0)


@pytest.mark.parametrize(("mapping", "match"), [
    ([], "is empty"),
    (["nope"] + [""] * 10, r"gateway.ros1.pads\[0\] = 'nope' is no pad"),
    (["wrist_1", "wrist_1"], "names pad 'wrist_1' twice"),
])
def test_a_bad_mapping_is_refused_naming_the_field(mapping: list[str], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        pad_map(mapping, PADS)


@pytest.mark.parametrize("scale", [0.0, -1.0, math.nan, math.inf])
def test_a_bad_scale_is_refused(scale: float) -> None:
    with pytest.raises(ConfigError, match="scale"):
        pad_map(ROS1_DEFAULT_PADS, PADS, scale_hpa=scale)


def test_the_profile_refuses_a_mapping_of_unknown_pads_only_with_the_ros1_source(tmp_path: Path) -> None:
    bad = '[gateway.ros1]\npads = ["elbow", "wrist_1"]\n'
    (tmp_path / "sim.toml").write_text(bad)
    load_profile(str(tmp_path / "sim.toml"))  # the simulated skin does not use it
    (tmp_path / "ros.toml").write_text('[gateway]\nsource = "ros1"\n' + bad)
    with pytest.raises(ConfigError, match=r"gateway.ros1.pads\[0\] = 'elbow' is no pad"):
        load_profile(str(tmp_path / "ros.toml"))


@pytest.mark.parametrize("n", [0, 1, 5, 9, 10])
def test_a_short_message_invalidates_the_pads_it_does_not_reach(n: int) -> None:
    mapped = map_values(rest(n), default_map())
    assert mapped.valid.tolist() == [i < n for i in range(10)]
    assert "length" in mapped.problems and f"carries {n} values, the pad mapping 11" in mapped.problems["length"]
    if n < 10:
        assert PADS[n] in mapped.problems["length"]
    else:  # only the unused index is missing
        assert "pads" not in mapped.problems["length"]


@pytest.mark.parametrize("n", [12, 40])
def test_a_long_message_keeps_its_mapped_values_and_says_so(n: int) -> None:
    mapped = map_values(rest(n), default_map())
    assert mapped.valid.all() and mapped.absolute_hpa.tolist() == rest()[:10]
    assert "values past index 10 are ignored" in mapped.problems["length"]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("index", [0, 4, 9, 10])
def test_a_non_finite_value_invalidates_its_pad_only(bad: float, index: int) -> None:
    values = rest()
    values[index] = bad
    mapped = map_values(values, default_map())
    assert mapped.valid.tolist() == [i != index for i in range(10)]
    if index < 10:
        assert PADS[index] in mapped.problems["non_finite"]
    else:  # an unused index: nobody cares
        assert mapped.problems == {}


@pytest.mark.parametrize("value", [-1.0, 5000.5, 1e30, -1e300])
def test_an_absolute_pressure_the_pipeline_refuses_invalidates_its_pad(value: float) -> None:
    values = rest()
    values[2] = value
    mapped = map_values(values, default_map())
    assert mapped.valid.tolist() == [i != 2 for i in range(10)]
    assert f"outside {ABSOLUTE_RANGE_HPA[0]:g}..{ABSOLUTE_RANGE_HPA[1]:g} hPa" in mapped.problems["range"]


def test_an_overflowing_scale_invalidates_instead_of_overflowing() -> None:
    mapped = map_values([3e38] * N_VALUES, pad_map(ROS1_DEFAULT_PADS, PADS, scale_hpa=1000.0))
    assert not mapped.valid.any() and "range" in mapped.problems


@pytest.mark.parametrize("values", [["a"] * 11, [None] * 11, [1.0, "x"] + rest(9), 7.0, (), b"\x00\x01"])
def test_what_is_not_numbers_never_raises(values: Any) -> None:
    mapped = map_values(values, default_map())
    assert mapped.absolute_hpa.shape == (10,) and mapped.problems


# -- the wiring: a real skin's sample through the same baseline filter ----------------------------------------------

def test_the_wiring_publishes_ros_samples_with_invalid_pads_and_replays_them_exactly() -> None:
    profile = Profile()
    profile.gateway.source = "ros1"
    clock = ManualClock(10**9)
    journal = Recording(clock)
    outs: list[m.SkinPressure] = []
    wiring = GatewayWiring(profile, journal=journal, out=lambda k, msg: outs.append(msg), diag=lambda *a: None)
    wiring.origin()
    pmap = default_map()
    for k in range(60):
        clock.advance(1 / 30)
        values = rest()
        if k >= 40:
            values[4] += 8.0  # a press on elbow_outer
        if k == 50:
            values[7] = math.nan
        wiring.on_sample(map_values(values, pmap).absolute_hpa)
    assert all(o.source == "ros1" and o.touch_hpa == [] for o in outs)
    assert outs[-1].change_hpa[4] == pytest.approx(8.0, abs=0.05) and outs[-1].contact[4]
    assert outs[50].valid[7] is False and outs[50].change_hpa[7] == 0.0 and outs[51].valid[7] is True
    assert all(abs(c) < 0.05 for c in outs[39].change_hpa)

    again: list[m.SkinPressure] = []
    entries = journal.take()
    playback = Playback(entries)
    rerun = GatewayWiring(profile, journal=playback, out=lambda k, msg: again.append(msg), diag=lambda *a: None)
    for entry in entries[1:]:
        rerun.replay(entry, None)
    assert again == outs


# -- the adapter: rospy's callback and the watchdog, without ROS --------------------------------------------------

class FakeMessage:
    def __init__(self, pressures: Any) -> None:
        self.pressures = pressures


def adapter() -> tuple[Ros1Skin, list[m.SkinPressure], list[tuple[str, str, str]]]:
    profile = Profile()
    profile.gateway.source = "ros1"
    outs: list[m.SkinPressure] = []
    diags: list[tuple[str, str, str]] = []
    clock = ManualClock(10**9)
    wiring = GatewayWiring(profile, journal=Recording(clock), out=lambda k, msg: outs.append(msg),
                           diag=lambda *a: None)
    wiring.origin()
    skin = Ros1Skin(settings_of(profile), default_map(), wiring, threading.Lock(),
                    lambda level, code, text, **kw: diags.append((level, code, text)))
    return skin, outs, diags


def test_the_callback_never_raises_and_reports_each_bad_message() -> None:
    skin, outs, diags = adapter()
    skin.on_message(FakeMessage(rest()))
    skin.on_message(FakeMessage(rest(9)))
    skin.on_message(FakeMessage([math.nan] + rest(10)))
    skin.on_message(FakeMessage("not numbers"))
    skin.on_message(object())  # no pressures field at all
    assert len(outs) == 4 and outs[0].valid == [True] * 10
    assert outs[1].valid == [i < 9 for i in range(10)] and outs[2].valid == [i != 0 for i in range(10)]
    assert not any(outs[3].valid)
    assert [d[1] for d in diags] == ["ros1_bad_message"] * 4
    assert "carries 9 values" in diags[0][2] and "shoulder_back (index 0: nan)" in diags[1][2]
    assert "AttributeError" in diags[3][2]
    assert (skin.count, skin.bad) == (4, 4)


def test_a_skin_in_pascal_is_one_units_error_naming_the_scale_and_its_samples_have_no_valid_pad() -> None:
    skin, outs, diags = adapter()
    skin.on_message(FakeMessage([v * 100.0 for v in rest()]))  # Pa, not hPa
    assert len(outs) == 1 and not any(outs[0].valid)
    assert [d[:2] for d in diags] == [("error", "ros1_units")]
    assert "every value on /bullet_ros/airskin_status is outside 0..5000 hPa" in diags[0][2]
    assert "scale_hpa = 0.01" in diags[0][2]
    skin.on_message(FakeMessage(rest()))  # the units fixed at the device: no error
    assert len(diags) == 1 and all(outs[1].valid)


def test_the_watchdog_reports_a_silent_topic_and_a_master_gone() -> None:
    skin, _, diags = adapter()
    skin.last -= 10.0
    skin.check("http://127.0.0.1:1")  # nothing listens on port 1
    assert [d[1] for d in diags] == ["ros1_no_messages", "ros1_master_unreachable"]
    assert skin.stale and skin.master_down
    skin.on_message(FakeMessage(rest()))
    assert not skin.stale


def test_without_rospy_the_ros1_source_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ros1, "ROS_PYTHON_DIRS", ())
    with pytest.raises(ConfigError, match="needs rospy.*apt install python3-rospy"):
        ros1.import_ros("nwr_no_such_ros_module")


@pytest.mark.parametrize(("message_type", "definition", "match"), [
    ("AirskinStatus", "float32[] pressures", "write package/Name"),
    ("airskin_msgs/AirskinStatus", "float32[ pressures", "no valid message definition"),
    ("nwr_no_such_msgs/Status", "", "cannot be imported from ROS"),
])
def test_a_message_type_that_cannot_be_had_is_one_line(message_type: str, definition: str, match: str) -> None:
    # In a child process: genpy comes from the system's packages, which this process must not take on.
    code = ("import sys\nfrom nwr.common.errors import ConfigError\n"
            "from nwr.services.gateway.sources.ros1 import Settings, message_class\n"
            f"try:\n    message_class(Settings(message_type={message_type!r}, definition={definition!r}))\n"
            "except ConfigError as exc:\n    print(exc)\n    sys.exit(3)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    if "needs rospy" in proc.stdout:
        require("genpy")
    assert proc.returncode == 3, proc.stderr
    assert __import__("re").search(match, proc.stdout), proc.stdout


# -- a real ROS 1: rosmaster, an AIRSKIN-like rospy node, nwr up -----------------------------------------------------

PRESSED_INDEX = 4  # elbow_outer by the default mapping
PORT = 17950


@pytest.mark.e2e
@pytest.mark.slow
def test_a_press_on_a_ros1_skin_reaches_skin_pain_and_the_arm_withdraws(tmp_path: Path) -> None:
    require("rospy", "genpy", rosmaster=True)
    pad = ROS1_DEFAULT_PADS[PRESSED_INDEX]
    profile_path = tmp_path / "profile.toml"
    profile_path.write_text(f'[zenoh]\nbase_port = {PORT}\n[recorder]\ndirectory = "{tmp_path}"\n'
                            '[gateway]\nsource = "ros1"\nrate_hz = 30.0\n')
    output = tmp_path / "session.mcap"
    pains: list[m.SkinPain] = []
    pressures: list[m.SkinPressure] = []
    lock = threading.Lock()

    def on_pain(sample: zenoh.Sample) -> None:
        with lock:
            pains.append(keys.codec(keys.SKIN_PAIN).decode(sample.payload.to_bytes()))

    def on_pressure(sample: zenoh.Sample) -> None:
        with lock:
            pressures.append(keys.codec(keys.SKIN_PRESSURE).decode(sample.payload.to_bytes()))

    with rosmaster(tmp_path) as (env, _master):
        pub_log = (tmp_path / "publisher.log").open("wb")
        press = tmp_path / "press"  # while it exists, a press of 15 hPa (PL 4) on value 4
        publisher = subprocess.Popen(
            [SYSTEM_PYTHON, str(SCRIPTS / "airskin_publisher.py"), "/bullet_ros/airskin_status", AIRSKIN_TYPE,
             AIRSKIN_DEFINITION, str(N_VALUES), str(PRESSED_INDEX), "15.0", str(press), "30.0"],
            env=env, stdout=pub_log, stderr=subprocess.STDOUT)
        up_log_path = tmp_path / "up.log"
        up_log = up_log_path.open("wb")
        up = subprocess.Popen([sys.executable, "-m", "nwr.services.cli", "--profile", str(profile_path), "up",
                               "--output", str(output)], env=env, stdout=up_log, stderr=subprocess.STDOUT)
        try:
            with zenoh.open(zenoh_config(ZenohSection(base_port=PORT))) as session:
                subs = [session.declare_subscriber(keys.key("ur10e", keys.SKIN_PAIN), on_pain),
                        session.declare_subscriber(keys.key("ur10e", keys.SKIN_PRESSURE), on_pressure)]

                def flowing() -> bool:  # the gateway's baseline is the pads' at rest, the pain estimated
                    with lock:
                        return len(pressures) > 30 and len(pains) > 30

                def pained() -> bool:
                    with lock:
                        return any(p.level[PRESSED_INDEX] >= 3 for p in pains)

                assert wait_for(flowing, 120.0), up_log_path.read_text()[-5000:]
                time.sleep(2.0)  # the arm on its task
                press.touch()
                try:
                    assert wait_for(pained, 10.0), up_log_path.read_text()[-5000:]
                    time.sleep(0.8)
                finally:
                    press.unlink()
                time.sleep(3.0)  # the reflex's return
                for sub in subs:
                    sub.undeclare()
        finally:
            up.send_signal(signal.SIGINT)
            code = up.wait(60)
            stop(publisher)
            up_log.close()
            pub_log.close()
    log = up_log_path.read_text()
    assert code == 0, log[-5000:]
    assert "Traceback" not in log, log[-5000:]
    with lock:
        assert all(p.source == "ros1" for p in pressures) and pressures
        assert all(p.valid == [True] * len(PADS) for p in pressures)
        pressed = [p for p in pains if p.level[PRESSED_INDEX] >= 3]
        # Only the mapped pad hurts.
        assert all(max(lv for i, lv in enumerate(p.level) if i != PRESSED_INDEX) <= 1 for p in pains)
        assert pressed and pressed[0].strongest is not None
    records, _ = read_recording(output)
    status_key = keys.planner_status(load_profile().bridge.active_planner)
    statuses = [r.message for r in records if r.key == status_key]
    reflexes = [s for s in statuses if s.mode == "REFLEX" and s.active]
    assert reflexes, "the pain made no reflex"
    assert any(s.reflex is not None and s.reflex.contact.pad == PADS.index(pad) for s in reflexes)
    # The gateway's journal re-makes its samples of the real skin bit for bit (nwr verify).
    assert cli.main(["verify", str(output)]) == 0
