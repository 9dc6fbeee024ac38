"""The taxel skin in the pipeline (robot.skin = "taxels", common/skin.py): the profile's selection, the
gateway's per-taxel samples in hPa, the gain estimator's pain per pad from the taxels' contacts, the strongest
Contact's point and normal (and its wire form on the pads, unchanged), the strategies reading a contact's own
location, and the per-touch table's touches from taxel samples."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.journal import Recording
from nwr.common.launch import Touch, TouchScript
from nwr.common.robot import RobotModel, load_description
from nwr.common.skin import contact_normal, contact_point, entry_pads, load_skin
from nwr.common.taxels import finger_pressure, nearest_taxel
from nwr.services.gain.taxels import TaxelGain
from nwr.services.gain.wiring import GainWiring
from nwr.services.gateway.wiring import GatewayWiring
from nwr.services.planner import strategies
from nwr.services.tools.recordings.analysis import _segment

DESC = load_description()
MODEL = RobotModel(DESC)
PROFILE = msgspec.convert({"robot": {"skin": "taxels"}}, Profile)
SKIN = load_skin(PROFILE, DESC)
assert SKIN is not None
PAD = {pad.name: pad.id for pad in DESC.pads}
KPA_TO_HPA = 10.0


def finger(pad: str, force_n: float,
           shift: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A finger's readings (kPa) at the taxel nearest the pad's point, moved by ``shift`` (link frame); and its
    centre."""
    p = DESC.pad(pad)
    centre = SKIN.points[nearest_taxel(SKIN, p.link, p.point + np.asarray(shift))]
    return finger_pressure(SKIN, p.link, centre, 0.03, force_n), centre


def sample(kpa: np.ndarray, seq: int = 0, valid: list[bool] | None = None) -> m.SkinPressure:
    change = (kpa * KPA_TO_HPA).tolist()
    n = len(change)
    return m.SkinPressure(seq=seq, stamp_ns=seq, absolute_hpa=change, baseline_hpa=[0.0] * n, change_hpa=change,
                          contact=[c >= 1.0 for c in change], valid=valid or [True] * n)


def estimator(**gain: object) -> TaxelGain:
    profile = msgspec.convert({"robot": {"skin": "taxels"}, "gain": gain}, Profile)
    return TaxelGain(profile.gain, DESC.pads, SKIN, profile.gateway.contact_hpa)


def test_the_profile_selects_the_skin_and_refuses_what_cannot_be() -> None:
    assert load_skin(Profile(), DESC) is None  # the pads by default
    assert SKIN is not None and len(SKIN) == 300 and SKIN.path.name == "skin-taxels.toml"
    with pytest.raises(msgspec.ValidationError, match="robot.skin"):
        msgspec.convert({"robot": {"skin": "airskin"}}, Profile)
    fr3 = msgspec.convert({"robot": {"name": "fr3", "description": "fr3", "skin": "taxels"}}, Profile)
    with pytest.raises(ConfigError, match="no taxel skin"):
        load_skin(fr3)
    with pytest.raises(ConfigError, match="force"):
        estimator(model="effective-mass")
    with pytest.raises(ConfigError, match="overrides"):
        estimator(overrides={"forearm_top": {"k": 5.0}})


def test_a_finger_gives_its_pads_level_and_the_strongest_contact_its_place() -> None:
    gain = estimator()
    for pad, force, level in (("upper_arm_top", 1.0, 2), ("forearm_bottom", 3.0, 3), ("upper_arm_bottom", 12.0, 4)):
        kpa, centre = finger(pad, force)
        pain = gain.process(sample(kpa), 5)
        expected = [1] * len(DESC.pads)
        expected[PAD[pad]] = level
        assert pain.level == expected
        assert [g > 0 for g in pain.gain] == [level >= 3 and i == PAD[pad] for i in range(len(DESC.pads))]
        if level < 3:
            assert pain.strongest is None  # PL 2: felt, no gain, no contact (as on the pads)
            continue
        c = pain.strongest
        assert c is not None and c.pad == PAD[pad] and c.name == pad and c.link == DESC.pad(pad).link
        assert c.force_n == pytest.approx(force, rel=1e-9) and c.level == level
        assert c.gain == pain.gain[PAD[pad]]
        assert np.linalg.norm(np.asarray(c.point) - centre) < 0.003  # the centroid: the finger's centre
        assert np.asarray(c.normal) @ SKIN.normals[nearest_taxel(SKIN, c.link, centre)] > 0.99
        assert c.change_hpa == pytest.approx(kpa.max() * KPA_TO_HPA)
        assert pain.trace == m.Trace(0, 0) and pain.model == "continuous"


