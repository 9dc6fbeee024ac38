"""The live ROS 2 side: the services' topics as rmw_zenoh puts them ([ros2] enabled) and the gateway's ``ros2`` skin
source, checked against implementations nobody here wrote: ``rosbags``' CDR (de)serializer, Foxglove's decoders
(node), pamoja-ros2's rmw_zenoh key names, Zenoh's own serializer for the attachment, rmw_zenoh_cpp's token
grammar. A Zenoh router on loopback stands in for rmw_zenohd (which is one)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
import zenoh
from pamoja import ros2 as pamoja
from pipeline import WAIT_S, Pipeline, free_base_port
from ros2_live import attachment, foxglove_decode, parse_token, rmw_router, ros_client, router_config
from rosbags.typesys import get_types_from_msg

from nwr.common import keys
from nwr.common import messages as m
from nwr.common import rmw_zenoh as rz
from nwr.common.clock import ManualClock
from nwr.common.config import Profile, ZenohSection
from nwr.common.errors import ConfigError
from nwr.common.journal import Recording
from nwr.common.launch import apply_env_overrides
from nwr.common.node import Node
from nwr.common.robot import load_description
from nwr.common.ros2 import typestore
from nwr.common.ros2_msgs import JOINT_STATES, REFLEX, SKIN_ABSOLUTE, SKIN_CHANGE, Ros2Builder
from nwr.common.skinmap import pad_map
from nwr.services.gateway.sources import ros2 as source
from nwr.services.gateway.wiring import GatewayWiring
from nwr.services.profile import load_profile

DESC = load_description()
PADS = [p.name for p in DESC.pads]
JAZZY = typestore("jazzy")
AIRSKIN = "airskin_msgs/msg/AirskinStatus"
AIRSKIN_DEFINITION = "float32[] pressures"
N_VALUES = 11


def rest(n: int = N_VALUES) -> list[float]:
    return [1000.0 + i for i in range(n)]


def airskin_types() -> Any:
    types = typestore("jazzy")
    types.register(get_types_from_msg(AIRSKIN_DEFINITION, AIRSKIN))
    return types


def airskin_cdr(values: list[float], types: Any = None) -> bytes:
    """An AIRSKIN sample's CDR, serialized by rosbags (not by nwr)."""
    types = types or airskin_types()
    msg = types.types[AIRSKIN](pressures=np.array(values, dtype=np.float32))
    return bytes(types.serialize_cdr(msg, AIRSKIN))


# -- the settings ----------------------------------------------------------------------------------------------------

def test_the_ros2_side_is_off_by_default_and_its_router_is_loopback() -> None:
    profile = Profile()
    assert not profile.ros2.enabled and profile.ros2.router == ["tcp/127.0.0.1:7447"]
    assert profile.gateway.source == "sim"


@pytest.mark.parametrize(("table", "match"), [
    ('message_type = "AirskinStatus"', "write package/msg/Name"),
    ('message_type = "nwr_no_msgs/msg/Skin"\ndefinition = ""', "no standard ROS 2 type of jazzy"),
    ('definition = "float32[ pressures"', "no valid message definition"),
    ('values_field = "data"', "'data' is no field of airskin_msgs/msg/AirskinStatus"),
    ('message_type = "std_msgs/msg/String"\ndefinition = ""\nvalues_field = "data"', "is string, not an array"),
    ('pads = ["elbow"]', r"gateway.ros2.pads\[0\] = 'elbow' is no pad"),
    ('type_hash = "RIHS01_abc"', "type_hash"),
])
def test_a_ros2_source_that_cannot_work_is_one_line_at_load(tmp_path: Path, table: str, match: str) -> None:
    (tmp_path / "sim.toml").write_text(f"[gateway.ros2]\n{table}\n")
    if "type_hash" not in table:
        load_profile(str(tmp_path / "sim.toml"))  # the simulated skin does not use it
    (tmp_path / "p.toml").write_text(f'[gateway]\nsource = "ros2"\n[gateway.ros2]\n{table}\n')
    with pytest.raises(ConfigError, match=match) as info:
        load_profile(str(tmp_path / "p.toml"))
    assert "\n" not in str(info.value)


