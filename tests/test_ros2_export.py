"""``nwr export --ros2``: a recording as a ROS 2 bag (rosbag2, MCAP storage) of standard messages, read back by
``rosbags`` and decoded by Foxglove's own MCAP reader and ROS 2 decoders (npm, run under node); an export
imported again gives the same skin samples and joint states."""

from __future__ import annotations

import json
import logging
import math
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml
from ros2_bags import write_ros2_bag
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.recordings import SESSION_METADATA, McapRecorder, read_recording
from nwr.common.robot import load_description
from nwr.services import cli
from nwr.services.tools.recordings.rosbag_export import export_ros2

DESC = load_description()
PADS = [p.name for p in DESC.pads]
PRESSED = 4
NODE_DIR = Path(__file__).resolve().parent / "node"


@pytest.fixture(scope="module")
def imported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A ROS 2 bag's session as a recording (skin samples, robot states, invalid pads)."""
    d = tmp_path_factory.mktemp("export")
    bag = write_ros2_bag(d / "bag", list(DESC.joints), seconds=5.0)
    assert cli.main(["import", str(bag), str(d / "imported.mcap")]) == 0
    return d / "imported.mcap"


@pytest.fixture(scope="module")
def replayed(imported: Path) -> Path:
    """The import replayed against the Cartesian reflex: pain, a reflex, the bridge's states."""
    out = imported.with_name("replayed.mcap")
    assert cli.main(["replay", str(imported), "--fast", "--reflex", "cartesian", "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def exported(replayed: Path) -> Path:
    out = replayed.with_name("replayed-ros2")
    assert cli.main(["export", "--ros2", str(replayed), str(out)]) == 0
    return out


def read_bag(bag: Path) -> dict[str, list[tuple[int, Any]]]:
    store = get_typestore(Stores.ROS2_JAZZY)
    out: dict[str, list[tuple[int, Any]]] = {}
    with Reader(bag) as reader:
        for connection, t, raw in reader.messages():
            out.setdefault(connection.topic, []).append((t, store.deserialize_cdr(raw, connection.msgtype)))
    return out


def same(a: float, b: float | None) -> bool:
    return (b is None or math.isnan(b)) if math.isnan(a) else a == b


def test_the_export_is_a_rosbag2_directory_that_rosbags_reads_back(exported: Path, replayed: Path) -> None:
    assert sorted(p.name for p in exported.iterdir()) == ["metadata.yaml", f"{exported.name}.mcap"]
    info = yaml.safe_load((exported / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == [f"{exported.name}.mcap"]
    assert info["custom_data"]["nwr.pads"] == ",".join(PADS)
    types = {t["topic_metadata"]["name"]: t["topic_metadata"]["type"] for t in info["topics_with_message_count"]}
    assert types["/joint_states"] == "sensor_msgs/msg/JointState"
    assert types["/nwr/skin/absolute_hpa"] == "std_msgs/msg/Float64MultiArray"
    assert types["/tf"] == types["/tf_static"] == "tf2_msgs/msg/TFMessage"
    assert types["/nwr/contacts"] == "visualization_msgs/msg/MarkerArray"
    assert all(t["topic_metadata"]["type_description_hash"].startswith("RIHS01_")
               for t in info["topics_with_message_count"])

    records, _ = read_recording(replayed)
    states = [r for r in records if r.key == keys.ROBOT_STATE]
    skin = [r for r in records if r.key == keys.SKIN_PRESSURE]
    bag = read_bag(exported)
    assert len(bag["/joint_states"]) == len(states) and len(bag["/nwr/skin/absolute_hpa"]) == len(skin)
    for (t, msg), r in zip(bag["/joint_states"], states, strict=True):
        assert t == r.log_time_ns and list(msg.name) == list(DESC.joints)
        assert list(msg.position) == r.message.q and list(msg.velocity) == r.message.dq
        assert list(msg.effort) == r.message.tau_ext == []  # a UR's state: no external torque estimated
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == r.message.stamp_ns
    for (_, absolute), (_, change), r in zip(bag["/nwr/skin/absolute_hpa"], bag["/nwr/skin/change_hpa"], skin,
                                             strict=True):
        assert absolute.layout.dim[0].label == "pads" and absolute.layout.dim[0].size == len(PADS)
        expect = [a if ok else math.nan for a, ok in zip(r.message.absolute_hpa, r.message.valid, strict=True)]
        assert all(same(e, float(a)) for e, a in zip(expect, absolute.data, strict=True))
        assert all(same(c if ok else math.nan, float(x))
                   for c, ok, x in zip(r.message.change_hpa, r.message.valid, change.data, strict=True))
    (_, static), = bag["/tf_static"]
    assert sorted(tr.child_frame_id for tr in static.transforms) == sorted(f"pad/{p}" for p in PADS)
    assert bag["/robot_description"][0][1].data.startswith("<?xml")
    assert len(bag["/tf"]) >= 10 and {tr.child_frame_id for tr in bag["/tf"][0][1].transforms} >= {"wrist_3_link"}
    # The press on elbow_outer: arrows in its frame; the reflex it caused, as a text.
    arrows = [mk for _, arr in bag["/nwr/contacts"] for mk in arr.markers if mk.action == 0]
    assert arrows and {mk.header.frame_id for mk in arrows} == {f"pad/{PADS[PRESSED]}"}
    texts = [mk.text for _, arr in bag["/nwr/reflex"] for mk in arr.markers]
    assert any("REFLEX (cartesian, elbow_outer" in t for t in texts) and any(t.endswith(": TASK") for t in texts)


def test_an_export_imported_again_gives_the_same_skin_samples_and_joint_states(imported: Path,
                                                                               tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    assert cli.main(["export", "--ros2", str(imported), str(bag)]) == 0
    again = tmp_path / "again.mcap"
    assert cli.main(["import", str(bag), str(again), "--topic", "/nwr/skin/absolute_hpa", "--message-type",
                     "std_msgs/msg/Float64MultiArray", "--field", "data", "--mapping", ",".join(PADS)]) == 0
    first, _ = read_recording(imported)
    second, _ = read_recording(again)
    for key in (keys.SKIN_PRESSURE, keys.ROBOT_STATE):
        a = [(r.log_time_ns, r.message) for r in first if r.key == key]
        b = [(r.log_time_ns, r.message) for r in second if r.key == key]
        assert len(a) == len(b) > 100
        assert a == b or all(repr(x) == repr(y) for x, y in zip(a, b, strict=True)), key  # NaN != NaN in ==
    skin = [r.message for r in second if r.key == keys.SKIN_PRESSURE]
    assert skin[60].valid == [i < 9 for i in range(10)] and skin[75].valid == [i != 0 for i in range(10)]


def test_a_frankas_external_torques_are_the_joint_states_efforts(tmp_path: Path) -> None:
    fr3 = load_description("fr3")
    n = len(fr3.joints)
    src = tmp_path / "fr3.mcap"
    states = []
    for i in range(40):
        tau = [0.0] * n if i < 20 else [0.25 * (j + 1) * (-1) ** i for j in range(n)]  # before and after a push
        states.append(m.RobotState(seq=i + 1, stamp_ns=10**9 + i * 2_000_000, q=[float(v) for v in fr3.home],
                                   dq=[0.0] * n, status="ok", owner="cartesian", backend="franky", tau_ext=tau))
    with src.open("wb") as f:
        rec = McapRecorder(f, "fr3")
        rec.metadata(SESSION_METADATA, {"robot": "fr3"})
        for s in states:
            rec.write("nwr/fr3/robot/state", s, s.stamp_ns)
        rec.finish()
    out = tmp_path / "fr3-ros2"
    export_ros2(src, out, description="fr3")
    bag = read_bag(out)["/joint_states"]
    assert [list(msg.effort) for _, msg in bag] == [s.tau_ext for s in states]
    assert list(bag[0][1].name) == list(fr3.joints) and len(bag[-1][1].effort) == n


def test_unusable_export_input_is_one_line(imported: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    (tmp_path / "there").mkdir()
    for argv, match in ((["export", "--ros2", str(imported), str(tmp_path / "there")], "exists"),
                        (["export", "--ros2", str(tmp_path / "none.mcap"), str(tmp_path / "x")], "none.mcap")):
        caplog.clear()
        assert cli.main(argv) == 2
        errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(errors) == 1 and match in errors[0] and "\n" not in errors[0], errors
    assert not (tmp_path / "x").exists() and not (tmp_path / "x.part").exists()
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    caplog.clear()
    assert cli.main(["export", "--ros2", str(imported), str(blocked / "bag")]) == 2  # no directory under a file
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "cannot be written" in errors[0] and "\n" not in errors[0], errors


# -- Foxglove's decoders -------------------------------------------------------------------------------------------


def foxglove_decode(node: str, mcap: Path) -> dict[str, Any]:
    proc = subprocess.run([node, str(NODE_DIR / "decode_ros2_mcap.mjs"), str(mcap)], cwd=NODE_DIR,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return dict(json.loads(proc.stdout))


def test_foxglove_decodes_every_exported_message_as_rosbags_does(node: str, exported: Path) -> None:
    decoded = foxglove_decode(node, exported / f"{exported.name}.mcap")
    bag = read_bag(exported)
    assert {t for t, v in decoded.items() if v["count"]} == set(bag)
    for topic, items in bag.items():
        assert decoded[topic]["count"] == len(items), topic
    for (t, msg), fox in zip(bag["/joint_states"], decoded["/joint_states"]["messages"], strict=True):
        assert int(fox["logTime"]) == t and fox["message"]["name"] == list(msg.name)
        assert fox["message"]["position"] == list(msg.position) and fox["message"]["velocity"] == list(msg.velocity)
        stamp = fox["message"]["header"]["stamp"]
        assert (stamp["sec"], stamp["nsec"]) == (msg.header.stamp.sec, msg.header.stamp.nanosec)
    for (_, msg), fox in zip(bag["/nwr/skin/absolute_hpa"], decoded["/nwr/skin/absolute_hpa"]["messages"],
                             strict=True):
        assert fox["message"]["layout"]["dim"] == [{"label": "pads", "size": len(PADS), "stride": len(PADS)}]
        assert all(same(float(a), b) for a, b in zip(msg.data, fox["message"]["data"], strict=True))
    assert any(None in m["message"]["data"] for m in decoded["/nwr/skin/absolute_hpa"]["messages"])  # NaN: invalid
    static = decoded["/tf_static"]["messages"][0]["message"]["transforms"]
    (_, ours), = bag["/tf_static"]
    for fox_tr, tr in zip(static, ours.transforms, strict=True):
        assert fox_tr["child_frame_id"] == tr.child_frame_id and fox_tr["header"]["frame_id"] == tr.header.frame_id
        assert fox_tr["transform"]["rotation"]["w"] == tr.transform.rotation.w
    fox_markers = [mk for m in decoded["/nwr/contacts"]["messages"] for mk in m["message"]["markers"]]
    ours_markers = [mk for _, arr in bag["/nwr/contacts"] for mk in arr.markers]
    assert [(f["header"]["frame_id"], f["type"], f["action"], f["color"]["g"]) for f in fox_markers] == \
        [(mk.header.frame_id, mk.type, mk.action, pytest.approx(mk.color.g)) for mk in ours_markers]
    assert [mk["text"] for m in decoded["/nwr/reflex"]["messages"] for mk in m["message"]["markers"]] == \
        [mk.text for _, arr in bag["/nwr/reflex"] for mk in arr.markers]
    assert decoded["/robot_description"]["messages"][0]["message"]["data"] == bag["/robot_description"][0][1].data


def test_a_live_recordings_monotonic_stamps_go_onto_utc_and_others_stay() -> None:
    from nwr.services.tools.recordings.rosbag_export import wall_offset_ns

    live = {"session": {"timing": "live", "start_time": "2026-01-02T03:04:05.000006+00:00",
                        "start_monotonic_ns": "1000"}}
    assert wall_offset_ns(live) == 1_767_323_045_000_006_000 - 1000
    assert wall_offset_ns({"session": {**live["session"], "timing": "imported"}}) == 0
    assert wall_offset_ns({"session": {**live["session"], "timing": "lockstep"}}) == 0
    assert wall_offset_ns({}) == 0