def test_a_finger_too_light_for_a_pain_level_is_a_light_touch_of_its_pad() -> None:
    gain = estimator()
    kpa, _ = finger("forearm_top", 0.3)
    pain = gain.process(sample(kpa), 5)
    assert pain.level == [1] * len(DESC.pads) and pain.light_touch == [PAD["forearm_top"]]
    kpa, _ = finger("forearm_top", 3.0)
    assert gain.process(sample(kpa), 6).light_touch == []  # felt at PL 3: no light touch


def test_two_fingers_on_one_patch_give_its_pad_the_stronger_and_the_strongest_is_the_firmest() -> None:
    weak, _ = finger("upper_arm_top", 2.5)
    strong, centre = finger("upper_arm_top", 8.0, (-0.15, 0.0, 0.0))  # 15 cm along the tube: another cluster
    other, _ = finger("forearm_top", 6.0)
    pain = estimator().process(sample(weak + strong + other), 0)
    assert len(estimator().process(sample(weak + strong), 0).level) == len(DESC.pads)
    gain = estimator()
    gain.process(sample(weak + strong + other), 0)
    assert sorted(round(c.force_n, 6) for c in gain.contacts) == [2.5, 6.0, 8.0]
    assert pain.level[PAD["upper_arm_top"]] == 4 and pain.level[PAD["forearm_top"]] == 4
    assert pain.gain[PAD["upper_arm_top"]] == gain.level_gain(8.0)[1]
    assert pain.strongest is not None and pain.strongest.force_n == pytest.approx(8.0)
    assert np.linalg.norm(np.asarray(pain.strongest.point) - centre) < 0.003
    # Pads without taxels read level 1, gain 0.
    bare = [i for i, pad in enumerate(DESC.pads) if pad.name not in SKIN.patches]
    assert bare and all(pain.level[i] == 1 and pain.gain[i] == 0.0 for i in bare)


def test_discrete_model_and_unreadable_taxels_and_a_wrong_count() -> None:
    kpa, _ = finger("forearm_top", 3.0)
    pain = estimator(model="discrete").process(sample(kpa), 0)
    assert pain.gain[PAD["forearm_top"]] == 0.35 and pain.model == "discrete"
    # Its taxels unreadable: no contact, no gain (a pad that reports garbage never triggers a reflex).
    blind = [not v for v in (kpa > 0)]
    assert estimator().process(sample(kpa, valid=blind), 0).strongest is None
    with pytest.raises(ValueError, match="300"):
        estimator().process(sample(kpa[:10]), 0)


def test_a_pads_contact_encodes_as_before_and_old_ones_decode() -> None:
    class OldContact(msgspec.Struct, frozen=True):
        pad: int
        name: str
        region: str
        change_hpa: float
        level: int
        gain: float

    old = OldContact(pad=3, name="forearm_top", region="forearm", change_hpa=12.5, level=4, gain=0.7)
    new = m.Contact(pad=3, name="forearm_top", region="forearm", change_hpa=12.5, level=4, gain=0.7)
    assert msgspec.msgpack.encode(new) == msgspec.msgpack.encode(old)
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(old), type=m.Contact) == new
    taxel = msgspec.structs.replace(new, link="forearm_link", point=[-0.2, 0.05, 0.04], normal=[0.0, 1.0, 0.0],
                                    force_n=4.0)
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(taxel), type=m.Contact) == taxel


def test_a_contacts_point_and_normal_are_its_own_where_it_carries_them() -> None:
    q = DESC.home + 0.3
    pad = DESC.pad("forearm_top")
    on_pad = m.Contact(pad=pad.id, name=pad.name, region=pad.region, change_hpa=12.0, level=4, gain=1.0)
    np.testing.assert_array_equal(contact_point(MODEL, q, on_pad), MODEL.pad_point(q, pad.id))
    np.testing.assert_array_equal(contact_normal(MODEL, q, on_pad), MODEL.pad_normal(q, pad.id))
    point, normal = np.array([-0.3, 0.0, 0.1]), np.array([0.0, 0.0, 1.0])
    taxel = msgspec.structs.replace(on_pad, link=pad.link, point=point.tolist(), normal=normal.tolist())
    pose = MODEL.frame_pose(q, pad.link)
    np.testing.assert_allclose(contact_point(MODEL, q, taxel), pose[:3, :3] @ point + pose[:3, 3], atol=1e-12)
    np.testing.assert_allclose(contact_normal(MODEL, q, taxel), pose[:3, 2], atol=1e-12)
    assert np.linalg.norm(contact_point(MODEL, q, taxel) - MODEL.pad_point(q, pad.id)) > 0.05