def test_standard_array_types_need_no_definition(tmp_path: Path) -> None:
    for msgtype in ("std_msgs/msg/Float32MultiArray", "std_msgs/msg/Float64MultiArray"):
        (tmp_path / "p.toml").write_text(f'[gateway]\nsource = "ros2"\n[gateway.ros2]\nmessage_type = "{msgtype}"\n'
                                         'definition = ""\nvalues_field = "data"\n')
        profile = load_profile(str(tmp_path / "p.toml"))
        assert source.settings_of(profile).message_type == msgtype


def test_a_router_beyond_loopback_needs_the_open_network_acknowledged() -> None:
    profile = Profile()
    profile.ros2.router = ["tcp/10.0.0.9:7447"]
    apply_env_overrides(profile, {})  # unused while nothing of ROS 2 runs
    profile.ros2.enabled = True
    with pytest.raises(ConfigError, match="no TLS.*NWR_INSECURE=1"):
        apply_env_overrides(profile, {})
    assert apply_env_overrides(profile, {"NWR_INSECURE": "1"}).ros2.router == ["tcp/10.0.0.9:7447"]


# -- the ros2 skin source's samples, in process ---------------------------------------------------------------------

def skin(cfg: source.Settings | None = None, types: Any = None) -> tuple[source.Ros2Skin, list[m.SkinPressure],
                                                                          list[tuple[str, str, str]]]:
    profile = Profile()
    profile.gateway.source = "ros2"
    cfg = cfg or source.Settings()
    outs: list[m.SkinPressure] = []
    diags: list[tuple[str, str, str]] = []
    wiring = GatewayWiring(profile, journal=Recording(ManualClock(10**9)), out=lambda k, msg: outs.append(msg),
                           diag=lambda *a, **k: None)
    wiring.origin()
    feed = source.Ros2Skin(cfg, types or source.skin_types(cfg, "jazzy"), pad_map(cfg.pads, PADS), wiring,
                           threading.Lock(), lambda level, code, text, **kw: diags.append((level, code, text)))
    return feed, outs, diags


def sample(payload: bytes, msgtype: str = AIRSKIN, hash_: str | None = None) -> Any:
    from nwr.common.ros2 import Ros2Sample

    return Ros2Sample("0/x", rz.dds_type_name(msgtype), hash_ or rz.type_hash(airskin_types(), msgtype), payload,
                      rz.Attachment(1, 0, bytes(16)))


def test_rosbags_samples_are_mapped_as_the_ros1_source_maps_them() -> None:
    feed, outs, diags = skin()
    values = rest()
    values[4] += 9.0
    feed.on_sample(sample(airskin_cdr(values)))
    assert diags == [] and len(outs) == 1 and outs[0].source == "ros2"
    assert outs[0].absolute_hpa == pytest.approx(np.float32(values[:10]).tolist())
    assert outs[0].valid == [True] * 10


@pytest.mark.parametrize("msgtype", ["std_msgs/msg/Float32MultiArray", "std_msgs/msg/Float64MultiArray"])
def test_multi_arrays_of_either_width(msgtype: str) -> None:
    cfg = source.Settings(message_type=msgtype, definition="", values_field="data")
    feed, outs, diags = skin(cfg)
    layout = JAZZY.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    dtype = np.float32 if "32" in msgtype else np.float64
    msg = JAZZY.types[msgtype](layout=layout, data=np.array(rest(), dtype=dtype))
    feed.on_sample(sample(bytes(JAZZY.serialize_cdr(msg, msgtype)), msgtype, rz.type_hash(JAZZY, msgtype)))
    assert diags == [] and outs[0].absolute_hpa == rest()[:10]


