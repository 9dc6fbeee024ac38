"""The view's core: colours, pad patches, transforms vs FK, rate capping, encoding, playback, export."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pinocchio as pin
import pytest
from mcap.reader import make_reader
from mcap.records import Schema as McapSchema
from mcap_protobuf.decoder import DecoderFactory

from nwr.common import messages as m
from nwr.common.recordings import McapRecorder, Recorded
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.strategies.whole_arm import WholeArmSettings
from nwr.services.view import core as c
from nwr.services.view.export import ExportError, export_foxglove, load_records
from nwr.services.view.playback import Player

DESC = load_description()
MODEL = RobotModel(DESC)
ROBOT = "ur10e"
CHANNELS = c.channel_specs([p.name for p in DESC.pads])
CHANNEL_BY_TOPIC = {spec.topic: spec for spec in CHANNELS}


# -- helpers shared with the end-to-end test ------------------------------------------


def protobuf_decoder(name: str, encoding: str, data: bytes) -> Any:
    """A decode(bytes) function for a protobuf schema (a FileDescriptorSet), as the mcap reader builds it."""
    decoder = DecoderFactory().decoder_for("protobuf", McapSchema(id=1, name=name, encoding=encoding, data=data))
    assert decoder is not None, name
    return decoder


def rgba(color: Any) -> tuple[float, float, float, float]:
    return (color.r, color.g, color.b, color.a)


def transforms_of(msg: Any) -> list[c.Transform]:
    return [c.Transform(t.parent_frame_id, t.child_frame_id,
                        np.array([t.translation.x, t.translation.y, t.translation.z]),
                        np.array([t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w])) for t in msg.transforms]


def arrow_length(arrow: Any) -> float:
    return arrow.shaft_length + arrow.head_length


def state(q: Any, seq: int = 0, stamp: int = 0, **kw: Any) -> m.RobotState:
    return m.RobotState(seq=seq, stamp_ns=stamp, q=[float(v) for v in q], dq=[0.0] * 6, status="ok",
                        owner=kw.pop("owner", "cartesian"), backend="sim", **kw)


def pain(gains: list[float], seq: int = 0, stamp: int = 0) -> m.SkinPain:
    best = int(np.argmax(gains))
    strongest = None
    if gains[best] > 0:
        pad = DESC.pads[best]
        strongest = m.Contact(pad=best, name=pad.name, region=pad.region, change_hpa=10.0, level=3, gain=gains[best])
    return m.SkinPain(seq=seq, stamp_ns=stamp, trace=m.Trace(seq, stamp), model="continuous",
                      level=[3 if g > 0 else 1 for g in gains], gain=gains, strongest=strongest)


def status(mode: str = "TASK", seq: int = 0, stamp: int = 0, target_pad: int = -1, reflex: Any = None,
           saved: Any = None) -> m.PlannerStatus:
    return m.PlannerStatus(seq=seq, stamp_ns=stamp, name="cartesian", strategy="cartesian", mode=mode,  # type: ignore[arg-type]
                           task_time_s=0.0, saved_pose=saved, reflex=reflex, target_pad=target_pad)


def reflex_info(pad: int, gain: float, *, target: list[float] | None = None,
                direction: list[float] | None = None) -> m.ReflexInfo:
    p = DESC.pads[pad]
    return m.ReflexInfo(reflex_seq=1, strategy="uniform" if target else "cartesian",
                        contact=m.Contact(pad=pad, name=p.name, region=p.region, change_hpa=15.0, level=4, gain=gain),
                        trace=m.Trace(0, 0), started_ns=0, duration_s=0.5, direction=direction or [],
                        target=target or [])


# -- colours --------------------------------------------------------------------------


def test_gain_colour_is_neutral_at_zero_and_runs_from_yellow_to_red():
    assert c.gain_color(0.0) == c.NEUTRAL
    assert c.gain_color(float("nan")) == c.NEUTRAL
    assert c.gain_color(-0.1) == c.NEUTRAL
    assert c.gain_color(1e-9)[:3] == pytest.approx((1.0, 1.0, 0.0))  # a reflex fires: yellow at once
    assert c.gain_color(0.5) == (1.0, 0.5, 0.0, 1.0)
    assert c.gain_color(1.0) == (1.0, 0.0, 0.0, 1.0)
    assert c.gain_color(3.0) == c.gain_color(1.0)
    greens = [c.gain_color(g)[1] for g in np.linspace(0.01, 1.0, 50)]
    assert all(b < a for a, b in zip(greens, greens[1:]))  # redder as the gain rises


def test_led_ring_is_red_on_the_target_pad_and_blue_elsewhere():
    assert c.led_color(3, 3) == c.LED_TARGET
    assert c.led_color(2, 3) == c.LED_IDLE
    assert c.led_color(0, -1) == c.LED_IDLE
    assert c.LED_TARGET[0] > 0.9 and c.LED_IDLE[2] > 0.9


# -- pad geometry -----------------------------------------------------------------------


def test_pad_patches_face_along_their_normals_around_their_points():
    patches = c.pad_patches(DESC)
    assert [p.pad for p in patches] == list(range(len(DESC.pads)))
    q = DESC.home + np.linspace(-0.2, 0.2, 6)
    for patch, pad in zip(patches, DESC.pads):
        r = patch.rotation
        assert r @ r.T == pytest.approx(np.eye(3), abs=1e-12) and np.linalg.det(r) == pytest.approx(1.0)
        assert r[:, 2] == pytest.approx(pad.normal, abs=1e-12)
        # The outer face is on the pad's point.
        assert patch.center + patch.normal * patch.size[2] / 2 == pytest.approx(pad.point, abs=1e-12)
        # The LED ring: a square around the point, in the patch's plane, just above it.
        offsets = patch.ring - pad.point
        assert offsets @ pad.normal == pytest.approx(np.full(4, c.LED_OFFSET_M), abs=1e-12)
        radial = offsets - np.outer(offsets @ pad.normal, pad.normal)
        assert np.linalg.norm(radial, axis=1) == pytest.approx(np.full(4, c.PAD_SIZE_M / math.sqrt(2)))
        # Carried by its link, the patch lands where the model puts the pad.
        link = MODEL.frame_pose(q, pad.link)
        assert link[:3, :3] @ patch.point + link[:3, 3] == pytest.approx(MODEL.pad_point(q, pad.id), abs=1e-9)
        assert link[:3, :3] @ r[:, 2] == pytest.approx(MODEL.pad_normal(q, pad.id), abs=1e-9)


def test_contact_arrow_presses_on_the_pad_and_scales_with_gain():
    patch = c.pad_patches(DESC)[5]
    assert c.contact_arrow(patch, 0.0) is None
    for gain in (0.1, 0.35, 1.0):
        arrow = c.contact_arrow(patch, gain)
        assert arrow is not None
        assert arrow.length == pytest.approx(c.ARROW_MAX_M * gain)
        assert arrow.tip == pytest.approx(patch.point)
        assert arrow.direction == pytest.approx(-patch.normal)
        assert arrow.frame == patch.link and arrow.color == c.gain_color(gain)


# -- transforms ---------------------------------------------------------------------------


def test_link_transforms_compose_to_the_models_forward_kinematics():
    core = c.ViewCore(DESC, MODEL)
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(DESC.q_min, DESC.q_max)
        transforms = c.link_transforms(MODEL, core.joints, q)
        poses = c.compose(transforms, DESC.base_frame)
        links = {j.child for j in core.joints} | {j.parent for j in core.joints}
        assert set(poses) == links
        for link in links:
            expected = MODEL.frame_pose(q, link)
            assert np.abs(poses[link][:3, 3] - expected[:3, 3]).max() < 1e-6, link
            assert np.abs(poses[link][:3, :3] - expected[:3, :3]).max() < 1e-6, link
        for t in transforms:
            assert np.linalg.norm(t.rotation) == pytest.approx(1.0) and t.rotation[3] >= 0


def test_visual_urdf_loads_with_pinocchio_and_keeps_the_kinematics():
    core = c.ViewCore(DESC, MODEL)
    model = pin.buildModelFromXML(core.urdf)
    assert tuple(model.names[1:]) == DESC.joints
    data = model.createData()
    q = DESC.home + 0.3
    pin.framesForwardKinematics(model, data, q)
    tool = data.oMf[model.getFrameId(DESC.tool_frame)].translation
    assert tool == pytest.approx(MODEL.tool_position(q), abs=1e-9)
    import xml.etree.ElementTree as ET

    root = ET.fromstring(core.urdf)
    moving = {j.child for j in core.joints if j.type != "fixed"}
    for link in root.findall("link"):
        geometries = link.findall("visual/geometry/*")
        assert all(g.tag in ("cylinder", "box") for g in geometries)
        if link.get("name") in moving:
            assert geometries, link.get("name")
    assert "mesh" not in core.urdf


# -- rate capping -----------------------------------------------------------------------------


def test_scene_clock_caps_the_rate_of_a_500_hz_caller():
    clock = c.SceneClock(30.0)
    calls = np.arange(0, 2_000_000_000, 2_000_000)  # 2 s at 500 Hz
    due = [int(t) for t in calls if clock.due(int(t))]
    assert 59 <= len(due) <= 61
    gaps = np.diff(due)
    assert gaps.min() >= clock.period_ns - 2_000_000  # never faster than the cap, within one call
    assert np.mean(gaps) == pytest.approx(clock.period_ns, rel=0.01)


def test_scene_clock_does_not_burst_after_a_stall():
    clock = c.SceneClock(30.0)
    assert clock.due(0)
    assert not clock.due(10_000_000)
    assert clock.due(1_000_000_000)  # a long stall
    assert not clock.due(1_000_000_000 + 2_000_000)  # no catching up
    assert clock.due(1_000_000_000 + clock.period_ns)
    with pytest.raises(Exception, match="positive rate"):
        c.SceneClock(0)


def test_timeline_frames_a_500_hz_stream_at_the_cap():
    core = c.ViewCore(DESC, MODEL)
    t0 = 5_000_000_000
    records = [Recorded("robot/state", t0 + i * 2_000_000, state(DESC.home, seq=i, stamp=t0 + i * 2_000_000))
               for i in range(1000)]  # 2 s of the bridge at 500 Hz
    outputs = list(c.timeline(records, core, 30.0))
    assert outputs[0].topic == c.ROBOT_DESCRIPTION and outputs[0].log_time_ns == t0
    tf = [o.log_time_ns for o in outputs if o.topic == "/tf"]
    assert 59 <= len(tf) <= 62
    assert set(np.diff(tf)) <= {round(1e9 / 30)}
    assert [o.log_time_ns for o in outputs] == sorted(o.log_time_ns for o in outputs)


# -- the core's frames and signals ---------------------------------------------------------------


def test_frame_shows_gain_contact_target_and_signals():
    core = c.ViewCore(DESC, MODEL)
    gains = [0.0] * 10
    gains[8] = 0.8
    core.apply(state(DESC.home, seq=4, stamp=100))
    core.apply(pain(gains, seq=7, stamp=90))
    core.apply(status(target_pad=2, seq=1))
    frame = core.frame(1000)
    assert frame.pads[8].color == c.gain_color(0.8) and frame.pads[0].color == c.NEUTRAL
    assert frame.pads[2].led == c.LED_TARGET and frame.pads[8].led == c.LED_IDLE
    assert frame.contact_pad == 8 and frame.contact is not None
    assert frame.contact.length == pytest.approx(0.8 * c.ARROW_MAX_M)
    topics = [t for t, _ in frame.signals]
    assert topics == ["/nwr/robot", "/nwr/skin", "/nwr/planner"]
    skin = dict(frame.signals)["/nwr/skin"]
    assert skin["gain"]["wrist_2"] == 0.8 and skin["strongest"] == {"pad": "wrist_2", "gain": 0.8, "level": 3}
    planner = dict(frame.signals)["/nwr/planner"]
    assert planner["mode_index"] == 0 and planner["target_name"] == "upper_arm_top" and planner["active"]
    assert (planner["reason"], planner["reach_m"], planner["others"]) == ("", 0.0, [])
    # Unchanged skin and status are not sent again; the robot state is (it goes with /tf).
    assert [t for t, _ in core.frame(2000).signals] == ["/nwr/robot"]
    # A whole-arm reflex's reason and reach, and its retreat check of another touched pad, by name.
    retreat = m.Retreat(sample_dt_s=0.01, normal_speed_m_s=[], toward_m=0.0, withdrawal_m=0.02, approach_m=[],
                        worst_pad=0, worst_approach_m=0.0, approached=False, corrected=False, contacts=[3],
                        contacts_toward_m=[0.0004])
    core.apply(status("REFLEX", seq=2, reflex=msgspec.structs.replace(
        reflex_info(8, 0.8, direction=[0.0, 0.0, 0.1]), reason="short", reach_m=0.02, retreat=retreat)))
    planner = dict(core.frame(3000).signals)["/nwr/planner"]
    assert (planner["reason"], planner["reach_m"], planner["others"]) == (
        "short", 0.02, [{"pad": "upper_arm_bottom", "toward_m": 0.0004}])


def test_onset_latency_is_published_once_per_reflex():
    core = c.ViewCore(DESC, MODEL)
    core.apply(state(DESC.home, reflex_seq=3, accepted=m.Trace(11, 1_000_000), accepted_ns=3_500_000))
    onset = [s for t, s in core.frame(0).signals if t == "/nwr/onset"]
    assert len(onset) == 1 and onset[0]["latency_ms"] == pytest.approx(2.5) and onset[0]["reflex_seq"] == 3
    core.apply(state(DESC.home, seq=1, reflex_seq=3, accepted=m.Trace(11, 1_000_000), accepted_ns=3_500_000))
    assert not [s for t, s in core.frame(1).signals if t == "/nwr/onset"]
    # Back in the task, the bridge's states still name the last onset (with reflex_seq 0): not another one.
    core.apply(state(DESC.home, seq=2, reflex_seq=0, accepted=m.Trace(11, 1_000_000), accepted_ns=3_500_000))
    assert not [s for t, s in core.frame(2).signals if t == "/nwr/onset"]


def test_ghost_of_a_joint_reflex_and_of_a_cartesian_one():
    core = c.ViewCore(DESC, MODEL)
    target = list(DESC.home + np.array([0.3, -0.5, 0.4, 0.2, 0.0, 0.0]))
    core.apply(state(DESC.home))
    core.apply(status("REFLEX", reflex=reflex_info(5, 1.0, target=target)))
    ghost = core.frame(0).ghost
    assert ghost is not None and ghost.polyline == pytest.approx(MODEL.joint_positions(target))
    direction = list(-0.25 * MODEL.pad_normal(DESC.home, 5))
    core.apply(status("REFLEX", seq=1, reflex=reflex_info(5, 1.0, direction=direction), saved=list(DESC.home)))
    ghost = core.frame(1).ghost
    assert ghost is not None and ghost.arrow is not None
    assert ghost.arrow.tail == pytest.approx(MODEL.pad_point(DESC.home, 5))
    assert ghost.arrow.tip == pytest.approx(MODEL.pad_point(DESC.home, 5) + 0.125 * -MODEL.pad_normal(DESC.home, 5))
    core.apply(status("RETURNING", seq=2))
    assert core.frame(2).ghost is None


def test_encoded_frame_decodes_against_its_schemas():
    core = c.ViewCore(DESC, MODEL)
    gains = [0.0] * 10
    gains[5] = 0.4
    core.apply(state(DESC.home))
    core.apply(pain(gains))
    core.apply(status(target_pad=5))
    outputs = {o.topic: o for o in c.encode_frame(core.frame(7_000_000_123))}
    decode = {s.topic: protobuf_decoder(s.schema_name, s.schema_encoding, s.schema)
              for s in core.channels if s.message_encoding == "protobuf"}
    tf = decode["/tf"](outputs["/tf"].data)
    assert len(tf.transforms) == len(core.joints)
    assert tf.transforms[0].timestamp.seconds == 7 and tf.transforms[0].timestamp.nanos == 123
    pads = decode["/nwr/pads"](outputs["/nwr/pads"].data)
    by_id = {e.id: e for e in pads.entities}
    forearm = by_id["pad/forearm_top"]
    assert forearm.frame_id == "forearm_link" and forearm.frame_locked
    assert rgba(forearm.cubes[0].color) == pytest.approx(c.gain_color(0.4))
    assert rgba(forearm.lines[0].color) == pytest.approx(c.LED_TARGET)
    assert rgba(by_id["pad/wrist_2"].cubes[0].color) == pytest.approx(c.NEUTRAL)
    contact = decode["/nwr/contact"](outputs["/nwr/contact"].data)
    arrow = contact.entities[0].arrows[0]
    assert arrow_length(arrow) == pytest.approx(0.4 * c.ARROW_MAX_M)
    # The arrow's +x points into the pad.
    o = arrow.pose.orientation
    x_axis = pin.Quaternion(o.w, o.x, o.y, o.z).toRotationMatrix()[:, 0]
    assert x_axis == pytest.approx(-DESC.pads[5].normal, abs=1e-9)
    reflex = decode["/nwr/reflex"](outputs["/nwr/reflex"].data)
    assert len(reflex.deletions) == 1 and not reflex.entities
    for spec in core.channels:
        if spec.message_encoding == "json" and spec.topic in outputs:
            message = json.loads(outputs[spec.topic].data)
            schema = json.loads(spec.schema)
            assert schema["type"] == "object" and set(message) <= set(schema["properties"]), spec.topic
    skin = json.loads(outputs["/nwr/skin"].data)
    assert list(skin["gain"]) == core.names and skin["gain"]["forearm_top"] == pytest.approx(0.4)


def person(name: str, kind: str, pads: list[int], force: float) -> m.WorldPerson:
    return m.WorldPerson(name=name, kind=kind, touch=-1, pads=pads, force_n=force, peak_force_n=force,
                         pressure_n_cm2=1.0, peak_pressure_n_cm2=1.0, energy_j=0.0, pushed_m=0.0, peak_pushed_m=0.0)


def test_a_physics_worlds_body_parts_show_as_contacts_with_force_arrows_and_go_when_they_leave():
    core = c.ViewCore(DESC, MODEL)
    core.apply(state(DESC.home))
    forearm, wrist_1, wrist_2 = (DESC.pad(n).id for n in ("forearm_top", "wrist_1", "wrist_2"))
    core.apply(m.WorldContacts(seq=0, stamp_ns=1_000_000_000, world_ns=0, people=[
        person("touch-0", "finger", [forearm], 25.0), person("palm", "palm", [wrist_1, wrist_2], 40.0),
        person("touch-1", "finger", [], 0.0)]))  # in the world, touching nothing: not drawn
    frame = core.frame(1_100_000_000)
    assert [(p.name, p.pad, p.force_n) for p in frame.people] == [
        ("touch-0", forearm, 25.0), ("palm", wrist_1, 20.0), ("palm", wrist_2, 20.0)]
    decode = {s.topic: protobuf_decoder(s.schema_name, s.schema_encoding, s.schema)
              for s in core.channels if s.message_encoding == "protobuf"}
    people = decode["/nwr/people"]({o.topic: o for o in c.encode_frame(frame)}["/nwr/people"].data)
    assert len(people.deletions) == 1  # the last frame's people go first
    by_id = {e.id: e for e in people.entities}
    assert sorted(by_id) == ["person/palm/wrist_1", "person/palm/wrist_2", "person/touch-0/forearm_top"]
    finger = by_id["person/touch-0/forearm_top"]
    pad = DESC.pads[forearm]
    assert finger.frame_id == pad.link and finger.frame_locked
    centre = finger.spheres[0].pose.position
    assert [centre.x, centre.y, centre.z] == pytest.approx(pad.point)
    arrow = finger.arrows[0]
    assert arrow_length(arrow) == pytest.approx(25.0 * c.FORCE_ARROW_M_PER_N)
    # The force on the person: from the arm out into them, along the pad's outward normal.
    o = arrow.pose.orientation
    assert pin.Quaternion(o.w, o.x, o.y, o.z).toRotationMatrix()[:, 0] == pytest.approx(pad.normal, abs=1e-9)
    assert arrow_length(by_id["person/palm/wrist_1"].arrows[0]) == pytest.approx(20.0 * c.FORCE_ARROW_M_PER_N)
    # The world stops publishing when the last part leaves: stale contacts show nobody.
    gone = core.frame(1_000_000_000 + c.PEOPLE_STALE_NS + 1)
    assert gone.people == []
    people = decode["/nwr/people"]({o.topic: o for o in c.encode_frame(gone)}["/nwr/people"].data)
    assert len(people.deletions) == 1 and not people.entities


def test_skin_channel_has_a_property_per_pad_of_the_robot():
    assert c.ViewCore(DESC, MODEL).channels == CHANNELS
    assert {s.topic for s in c.channel_specs(["a", "b"])} == {s.topic for s in CHANNELS} == c.VIEW_TOPICS
    skin = json.loads(CHANNEL_BY_TOPIC["/nwr/skin"].schema)
    for field, value_type in (("change_hpa", "number"), ("level", "integer"), ("gain", "number")):
        assert skin["properties"][field]["properties"] == {p.name: {"type": value_type} for p in DESC.pads}
    other = json.loads({s.topic: s for s in c.channel_specs(["a", "b"])}["/nwr/skin"].schema)
    assert list(other["properties"]["gain"]["properties"]) == ["a", "b"]


# -- playback ----------------------------------------------------------------------------------


def test_player_plays_pauses_seeks_and_ends():
    times = [1000 + 100 * i for i in range(11)]  # 1000 .. 2000
    player = Player(times)
    assert player.status == "paused" and player.advance(5) == (0, 0)
    player.play(0)
    assert player.advance(0) == (0, 1)  # the first output is due at once
    assert player.advance(250) == (1, 3)  # 250 ns later: up to log time 1250
    player.pause(250)
    assert player.advance(10_000) == (3, 3) and player.current_time(10_000) == 1250
    player.set_speed(2.0, 10_000)
    player.play(10_000)
    assert player.advance(10_100) == (3, 5)  # 100 ns at 2x: up to 1450
    position, target = player.seek(1720, 10_100)
    assert (position, target) == (8, 1720) and player.status == "playing"
    assert player.advance(10_100) == (8, 8)
    assert player.advance(10_200) == (8, 10)  # 1920
    assert player.advance(11_000) == (10, 11) and player.status == "ended"
    player.play(11_000)
    assert player.status == "ended"  # seek first to play again
    player.seek(0, 12_000)  # clamped to the start
    assert player.status == "paused" and player.position == 1 and player.current_time(12_000) == 1000
    with pytest.raises(ValueError, match="nothing to play"):
        Player([])


# -- export ---------------------------------------------------------------------------------------


def write_recording(path: Path) -> list[Recorded]:
    """A short synthetic session: the bridge at 500 Hz, a touch on wrist_2 and a uniform reflex."""
    t0 = 10_000_000_000
    records: list[Recorded] = []
    for i in range(600):  # 1.2 s
        t = t0 + i * 2_000_000
        q = DESC.home + np.array([0.2 * math.sin(i / 100), 0, 0, 0, 0, 0])
        records.append(Recorded("robot/state", t, state(q, seq=i, stamp=t)))
        if i % 20 == 0:  # 25 Hz skin
            gains = [0.0] * 10
            gains[8] = min(1.0, max(0.0, (i - 200) / 200)) if 200 <= i < 500 else 0.0
            records.append(Recorded("skin/pain", t + 1, pain(gains, seq=i // 20, stamp=t)))
        if i % 25 == 0:
            mode = "REFLEX" if 300 <= i < 400 else "TASK"
            info = reflex_info(8, 1.0, target=[float(v) for v in DESC.home + 0.2]) if mode == "REFLEX" else None
            records.append(Recorded("reflex/cartesian/status", t + 2, status(mode, seq=i // 25, stamp=t, reflex=info,
                                                                              target_pad=8)))
    with path.open("wb") as f:
        rec = McapRecorder(f, ROBOT)
        for r in records:
            rec.write(f"nwr/{ROBOT}/{r.key}", r.message, r.log_time_ns)
        rec.finish()
    return records


def test_export_adds_scene_channels_that_decode_and_a_description_pinocchio_loads(tmp_path):
    src, dst = tmp_path / "session.mcap", tmp_path / "session-foxglove.mcap"
    records = write_recording(src)
    report = export_foxglove(src, dst)
    assert report.copied == len(records)
    assert report.added["/tf"] == pytest.approx(1.2 * 30, abs=2)
    seen: dict[str, int] = {}
    with dst.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        schemas = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        assert schemas["/tf"].name == "foxglove.FrameTransforms" and schemas["/tf"].encoding == "protobuf"
        assert schemas["/nwr/pads"].name == "foxglove.SceneUpdate"
        assert schemas["/robot_description"].name == "std_msgs/String"
        assert schemas[f"nwr/{ROBOT}/robot/state"].name == "nwr.RobotState"  # the original channels stay
        for _schema, channel, _message, decoded in reader.iter_decoded_messages(
                topics=["/tf", "/nwr/pads", "/nwr/contact", "/nwr/reflex"]):
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == "/tf":
                assert len(decoded.transforms) == 10  # one per URDF joint
            if channel.topic == "/nwr/pads":
                assert len(decoded.entities) == 10
        f.seek(0)
        description = [json.loads(msg.data)
                       for _s, _c, msg in make_reader(f).iter_messages(topics=["/robot_description"])]
        f.seek(0)
        metadata = {r.name: dict(r.metadata) for r in make_reader(f).iter_metadata()}
    assert set(seen) == {"/tf", "/nwr/pads", "/nwr/contact", "/nwr/reflex"} and seen["/tf"] == report.added["/tf"]
    model = pin.buildModelFromXML(description[0]["data"])
    assert tuple(model.names[1:]) == DESC.joints
    assert "recording" in metadata and "foxglove_export" in metadata  # the original metadata is kept
    # The pipeline's messages read back unchanged from the export.
    again, _ = load_records(dst)
    assert [(r.key, r.log_time_ns) for r in again] == [(r.key, r.log_time_ns) for r in records]
    with pytest.raises(ExportError, match="already exported"):
        export_foxglove(dst, tmp_path / "twice.mcap")
    with pytest.raises(ExportError, match="is the input"):
        export_foxglove(src, src)


def test_shipped_layout_plots_fields_the_view_publishes():
    layout = json.loads((Path(__file__).parents[1] / "deploy" / "foxglove" / "nwr-layout.json").read_text())
    panels = layout["configById"]
    assert {k.split("!")[0] for k in panels} == {"3D", "Plot", "StateTransitions"}

    def ids(node: Any) -> set[str]:
        return {node} if isinstance(node, str) else ids(node["first"]) | ids(node["second"])

    assert ids(layout["layout"]) == set(panels)
    paths = [p["value"] for config in panels.values() for p in config.get("paths", [])]
    names = {p.name for p in DESC.pads}
    for path in paths:
        topic, *fields = path.split(".")
        schema = json.loads(CHANNEL_BY_TOPIC[topic].schema)
        for name in fields:  # every step of the path is a property its schema lists (what the panels resolve)
            assert name in schema.get("properties", {}), path
            schema = schema["properties"][name]
        assert schema["type"] in ("number", "integer", "string", "boolean"), path
    for field in ("change_hpa", "gain"):
        assert {p.rsplit(".", 1)[1] for p in paths if p.startswith(f"/nwr/skin.{field}.")} == names
    assert "/nwr/planner.mode" in paths and "/nwr/onset.latency_ms" in paths
    assert set(panels["3D!nwr"]["topics"]) <= set(CHANNEL_BY_TOPIC)


def test_the_live_server_broadcasts_time_without_an_error(caplog):
    from nwr.services.view.server import ViewServer

    # As `nwr view` serves live: no capability asked.
    view = ViewServer("127.0.0.1", 0, name="time test", channels=CHANNELS)
    try:
        with caplog.at_level("DEBUG"):
            for t in range(5):
                view.server.broadcast_time(1_000_000 * t)
    finally:
        view.stop()
    assert not [r for r in caplog.records if r.levelname == "ERROR"], caplog.text  # was one per frame


def test_ghost_of_a_whole_arm_withdrawal_is_its_displacement_and_none_when_it_holds_still():
    """The reflex as the whole-arm planner publishes it (its strategy's onset direction and duration): the
    arrow is where the pad is headed (its mean speed over the withdrawal); a blocked reflex draws none."""
    from nwr.common.config import PlannerSection
    from nwr.services.planner import strategies

    cfg = PlannerSection(strategy="whole-arm")
    strategy = strategies.build(cfg, DESC, MODEL, cfg.speed_fraction * DESC.v_max)
    pad, q0 = 5, DESC.home.copy()
    info = reflex_info(pad, 0.58)
    onset = strategy.start(q0, info.contact)
    info = msgspec.structs.replace(info, strategy="whole-arm", direction=onset.direction,
                                   duration_s=strategy.duration_s)
    core = c.ViewCore(DESC, MODEL)
    core.apply(state(q0))
    core.apply(status("REFLEX", reflex=info, saved=list(q0)))
    ghost = core.frame(0).ghost
    assert ghost is not None and ghost.arrow is not None and ghost.strategy == "whole-arm"
    length = float(np.linalg.norm(ghost.arrow.tip - ghost.arrow.tail))
    assert length == pytest.approx(0.58 * WholeArmSettings().distance_m)
    assert ghost.arrow.tip - ghost.arrow.tail == pytest.approx(-length * MODEL.pad_normal(q0, pad), abs=1e-3)
    blocked = msgspec.structs.replace(info, direction=[0.0, 0.0, 0.0], reason="blocked")
    core.apply(status("REFLEX", seq=1, reflex=blocked, saved=list(q0)))
    assert core.frame(1).ghost is None