@pytest.mark.parametrize("strategy", ["cartesian", "whole-arm"])
def test_the_strategies_withdraw_along_the_contacts_own_normal(strategy: str) -> None:
    from nwr.common.config import PlannerSection

    cfg = PlannerSection(strategy=strategy)
    built = strategies.build(cfg, DESC, MODEL, cfg.speed_fraction * DESC.v_max)
    q = DESC.home.copy()
    pad = DESC.pad("upper_arm_top")
    # A contact on the pad's patch, its normal tilted 60 degrees from the pad's about the tube's axis (x).
    tilt = np.radians(60.0)
    link_normal = np.array([0.0, np.cos(tilt), np.sin(tilt)])
    contact = m.Contact(pad=pad.id, name=pad.name, region=pad.region, change_hpa=50.0, level=4, gain=1.0,
                        link=pad.link, point=(np.array([-0.3, 0.0, 0.176]) + 0.065 * link_normal).tolist(),
                        normal=link_normal.tolist())
    onset = built.start(q, contact)
    normal = contact_normal(MODEL, q, contact)
    assert normal @ MODEL.pad_normal(q, pad.id) < 0.9  # not the pad's own
    if strategy == "cartesian":
        direction = np.asarray(onset.direction)
        np.testing.assert_allclose(direction / np.linalg.norm(direction), -normal, atol=1e-12)
    else:
        np.testing.assert_allclose(built.normal, normal, atol=1e-12)  # type: ignore[attr-defined]
        np.testing.assert_allclose(built.contact, contact_point(MODEL, q, contact), atol=1e-12)  # type: ignore[attr-defined]


def test_the_gateway_and_gain_wirings_carry_a_scripted_touch_on_the_taxels() -> None:
    script = TouchScript(duration_s=1.0, touch=[Touch(pad="forearm_top", start_s=0.1, duration_s=0.3, peak_hpa=12.0)])
    clock = ManualClock(10**9)
    pressures: list[m.SkinPressure] = []
    pains: list[m.SkinPain] = []
    gateway = GatewayWiring(PROFILE, journal=Recording(clock), diag=lambda *a, **k: None, script=script,
                            out=lambda key, msg: pressures.append(msg) if key == "skin/pressure" else None)
    gain = GainWiring(PROFILE, journal=Recording(clock), out=lambda key, msg: pains.append(msg),
                      diag=lambda *a, **k: None)
    gateway.origin()
    for _ in range(25):  # 1 s at 25 Hz
        clock.advance(0.04)
        gateway.tick()
        gain.on_pressure(pressures[-1])
    assert all(len(p.change_hpa) == len(p.contact) == len(p.touch_hpa) == 300 for p in pressures)
    touched = [i for i, p in enumerate(pains) if p.strongest is not None]
    assert touched == list(range(2, 9))  # 0.12-0.36 s: the touch's 0.1-0.4 s at 25 Hz (the end excluded)
    peak = max(pressures, key=lambda p: max(p.change_hpa))
    # 12 hPa on the pads is PL 4's threshold; on the taxels 5 N, the finger's readings in hPa (kPa x 10).
    kpa, centre = finger("forearm_top", 5.0)
    np.testing.assert_allclose(peak.change_hpa, kpa * KPA_TO_HPA, rtol=1e-9, atol=1e-9)
    strongest = pains[touched[0]].strongest
    assert strongest is not None and strongest.name == "forearm_top" and strongest.level == 4
    assert np.linalg.norm(np.asarray(strongest.point) - centre) < 0.003
    with pytest.raises(ConfigError, match="simulated skin"):
        GatewayWiring(msgspec.convert({"robot": {"skin": "taxels"}, "gateway": {"source": "ros1"}}, Profile),
                      journal=Recording(clock), out=lambda *a: None, diag=lambda *a, **k: None, script=script)