def test_bad_samples_are_dropped_or_marked_and_reported() -> None:
    feed, outs, diags = skin()
    good = airskin_cdr(rest())
    feed.on_sample(sample(good[:6]))  # cut CDR
    feed.on_sample(sample(b"\x00\x01\x00\x00" + b"\xff" * 12))  # a sequence length no sample holds
    feed.on_sample(sample(good, "std_msgs/msg/Float32MultiArray"))  # another type on the topic
    feed.on_dropped("0/x", "an rmw_zenoh attachment is 33 bytes, not 0")
    assert outs == [] and [d[1] for d in diags] == ["ros2_bad_message"] * 3 + ["ros2_no_attachment"]
    assert "does not decode as airskin_msgs/msg/AirskinStatus" in diags[0][2]
    assert "its type is std_msgs::msg::dds_::Float32MultiArray_, not airskin_msgs::msg::dds_::AirskinStatus_" \
        in diags[2][2]
    assert (feed.bad, feed.dropped) == (3, 1)

    feed.on_sample(sample(airskin_cdr(rest(7))))  # too short: the pads it does not reach are invalid
    feed.on_sample(sample(airskin_cdr([v * 100 for v in rest()])))  # Pa, not hPa
    assert outs[0].valid == [i < 7 for i in range(10)] and not any(outs[1].valid)
    assert [d[1] for d in diags[4:]] == ["ros2_bad_message", "ros2_units"]
    assert "carries 7 values" in diags[4][2] and "gateway.ros2's scale_hpa" in diags[5][2]


def test_a_configured_type_hash_refuses_another_definition() -> None:
    theirs = rz.type_hash(airskin_types(), AIRSKIN)
    feed, outs, diags = skin(source.Settings(type_hash=theirs))
    feed.on_sample(sample(airskin_cdr(rest())))
    feed.on_sample(sample(airskin_cdr(rest()), hash_=rz.TYPE_HASH_NOT_SUPPORTED))
    assert len(outs) == 1 and [d[1] for d in diags] == ["ros2_bad_message"] and "type hash" in diags[0][2]


# -- names against a third party's ---------------------------------------------------------------------------------

@pytest.mark.parametrize(("topic", "msgtype"), [
    (JOINT_STATES, "sensor_msgs/msg/JointState"), (SKIN_ABSOLUTE, "std_msgs/msg/Float64MultiArray"),
    (SKIN_CHANGE, "std_msgs/msg/Float64MultiArray"), (REFLEX, "visualization_msgs/msg/MarkerArray"),
    ("/bullet_ros/airskin_status", AIRSKIN),
])
@pytest.mark.parametrize("domain", [0, 42])
def test_keys_and_names_are_pamoja_ros2s(topic: str, msgtype: str, domain: int) -> None:
    hash_ = rz.type_hash(airskin_types(), msgtype)
    assert pamoja.is_valid_name(topic)
    assert rz.topic_keyexpr(domain, topic, msgtype, hash_) == pamoja.entity_key(domain, topic, msgtype, hash_)
    assert rz.dds_type_name(msgtype) == pamoja.dds_type_name(msgtype)
    assert rz.mangle(topic) == pamoja.percent_mangle(topic)
    assert pamoja.type_hash_digest(hash_) == bytes.fromhex(hash_.removeprefix("RIHS01_"))


# -- live, over Zenoh on loopback ------------------------------------------------------------------------------------

class Outputs:
    """A wiring with the outputs of the bridge, the gateway and a planner (Node.wire's contract)."""

    service = "test"
    outputs = (keys.ROBOT_STATE, keys.SKIN_PRESSURE, keys.planner_status("cartesian"))

    def __init__(self, profile: Profile, *, journal: Any, out: Any, diag: Any) -> None:
        self.out = out

    def params(self) -> dict[str, Any]:
        return {}


def state(seq: int) -> m.RobotState:
    q = (np.asarray(DESC.home) + 0.01 * seq).tolist()
    return m.RobotState(seq=seq, stamp_ns=time.monotonic_ns(), q=q, dq=[0.1 * seq] * len(q), status="ok",
                        owner="cartesian", backend="sim")


def pressure(seq: int) -> m.SkinPressure:
    n = len(PADS)
    absolute = [1000.0 + seq + i for i in range(n)]
    valid = [i != 3 for i in range(n)]
    return m.SkinPressure(seq=seq, stamp_ns=time.monotonic_ns(), absolute_hpa=absolute, baseline_hpa=[1000.0] * n,
                          change_hpa=[float(seq)] * n, contact=[False] * n, valid=valid)


