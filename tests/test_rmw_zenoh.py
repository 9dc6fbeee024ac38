"""rmw_zenoh's names and bytes (nwr.common.rmw_zenoh) against implementations nobody here wrote: the type hash
from ``rosbags``, the design document's example key (the same in roslibrust's, ros-z's and other published
rmw_zenoh-compatible code), the attachment against Zenoh's own serializer (zenoh.ext), the tokens against
rmw_zenoh_cpp's grammar (liveliness_utils.cpp) and Zenoh's key-expression rules."""

from __future__ import annotations

import pytest
import zenoh
import zenoh.ext as zx
from ros2_live import parse_token
from rosbags.typesys import Stores, get_typestore

from nwr.common import rmw_zenoh as rz

STORE = get_typestore(Stores.ROS2_JAZZY)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ZID = "1d4e2b9f0c6a4e8b9a7c3f2e1d0c9b8a"


def test_the_data_key_of_the_design_documents_example() -> None:
    assert rz.type_hash(STORE, "std_msgs/msg/String") == STRING_HASH
    assert rz.topic_keyexpr(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    js = rz.type_hash(STORE, "sensor_msgs/msg/JointState")
    assert js.startswith("RIHS01_") and len(js) == 71
    assert rz.topic_keyexpr(7, "/nwr/ur10e/joint_states/", "sensor_msgs/msg/JointState", js) == \
        f"7/nwr/ur10e/joint_states/sensor_msgs::msg::dds_::JointState_/{js}"
    humble = rz.type_hash(STORE, "std_msgs/msg/String", humble=True)
    assert rz.topic_keyexpr(0, "chatter", "std_msgs/String", humble) == \
        "0/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported"
    for key in (rz.topic_keyexpr(0, "/chatter", "std_msgs/msg/String", STRING_HASH),):
        assert str(zenoh.KeyExpr(key)) == key  # a valid, canonical Zenoh key expression


@pytest.mark.parametrize(("domain", "topic", "msgtype"), [
    (233, "/chatter", "std_msgs/msg/String"), (0, "/", "std_msgs/msg/String"), (0, "/a//b", "std_msgs/msg/String"),
    (0, "/a/*", "std_msgs/msg/String"), (0, "/chatter", "String"), (0, "/chatter", "a/b/c/d"),
])
def test_names_that_are_no_ros2_names_are_refused(domain: int, topic: str, msgtype: str) -> None:
    with pytest.raises(ValueError):
        rz.topic_keyexpr(domain, topic, msgtype, STRING_HASH)


@pytest.mark.parametrize(("seq", "stamp"), [(0, 0), (1, 1_700_000_000_123_456_789), (2**63 - 1, -1), (-5, 2**62)])
def test_the_attachment_is_zenohs_own_serialization_of_seq_stamp_and_gid(seq: int, stamp: int) -> None:
    gid = bytes(range(3, 19))
    ours = rz.Attachment(seq, stamp, gid).encode()
    theirs = zx.z_serialize((zx.Int64(seq), zx.Int64(stamp), gid)).to_bytes()
    assert ours == theirs and len(ours) == 33
    assert zx.z_deserialize(tuple[zx.Int64, zx.Int64, bytes], zenoh.ZBytes(ours)) == (seq, stamp, gid)
    assert rz.Attachment.decode(theirs) == rz.Attachment(seq, stamp, gid)


@pytest.mark.parametrize("data", [b"", bytes(32), bytes(34), bytes(16) + b"\x0f" + bytes(16)])
def test_anything_but_the_33_bytes_is_no_attachment(data: bytes) -> None:
    with pytest.raises(ValueError):
        rz.Attachment.decode(data)
    with pytest.raises(ValueError):
        rz.Attachment(0, 0, bytes(15)).encode()


def test_liveliness_tokens_follow_rmw_zenohs_grammar() -> None:
    node = rz.Node(domain_id=0, zid=ZID, node_id=0, name="talker")
    assert node.token() == f"@ros2_lv/0/{ZID}/0/0/NN/%/%/talker"
    pub = node.endpoint_token(11, "MP", "chatter", "std_msgs/msg/String", STRING_HASH)
    assert pub == f"@ros2_lv/0/{ZID}/0/11/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/" \
        "::,:,:,:,,"
    parts = parse_token(pub)
    assert rz.demangle(parts[9]) == "/chatter" and parts[12].count(":") == 5
    parse_token(node.token())

    lab = rz.Node(domain_id=3, zid=ZID, node_id=2, name="skin", namespace="/nwr/ur10e")
    sub = lab.endpoint_token(5, "MS", "airskin", "std_msgs/msg/Float64MultiArray", "TypeHashNotSupported",
                             rz.Qos(reliability=rz.BEST_EFFORT, durability=rz.TRANSIENT_LOCAL, depth=1))
    parts = parse_token(sub)
    assert parts[6:10] == ["%", "%nwr%ur10e", "skin", "%nwr%ur10e%airskin"]
    assert parts[12] == "2:1:,1:,:,:,,"
    with pytest.raises(ValueError):
        rz.Node(0, ZID, 0, "a/b").token()


def test_a_gid_is_16_bytes_per_token() -> None:
    node = rz.Node(0, ZID, 0, "talker")
    a = rz.gid_of(node.endpoint_token(1, "MP", "/a", "std_msgs/msg/String", STRING_HASH))
    b = rz.gid_of(node.endpoint_token(2, "MP", "/a", "std_msgs/msg/String", STRING_HASH))
    assert len(a) == len(b) == 16 and a != b
