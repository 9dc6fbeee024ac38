"""``nwr import`` of ROS 2 bags written by ``rosbags``' rosbag2 writer, in both storages (MCAP, SQLite): the same
mapping, checks and exit codes as a ROS 1 bag; and the ROS 2 bags it refuses."""

from __future__ import annotations

import logging
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
from ros2_bags import AIRSKIN_TYPE, STORAGES, TOPIC, storage_file, typestore, write_ros2_bag
from rosbags.rosbag2 import StoragePlugin, Writer

from nwr.common import keys
from nwr.common.recordings import read_recording
from nwr.common.robot import load_description
from nwr.services import cli

DESC = load_description()
JOINTS = list(DESC.joints)
PRESSED = 4  # elbow_outer by the default mapping


@pytest.fixture(scope="module", params=["mcap", "sqlite3"])
def bag(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_ros2_bag(tmp_path_factory.mktemp("ros2") / f"session-{request.param}", JOINTS,
                          storage=request.param)


def _one_line_error(caplog: pytest.LogCaptureFixture) -> str:
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info is None, caplog.text
    message = errors[0].getMessage()
    assert "\n" not in message and "Traceback" not in message
    return message


@pytest.mark.parametrize("whole", [True, False], ids=["directory", "storage-file"])
def test_a_ros2_bag_becomes_a_recording_as_a_ros1_bag_does(bag: Path, whole: bool, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    source = bag if whole else storage_file(bag)
    out = tmp_path / "imported.mcap"
    assert cli.main(["import", str(source), str(out)]) == 0
    report = capsys.readouterr().out
    assert "imported 180 skin samples and 600 robot states" in report
    assert "1 skin messages with a problem (length)" in report and "1 skin messages with a problem (non_finite)" \
        in report
    assert "device indices [10] are mapped to no pad" in report

    records, metadata = read_recording(out)
    session = metadata["session"]
    assert session["label.imported_from"] == str(source) and session["label.ros_version"] == "ROS 2"
    assert session["timing"] == "imported"
    skin = [r.message for r in records if r.key == keys.SKIN_PRESSURE]
    states = [r.message for r in records if r.key == keys.ROBOT_STATE]
    assert len(skin) == 180 and len(states) == 600
    assert all(s.source == "ros2" and len(s.absolute_hpa) == 10 for s in skin)
    assert [s.seq for s in skin] == list(range(180))
    assert skin[0].stamp_ns == 1_700_000_000 * 10**9
    assert all(a.stamp_ns < b.stamp_ns for a, b in zip(skin, skin[1:]))
    assert skin[60].valid == [i < 9 for i in range(10)] and skin[60].change_hpa[9] == 0.0
    assert skin[75].valid == [i != 0 for i in range(10)]
    assert all(all(s.valid) for i, s in enumerate(skin) if i not in (60, 75))
    pressed = skin[round(3.4 * 30)]
    assert pressed.change_hpa[PRESSED] == pytest.approx(15.0, abs=0.2) and pressed.contact[PRESSED]
    assert max(abs(c) for i, c in enumerate(pressed.change_hpa) if i != PRESSED) < 0.2
    assert skin[round(3.4 * 30)].absolute_hpa[PRESSED] == pytest.approx(1013.0 + 2.0 + 15.0, abs=0.05)
    assert states[0].q == pytest.approx([0.1 * i for i in range(6)], abs=0.02)


def test_a_ros2_import_replays(bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "imported.mcap"
    assert cli.main(["import", str(bag), str(out)]) == 0
    replay = tmp_path / "replay.mcap"
    assert cli.main(["replay", str(out), "--fast", "--reflex", "cartesian", "-o", str(replay)]) == 0
    statuses = [r.message for r in read_recording(replay)[0] if r.key == keys.planner_status("cartesian")]
    reflexes = [s for s in statuses if s.mode == "REFLEX" and s.reflex is not None]
    assert reflexes and reflexes[0].reflex.contact.pad == PRESSED


@pytest.mark.parametrize(("argv", "match"), [
    (["--topic", "/nope"], "has no skin topic /nope: its topics are"),
    (["--topic", "/joint_states"], "is of type sensor_msgs/msg/JointState, which has no field 'pressures'"),
    (["--joint-topic", TOPIC], f"{TOPIC} in .* is of type {AIRSKIN_TYPE}, not sensor_msgs/msg/JointState"),
])
def test_unusable_ros2_input_exits_non_zero_with_one_line(bag: Path, tmp_path: Path, argv: list[str], match: str,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    out = tmp_path / "x.mcap"
    assert cli.main(["import", str(bag), str(out), *argv]) == 2
    assert __import__("re").search(match, _one_line_error(caplog)), caplog.text
    assert not out.exists()


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("definition", ["", "float32[ pressures !!"], ids=["none", "garbage"])
def test_a_skin_type_the_bag_does_not_define_is_unknown(tmp_path: Path, storage: str, definition: str,
                                                        caplog: pytest.LogCaptureFixture) -> None:
    bag = tmp_path / "unknown"
    store = typestore()
    data = store.serialize_cdr(store.types[AIRSKIN_TYPE](pressures=np.zeros(11, dtype=np.float32)), AIRSKIN_TYPE)
    with Writer(bag, version=9, storage_plugin=STORAGES[storage]) as writer:
        conn = writer.add_connection("/skin", "lab_msgs/msg/Skin", msgdef=definition, rihs01="RIHS01_" + "0" * 64)
        writer.write(conn, 1, data)
    out = tmp_path / "x.mcap"
    assert cli.main(["import", str(bag), str(out), "--topic", "/skin"]) == 2
    message = _one_line_error(caplog)
    assert "definition of lab_msgs/msg/Skin on /skin cannot be read" in message and "type is unknown" in message
    assert not out.exists()
    # Told the type and its definition, the import takes it.
    caplog.clear()
    assert cli.main(["import", str(bag), str(out), "--topic", "/skin", "--message-type", "lab_msgs/msg/Skin"]) == 0


def test_a_skin_topic_of_the_wrong_shape_is_refused_or_marks_its_pads_invalid(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture) -> None:
    bag = tmp_path / "strings"
    store = typestore()
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        text = writer.add_connection("/skin", "std_msgs/msg/String", typestore=store)
        short = writer.add_connection(TOPIC, AIRSKIN_TYPE, typestore=store)
        for k in range(5):
            writer.write(text, k, store.serialize_cdr(store.types["std_msgs/msg/String"](data="1013 hPa"),
                                                      "std_msgs/msg/String"))
            writer.write(short, k, store.serialize_cdr(
                store.types[AIRSKIN_TYPE](pressures=np.full(3, 1013.0, dtype=np.float32)), AIRSKIN_TYPE))
    out = tmp_path / "strings.mcap"
    assert cli.main(["import", str(bag), str(out), "--topic", "/skin", "--field", "data"]) == 2
    assert ("/skin in " in (line := _one_line_error(caplog)) and "is of type std_msgs/msg/String, whose field "
            "'data' is string, not an array of numbers") in line
    assert not out.exists()
    assert cli.main(["import", str(bag), str(out)]) == 0  # 3 values of 11: the pads they reach
    assert "5 skin messages with a problem (length)" in capsys.readouterr().out
    skin = [r.message for r in read_recording(out)[0] if r.key == keys.SKIN_PRESSURE]
    assert all(s.valid == [i < 3 for i in range(10)] for s in skin)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_cdr_that_does_not_decode_is_counted_and_a_bad_joint_state_makes_the_import_partial(
        tmp_path: Path, storage: str, capsys: pytest.CaptureFixture[str]) -> None:
    def spoil(topic: str, k: int, data: bytes) -> bytes:
        if topic == TOPIC and k in (10, 11):
            return data[:6]  # a sequence length with its elements cut off
        if topic == "/joint_states" and k == 20:
            return b"\x00\x01"  # no CDR header
        return data

    bag = write_ros2_bag(tmp_path / "spoiled", JOINTS, storage=storage, seconds=1.0, bad=1e300, spoil=spoil)
    out = tmp_path / "spoiled.mcap"
    assert cli.main(["import", str(bag), str(out)]) == 3  # written, with joint states left out
    report = capsys.readouterr().out
    # 30 skin messages, 2 of them dropped; 100 joint states, 3 with bad values and 1 that does not decode.
    assert "imported 28 skin samples and 96 robot states" in report
    assert "2 skin messages with a problem (undecodable: SerdeError)" in report
    assert "1 joint states skipped (undecodable: SerdeError)" in report
    assert "joint states skipped (/joint_states: positions beyond the joint limits), the first at " \
        "1700000000.500 s: elbow_joint = 1e+300 rad" in report


@pytest.mark.parametrize("name", ["garbage.mcap", "garbage.db3"])
@pytest.mark.parametrize("head", [True, False], ids=["magic", "no-magic"])
def test_a_garbage_ros2_file_is_one_line_and_a_non_zero_exit(tmp_path: Path, name: str, head: bool,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    magic = b"\x89MCAP0\r\n" if name.endswith(".mcap") else b"SQLite format 3\x00"
    garbage = tmp_path / name
    garbage.write_bytes((magic if head else b"") + random.Random(7).randbytes(20_000))
    out = tmp_path / "x.mcap"
    assert cli.main(["import", str(garbage), str(out)]) == 2
    message = _one_line_error(caplog)
    assert str(garbage) in message and "ROS 2 bag" in message
    assert not out.exists() and not (tmp_path / "x.mcap.part").exists()


def test_a_cut_or_damaged_ros2_bag_imports_or_ends_in_one_line(tmp_path: Path,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    bag = write_ros2_bag(tmp_path / "good", JOINTS, storage="mcap", seconds=2.0)
    good = storage_file(bag).read_bytes()
    codes = []
    for seed, cut in enumerate([len(good) // 2, len(good) - 20, 100, None, None, None, None]):
        data = bytearray(good[:cut] if cut is not None else good)
        rng = random.Random(seed)
        for _ in range(0 if cut is not None else 30):
            i = rng.randrange(len(data))
            data[i] ^= 1 << rng.randrange(8)
        damaged = tmp_path / f"damaged-{seed}.mcap"
        damaged.write_bytes(bytes(data))
        out = tmp_path / f"damaged-{seed}-out.mcap"
        caplog.clear()
        code = cli.main(["import", str(damaged), str(out)])  # never an exception
        codes.append(code)
        if code == 2:
            assert "ROS 2 bag" in _one_line_error(caplog) and not out.exists()
    assert codes[:3] == [2, 2, 2], codes


def test_a_ros2_directory_without_or_with_bad_metadata(bag: Path, tmp_path: Path,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli.main(["import", str(empty), str(tmp_path / "x.mcap")]) == 2
    assert "without metadata.yaml" in _one_line_error(caplog)
    broken = tmp_path / "broken"
    shutil.copytree(bag, broken)
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information: [not, a, bag\n")
    caplog.clear()
    assert cli.main(["import", str(broken), str(tmp_path / "y.mcap")]) == 2
    assert "is no readable ROS 2 bag" in _one_line_error(caplog)


def test_a_project_recording_is_no_ros2_bag(bag: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    recording = tmp_path / "recording.mcap"
    assert cli.main(["import", str(bag), str(recording)]) == 0
    caplog.clear()
    assert cli.main(["import", str(recording), str(tmp_path / "again.mcap")]) == 2
    assert "is no readable ROS 2 bag" in _one_line_error(caplog)  # its channels are msgpack, not ROS 2 CDR