@pytest.mark.e2e
def test_the_services_topics_decode_with_rosbags_and_foxglove(node: str) -> None:
    """A service's outputs, put through Node.wire with [ros2] enabled, as a ROS 2 subscriber receives them."""
    with rmw_router() as (endpoint, router), ros_client(endpoint) as ros:
        got: list[zenoh.Sample] = []
        lock = threading.Lock()

        def keep(s: zenoh.Sample) -> None:
            with lock:
                got.append(s)

        sub = ros.declare_subscriber("0/**", keep)
        profile = Profile()
        profile.ros2 = rz.Ros2Section(enabled=True, router=[endpoint])
        with Node("bridge", "ur10e", ZenohSection(base_port=free_base_port()), token=False) as nwr:
            wiring = nwr.wire(Outputs, profile, threading.Lock())
            time.sleep(0.5)  # the subscription reaches the publishers
            status_key = keys.planner_status("cartesian")
            for seq in range(1, 6):
                wiring.out(keys.ROBOT_STATE, state(seq))
                wiring.out(keys.SKIN_PRESSURE, pressure(seq))
            status = m.PlannerStatus(seq=1, stamp_ns=5, name="cartesian", strategy="cartesian", mode="TASK",
                                     task_time_s=0.0)
            wiring.out(status_key, status)
            wiring.out(status_key, status)  # no change: no marker
            time.sleep(0.5)
            tokens = [str(r.ok.key_expr) for r in ros.liveliness().get("@ros2_lv/**", timeout=2.0) if r.ok]
        sub.undeclare()
    by_topic: dict[str, list[zenoh.Sample]] = {}
    for s in got:
        by_topic.setdefault(str(s.key_expr).rsplit("/", 2)[0], []).append(s)
    types = {JOINT_STATES: "sensor_msgs/msg/JointState", SKIN_ABSOLUTE: "std_msgs/msg/Float64MultiArray",
             SKIN_CHANGE: "std_msgs/msg/Float64MultiArray", REFLEX: "visualization_msgs/msg/MarkerArray"}
    assert sorted(by_topic) == sorted(f"0/{t.strip('/')}" for t in types)
    assert [len(by_topic[f"0/{t.strip('/')}"]) for t in types] == [5, 5, 5, 1]

    # The graph: the node and one publisher per topic, in rmw_zenoh_cpp's grammar, each key's type and hash.
    parts = [parse_token(t) for t in tokens]
    assert [p[5] for p in parts].count("NN") == 1 and [p[5] for p in parts].count("MP") == 4
    for p in parts:
        if p[5] == "MP":
            topic, msgtype = rz.demangle(p[9]), types[rz.demangle(p[9])]
            assert p[8] == "nwr_bridge" and p[10] == pamoja.dds_type_name(msgtype)
            assert p[11] == rz.type_hash(JAZZY, msgtype)
            key = pamoja.entity_key(0, topic, msgtype, p[11])
            samples = by_topic[key.rsplit("/", 2)[0]]
            assert all(str(s.key_expr) == key for s in samples)
            # Every sample's attachment: the sequence from 1, a source time now, the GID of its publisher's token.
            att = [rz.Attachment.decode(s.attachment.to_bytes()) for s in samples]
            assert [a.sequence_number for a in att] == list(range(1, len(att) + 1))
            assert all(abs(a.source_timestamp_ns - time.time_ns()) < 60e9 for a in att)
            assert {a.gid for a in att} == {rz.gid_of("/".join(p))}

    # rosbags' deserializer and Foxglove's decoders read the same values.
    flat = [(types["/" + k.removeprefix("0/")], bytes(s.payload.to_bytes())) for k, ss in by_topic.items()
            for s in ss]
    theirs = foxglove_decode(node, JAZZY, flat)
    for (msgtype, data), fox in zip(flat, theirs, strict=True):
        ours = JAZZY.deserialize_cdr(data, msgtype)
        if msgtype.endswith("JointState"):
            seq = round(ours.velocity[0] / 0.1)
            assert list(ours.name) == list(DESC.joints) == fox["name"]
            assert ours.position.tolist() == fox["position"] == state(seq).q
            assert ours.header.stamp.sec == fox["header"]["stamp"]["sec"] > 1.7e9  # UTC, not the monotonic clock
        elif msgtype.endswith("MultiArray"):
            assert fox["layout"]["dim"][0] == {"label": "pads", "size": len(PADS), "stride": len(PADS)}
            values = [None if math.isnan(v) else v for v in ours.data.tolist()]
            assert values == fox["data"] and values[3] is None
        else:
            assert ours.markers[0].text == fox["markers"][0]["text"] == "cartesian: TASK"