def test_the_touch_table_segments_taxel_samples_by_pad() -> None:
    kpa, _ = finger("forearm_top", 5.0)
    quiet = np.zeros(len(SKIN))
    samples = [sample(k, seq) for seq, k in enumerate([quiet, kpa, kpa, quiet, quiet])]
    pads = entry_pads(SKIN, DESC.pads)
    assert sorted(set(pads.tolist())) == sorted(PAD[p] for p in SKIN.patches)
    touches = _segment(samples, DESC, pads)
    assert [(t.name, t.first_seq, t.last_seq) for t in touches] == [("forearm_top", 1, 2)]
    assert touches[0].peak_hpa == pytest.approx(kpa.max() * KPA_TO_HPA)
    assert _segment(samples, DESC) == []  # without the taxels' pads: nothing made up


@pytest.mark.slow
def test_a_lockstep_demo_on_the_taxels_withdraws_at_the_fingers_and_verifies(tmp_path, capsys) -> None:
    """``nwr demo --fast --skin taxels`` on two fingers (upper arm 20 hPa, forearm 14 hPa at 3 s): a reflex
    whose contact lies under the firmer finger, the per-touch table complete, ``nwr verify`` bit for bit."""
    from nwr.common.recordings import read_recording
    from nwr.services import cli
    from nwr.services.gateway.taxels import covering_taxel

    path = tmp_path / "taxels.mcap"
    assert cli.main(["demo", "--fast", "--skin", "taxels", "--world", "scripted", "--script", "two-fingers",
                     "--reflex", "cartesian", "-o", str(path)]) == 0
    table = capsys.readouterr().out
    assert "all 2 scripted touches as expected" in table
    records, _ = read_recording(path)
    pressure = [r.message for r in records if r.key == "skin/pressure"]
    assert pressure and all(len(p.change_hpa) == 300 for p in pressure)
    reflexes = {r.message.reflex.reflex_seq: r.message.reflex for r in records
                if isinstance(r.message, m.PlannerStatus) and r.message.reflex is not None}
    assert len(reflexes) == 1
    reflex = next(iter(reflexes.values()))
    contact = reflex.contact
    pad = DESC.pad("upper_arm_top")  # 20 hPa: 10 N on the taxels, the firmer finger
    assert contact.name == pad.name and contact.link == pad.link and contact.force_n == pytest.approx(10.0)
    under = SKIN.points[covering_taxel(SKIN, pad)]
    assert np.linalg.norm(np.asarray(contact.point) - under) < 0.003
    assert 2.9e9 < reflex.trace.stamp_ns - pressure[0].stamp_ns < 3.2e9
    assert cli.main(["verify", str(path)]) == 0
    assert "4 of 4 service runs re-made their recorded outputs bit for bit" in capsys.readouterr().out


def test_the_door_and_the_bridge_take_a_taxel_sample_and_a_located_contact() -> None:
    from nwr.common.door import Door

    kpa, _ = finger("forearm_top", 5.0)
    door = Door(DESC, SKIN)
    assert door.refuse(sample(kpa)) is None
    assert Door(DESC).refuse(sample(kpa)).cause == "wrong pad count"  # type: ignore[union-attr]
    pain = estimator().process(sample(kpa), 0)
    assert door.refuse(pain) is None and pain.strongest is not None
    off = msgspec.structs.replace(pain.strongest, link="base_link_inertia")
    bent = msgspec.structs.replace(pain.strongest, normal=[0.0, 2.0, 0.0])
    for contact in (off, bent):
        refused = door.refuse(msgspec.structs.replace(pain, strongest=contact))
        assert refused is not None and refused.cause == "contact off the skin"
    # The bridge: a taxel sample is fresh skin data; a pad is blind when all its taxels are invalid.
    from nwr.services.bridge.wiring import BridgeWiring

    clock = ManualClock(10**9)
    bridge = BridgeWiring(PROFILE, journal=Recording(clock), out=lambda *a: None, diag=lambda *a, **k: None).core
    bridge.on_skin(sample(kpa), clock.now_ns())
    assert bridge.last_skin_ns == clock.now_ns() and not bridge.events
    taxels = entry_pads(SKIN, DESC.pads)
    one_off = [i != int(np.flatnonzero(taxels == PAD["forearm_top"])[0]) for i in range(len(SKIN))]
    patch_off = (taxels != PAD["forearm_top"]).tolist()
    for valid, blind in ((one_off, frozenset()), (patch_off, frozenset({PAD["forearm_top"]}))):
        clock.advance(1.0)
        bridge.on_skin(sample(kpa, valid=valid), clock.now_ns())
        assert bridge.last_skin_ns == clock.now_ns()
        clock.advance(1.0)
        bridge.on_skin(sample(kpa, valid=valid), clock.now_ns())
        assert bridge.blind == blind
