"""``nwr import``: a ROS 1 bag written by the real rosbag -> a recording that reads back, replays in lockstep
against two reflex services, and compares; and the bags it refuses."""

from __future__ import annotations

import logging
import random
import subprocess
from pathlib import Path

import pytest
from ros_support import AIRSKIN_DEFINITION, AIRSKIN_TYPE, SCRIPTS, SYSTEM_PYTHON, require

from nwr.common import keys
from nwr.common.recordings import read_recording
from nwr.common.robot import load_description
from nwr.services import cli

DESC = load_description()
PADS = [p.name for p in DESC.pads]
TOPIC = "/bullet_ros/airskin_status"
PRESSED = 4  # elbow_outer by the default mapping


def write_bag(path: Path, *, n: int = 11, topic: str = TOPIC, type_name: str = AIRSKIN_TYPE,
              definition: str = AIRSKIN_DEFINITION, seconds: float = 6.0) -> Path:
    proc = subprocess.run([SYSTEM_PYTHON, str(SCRIPTS / "write_bag.py"), str(path), topic, type_name, definition,
                           str(n), str(PRESSED), str(seconds), ",".join(DESC.joints)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return path


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    require("rosbag", "rospy", "genpy", "sensor_msgs.msg")
    return write_bag(tmp_path_factory.mktemp("bag") / "session.bag")


def test_a_bag_becomes_a_recording_that_reads_back(bag: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "imported.mcap"
    assert cli.main(["import", str(bag), str(out)]) == 0
    report = capsys.readouterr().out
    assert "imported 180 skin samples and 600 robot states" in report
    assert "1 skin messages with a problem (length)" in report and "1 skin messages with a problem (non_finite)" \
        in report
    assert "device indices [10] are mapped to no pad" in report

    records, metadata = read_recording(out)
    session = metadata["session"]
    assert session["label.imported_from"] == str(bag) and session["label.ros_skin_topic"] == TOPIC
    assert session["timing"] == "imported"
    skin = [r.message for r in records if r.key == keys.SKIN_PRESSURE]
    states = [r.message for r in records if r.key == keys.ROBOT_STATE]
    assert len(skin) == 180 and len(states) == 600
    assert all(s.source == "ros1" and len(s.absolute_hpa) == len(PADS) for s in skin)
    assert [s.seq for s in skin] == list(range(180))
    # The bag's stamps, in order.
    assert skin[0].stamp_ns == 1_700_000_000 * 10**9
    assert all(a.stamp_ns < b.stamp_ns for a, b in zip(skin, skin[1:]))
    # Message 60 carries 9 values: pads 9 (wrist_3) and beyond invalid; message 75 a NaN on value 0.
    assert skin[60].valid == [i < 9 for i in range(10)] and skin[60].change_hpa[9] == 0.0
    assert skin[75].valid == [i != 0 for i in range(10)]
    assert all(all(s.valid) for i, s in enumerate(skin) if i not in (60, 75))
    # The press at 3.0-3.8 s on value 4, as a change from the baseline.
    pressed = skin[round(3.4 * 30)]
    assert pressed.change_hpa[PRESSED] == pytest.approx(15.0, abs=0.2) and pressed.contact[PRESSED]
    assert max(abs(c) for i, c in enumerate(pressed.change_hpa) if i != PRESSED) < 0.2
    # Joint states in the robot's joint order, whatever the bag's.
    assert states[0].q == pytest.approx([0.1 * i for i in range(6)], abs=0.02)


def test_the_import_replays_against_two_reflexes_and_compares(bag: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "imported.mcap"
    assert cli.main(["import", str(bag), str(out)]) == 0
    replays = []
    for reflex in ("cartesian", "uniform"):
        replay = tmp_path / f"replay-{reflex}.mcap"
        assert cli.main(["replay", str(out), "--fast", "--reflex", reflex, "-o", str(replay)]) == 0
        records, _ = read_recording(replay)
        statuses = [r.message for r in records if r.key == keys.planner_status(reflex)]
        reflexes = [s for s in statuses if s.mode == "REFLEX" and s.reflex is not None]
        assert reflexes and reflexes[0].reflex.contact.pad == PRESSED, reflex
        replays.append(replay)
    capsys.readouterr()
    assert cli.main(["compare", *map(str, replays), "--figure", "none"]) == 0
    table = capsys.readouterr().out
    assert "cartesian" in table and "uniform" in table


def test_a_mapping_from_the_command_line(bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "remapped.mcap"
    mapping = ",".join(["", "", "", "", "wrist_3", *PADS[:-1], ""][:11])
    assert cli.main(["import", str(bag), str(out), "--mapping", mapping]) == 0
    skin = [r.message for r in read_recording(out)[0] if r.key == keys.SKIN_PRESSURE]
    assert skin[round(3.4 * 30)].change_hpa[PADS.index("wrist_3")] == pytest.approx(15.0, abs=0.2)


@pytest.mark.parametrize(("argv", "match"), [
    (["--topic", "/nope"], "has no skin topic /nope: its topics are"),
    (["--topic", "/joint_states"], "is of type sensor_msgs/JointState, which has no field 'pressures'"),
    (["--joint-topic", TOPIC], f"{TOPIC} in .* is of type airskin_msgs/AirskinStatus, not sensor_msgs/JointState"),
    (["--mapping", "nope"], r"--mapping\[0\] = 'nope' is no pad"),
])
def test_unusable_input_exits_non_zero_with_one_line(bag: Path, tmp_path: Path, argv: list[str], match: str,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    out = tmp_path / "x.mcap"
    assert cli.main(["import", str(bag), str(out), *argv]) == 2
    assert any(__import__("re").search(match, r.getMessage()) for r in caplog.records), caplog.text
    assert not out.exists()


def test_a_missing_bag_and_an_existing_output(bag: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    assert cli.main(["import", str(tmp_path / "none.bag"), str(tmp_path / "x.mcap")]) == 2
    assert "no such bag file" in caplog.text
    (tmp_path / "x.mcap").write_bytes(b"")
    assert cli.main(["import", str(bag), str(tmp_path / "x.mcap")]) == 2
    assert "exists" in caplog.text
    assert cli.main(["import", str(bag), str(tmp_path / "x.mcap"), "--force"]) == 0
    not_a_bag = tmp_path / "text.bag"
    not_a_bag.write_text("hello")
    assert cli.main(["import", str(not_a_bag), str(tmp_path / "y.mcap")]) == 2
    assert "is no ROS 1 bag: it does not begin with '#ROSBAG V2.0'" in caplog.text


def _one_line_error(caplog: pytest.LogCaptureFixture) -> str:
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info is None, caplog.text
    message = errors[0].getMessage()
    assert "\n" not in message and "Traceback" not in message
    return message


@pytest.mark.parametrize("head", [b"", b"#ROSBAG V2.0\n"])
def test_a_garbage_file_is_one_line_and_a_non_zero_exit(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                       head: bytes) -> None:
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(head + random.Random(5).randbytes(20_000))
    out = tmp_path / "x.mcap"
    assert cli.main(["import", str(garbage), str(out)]) == 2
    message = _one_line_error(caplog)
    assert str(garbage) in message and ("is no ROS 1 bag" in message or "no readable ROS 1 bag" in message)
    assert not out.exists() and not (tmp_path / "x.mcap.part").exists()


def test_a_bag_with_bit_flips_imports_or_ends_in_one_line(bag: Path, tmp_path: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    good = bag.read_bytes()
    codes = []
    for seed in range(12):
        rng = random.Random(seed)
        data = bytearray(good)
        for _ in range(20):
            i = rng.randrange(len(data))
            data[i] ^= 1 << rng.randrange(8)
        flipped = tmp_path / f"flipped-{seed}.bag"
        flipped.write_bytes(bytes(data))
        out = tmp_path / f"flipped-{seed}.mcap"
        caplog.clear()
        code = cli.main(["import", str(flipped), str(out)])  # never an exception
        codes.append(code)
        if code == 2:
            assert "damaged" in _one_line_error(caplog) and not out.exists()
    assert 2 in codes


def test_joint_values_beyond_the_limits_or_not_finite_are_refused_by_name(tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    require("rosbag", "rospy", "genpy", "sensor_msgs.msg")
    bad = tmp_path / "bad-joints.bag"
    proc = subprocess.run([SYSTEM_PYTHON, str(SCRIPTS / "write_bag.py"), str(bad), TOPIC, AIRSKIN_TYPE,
                           AIRSKIN_DEFINITION, "11", str(PRESSED), "1.0", ",".join(DESC.joints), "1e300"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "bad-joints.mcap"
    assert cli.main(["import", str(bad), str(out)]) == 3  # written, with joint states left out: partial
    report = capsys.readouterr().out
    assert ("1 joint states skipped (/joint_states: positions beyond the joint limits), the first at "
            "1700000000.500 s: elbow_joint = 1e+300 rad, its limits [-3.14159, 3.14159] rad") in report
    assert "(/joint_states: non-finite positions), the first at 1700000000.510 s: wrist_1_joint = nan" in report
    assert ("(/joint_states: velocities beyond the joint speed limits), the first at 1700000000.520 s: "
            "shoulder_lift_joint = 1e+300 rad/s") in report
    states = [r.message for r in read_recording(out)[0] if r.key == keys.ROBOT_STATE]
    assert len(states) == 97
    assert all(abs(q) < 4.0 for s in states for q in s.q) and all(abs(v) < 4.0 for s in states for v in s.dq)


def test_a_bag_whose_messages_have_fewer_values_than_the_mapping(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    require("rosbag", "rospy", "genpy", "sensor_msgs.msg")
    bag = write_bag(tmp_path / "short.bag", n=8, seconds=1.0)
    out = tmp_path / "short.mcap"
    assert cli.main(["import", str(bag), str(out)]) == 0  # usable: the pads the messages reach
    assert "30 skin messages with a problem (length)" in capsys.readouterr().out
    skin = [r.message for r in read_recording(out)[0] if r.key == keys.SKIN_PRESSURE]
    assert all(s.valid == [i < 8 for i in range(10)] for s in skin if len(s.valid) == 10 and s.seq != 0)