PRESSED = 4  # elbow_outer by the default mapping


@pytest.mark.e2e
def test_a_ros2_skin_drives_the_gateway_and_comes_back_as_ros2_topics(pipeline: Pipeline, node: str) -> None:
    """``nwr run gateway`` on the ros2 source, [ros2] enabled: a ROS 2 publisher's AIRSKIN samples (rosbags' CDR,
    Zenoh's attachment) become skin/pressure, bad ones are reported, and the skin is published back to ROS 2."""
    with rmw_router() as (endpoint, _router), ros_client(endpoint) as ros:
        pipeline.configure(f'[gateway]\nsource = "ros2"\nrate_hz = 30.0\n[ros2]\nenabled = true\n'
                           f'router = ["{endpoint}"]\n')
        back: list[zenoh.Sample] = []
        sub = ros.declare_subscriber(f"0/{SKIN_ABSOLUTE.strip('/')}/**", back.append)
        types = airskin_types()
        key = rz.topic_keyexpr(0, "/bullet_ros/airskin_status", AIRSKIN, rz.type_hash(types, AIRSKIN))
        pub = ros.declare_publisher(key)
        gid = bytes(range(16))
        with pipeline.node() as nwr:
            pressures: list[m.SkinPressure] = []
            diags: list[m.Diagnostic] = []
            nwr.subscribe(keys.SKIN_PRESSURE, pressures.append)
            nwr.subscribe(keys.diag("gateway"), diags.append)
            pipeline.start("gateway", "run", "gateway")
            pipeline.wait_alive(nwr.session, {"gateway"})
            pipeline.wait_until(lambda: any(t.endswith("/MS/%/%/nwr_gateway/%bullet_ros%airskin_status/"
                                                       f"airskin_msgs::msg::dds_::AirskinStatus_/{key.rsplit('/')[-1]}"
                                                       "/::,:,:,:,,")
                                            for t in (str(r.ok.key_expr) for r in
                                                      ros.liveliness().get("@ros2_lv/**", timeout=1.0) if r.ok)),
                                WAIT_S, "the gateway's ROS 2 subscription")
            for seq in range(1, 41):
                values = rest()
                if seq > 25:
                    values[PRESSED] += 12.0
                pub.put(airskin_cdr(values, types), attachment=attachment(seq, time.time_ns(), gid))
                time.sleep(1 / 30)
            pub.put(airskin_cdr(rest(), types))  # no attachment: dropped
            pub.put(b"\x00\x01\x00\x00\x07", attachment=attachment(41, time.time_ns(), gid))  # no AirskinStatus
            pub.put(airskin_cdr(rest(5), types), attachment=attachment(42, time.time_ns(), gid))  # 5 values
            pipeline.wait_until(lambda: len(pressures) >= 41 and {"ros2_no_attachment", "ros2_bad_message"}
                                <= {d.code for d in diags}, WAIT_S, "the samples and the diagnostics")
            assert len(pressures) == 41, [d.code for d in diags]
            time.sleep(0.3)
            assert pipeline.stop("gateway") == 0
        sub.undeclare()
    assert all(p.source == "ros2" for p in pressures) and len(pressures) == 41
    assert pressures[-2].change_hpa[PRESSED] == pytest.approx(12.0, abs=0.1) and pressures[-2].contact[PRESSED]
    assert pressures[-1].valid == [i < 5 for i in range(len(PADS))]
    assert all(p.valid == [True] * len(PADS) for p in pressures[:-1])
    log = pipeline.log("gateway")
    assert "Traceback" not in log and "41 skin samples, 2 with problems, 1 without rmw_zenoh's attachment" in log
    # The skin back on ROS 2: the gateway's samples, decoded by rosbags and by Foxglove's decoders alike.
    assert len(back) >= 35
    data = [("std_msgs/msg/Float64MultiArray", bytes(s.payload.to_bytes())) for s in back]
    for (msgtype, raw), fox in zip(data, foxglove_decode(node, JAZZY, data), strict=True):
        ours = [None if math.isnan(v) else v for v in JAZZY.deserialize_cdr(raw, msgtype).data.tolist()]
        assert ours == fox["data"] and len(ours) == len(PADS)
    assert [None if v is None else round(v, 3) for v in fox["data"]] == \
        [round(v, 3) if ok else None for v, ok in zip(pressures[-1].absolute_hpa, pressures[-1].valid, strict=True)]


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_the_messages_serialize_with_either_distributions_definitions(distro: str) -> None:
    types = typestore(distro)
    build = Ros2Builder(types, DESC.joints, offset_ns=10**18)
    status = m.PlannerStatus(seq=1, stamp_ns=5, name="cartesian", strategy="cartesian", mode="REFLEX",
                             task_time_s=0.0)
    for msg, msgtype in ((build.joint_state(state(1)), "sensor_msgs/msg/JointState"),
                         (build.skin(pressure(1))[1], "std_msgs/msg/Float64MultiArray"),
                         (build.reflex(status, DESC.base_frame), "visualization_msgs/msg/MarkerArray")):
        again = types.deserialize_cdr(bytes(types.serialize_cdr(msg, msgtype)), msgtype)
        assert type(again).__name__ == type(msg).__name__
    torques = [0.5, -1.25, 0.0, 23.0, 0.0, 0.0]  # a controller that estimates its external torques: the efforts
    with_tau = build.joint_state(msgspec.structs.replace(state(2), tau_ext=torques))
    again = types.deserialize_cdr(bytes(types.serialize_cdr(with_tau, "sensor_msgs/msg/JointState")),
                                  "sensor_msgs/msg/JointState")
    assert list(again.effort) == torques and list(again.velocity) == [0.2] * len(torques)
    assert list(build.joint_state(state(3)).effort) == []  # none estimated: empty, as ROS leaves an unknown field
    assert build.reflex(status, DESC.base_frame) is None  # no change, no marker
    string = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"  # the design document's
    assert rz.type_hash(types, "std_msgs/msg/String", humble=distro == "humble") == (
        rz.TYPE_HASH_NOT_SUPPORTED if distro == "humble" else string)


@pytest.mark.e2e
def test_a_router_that_is_not_there_yet_is_reported_and_joined_when_it_comes() -> None:
    from nwr.common.ros2 import Ros2Link

    port = free_base_port(1)
    endpoint = f"tcp/127.0.0.1:{port}"
    diags: list[tuple[str, str]] = []
    link = Ros2Link(rz.Ros2Section(enabled=True, router=[endpoint]), "bridge",
                    lambda level, code, text, **kw: diags.append((level, code)))
    try:
        pub = link.publisher(JOINT_STATES, "sensor_msgs/msg/JointState")
        build_state = Ros2Builder(link.types, DESC.joints).joint_state(state(1))
        pub.publish(build_state)
        assert diags == [("error", "ros2_router_unreachable")] and (pub.sent, pub.dropped) == (0, 1)
        with zenoh.open(router_config(endpoint)) as router:
            got: list[zenoh.Sample] = []
            sub = router.declare_subscriber("0/**", got.append)
            deadline = time.monotonic() + WAIT_S
            while not got and time.monotonic() < deadline:
                pub.publish(build_state)
                time.sleep(0.2)
            sub.undeclare()
        assert got and str(got[0].key_expr) == pub.key and pub.token.endswith("/::,:,:,:,,")
        assert rz.Attachment.decode(got[0].attachment.to_bytes()).gid == rz.gid_of(pub.token)
    finally:
        link.close()
