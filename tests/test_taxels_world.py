"""The physics world's contacts read by the UR10e's taxel skin (services/worlds/taxels.py): a finger pressing
a pad of a taxel link presses the taxels under it with the world's own contact force; elsewhere, nothing. The
hosted world samples them at the taxel skin's rate and publishes them (world/skin's ``taxels``), the gateway's
physics source reads them in hPa, the door checks them."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile
from nwr.common.door import Door
from nwr.common.errors import ConfigError
from nwr.common.journal import Recording
from nwr.common.recordings import read_recording
from nwr.common.robot import ROBOTS_DIR, RobotModel, load_description
from nwr.common.taxels import contacts, finger_pressure, load_taxel_skin, nearest_taxel
from nwr.services.gateway.wiring import GatewayWiring
from nwr.services.worlds.hosted import HostedWorld, finger_force
from nwr.services.worlds.physics import PhysicsSettings, PhysicsWorld
from nwr.services.worlds.taxels import WorldTaxels

DESC = load_description(None)
MODEL = RobotModel(DESC)
SKIN = load_taxel_skin(ROBOTS_DIR / "ur10e" / "skin-taxels.toml", DESC)


@pytest.mark.parametrize(("pad", "force", "surface"), [
    ("upper_arm_top", 8.0, (-0.30, 0.065, 0.176)),
    ("upper_arm_bottom", 14.0, (-0.30, -0.065, 0.176)),
    ("forearm_top", 5.0, (-0.28, 0.06, 0.04)),
    ("forearm_bottom", 8.0, (-0.28, -0.06, 0.04)),
])
def test_a_finger_in_the_world_presses_the_taxels_under_its_pad(pad: str, force: float,
                                                                 surface: tuple[float, ...]) -> None:
    world = PhysicsWorld(DESC)
    world.press("finger", pad, force)
    world.run(DESC.home, 1.0)
    readings = WorldTaxels(world, SKIN, MODEL, 0.03).readings()
    # The world's normal force on the pad's cushion, all of it on the taxels, as one contact.
    pad_force = float(world.pad_force_n()[DESC.pad(pad).id])
    assert pad_force == pytest.approx(force, rel=0.1)
    (contact,) = contacts(SKIN, readings, 1e-9)
    assert contact.force_n == pytest.approx(pad_force, rel=1e-9)
    assert contact.patch == pad and contact.link == DESC.pad(pad).link
    # Under the pad's point, on the taxel surface, facing as the pad does.
    assert np.linalg.norm(contact.point - surface) < 0.01
    assert contact.normal @ DESC.pad(pad).normal > 0.99


def test_contacts_off_the_taxels_read_nothing() -> None:
    # A finger on the wrist (a link without taxels) and a palm on the elbow's lid (the upper arm's link, 0.1 m
    # past its last taxels): the world feels both, no taxel does.
    world = PhysicsWorld(DESC)
    world.press("finger", "wrist_1", 8.0)
    world.press("palm", "elbow_outer", 10.0, kind="palm")
    world.run(DESC.home, 1.0)
    felt = world.pad_force_n()
    assert felt[DESC.pad("wrist_1").id] > 5.0 and felt[DESC.pad("elbow_outer").id] > 5.0
    taxels = WorldTaxels(world, SKIN, MODEL, 0.03)
    links = {taxels.link_of(t.geom) for t in world.touches()}
    assert links == {None, "upper_arm_link"}
    assert not taxels.readings().any()


# ------------------------------------------------------------------------------ the hosted world's taxel skin

UPPER_ARM_TOP = DESC.pad("upper_arm_top").id


def touch_message(seq: int, pad: int, start_s: float, peak_hpa: float, duration_s: float) -> m.SkinTouch:
    return m.SkinTouch(seq=seq, stamp_ns=0, pad=pad, name=DESC.pads[pad].name, origin_ns=0, start_s=start_s,
                       duration_s=duration_s, peak_hpa=peak_hpa, shape="step", ramp_s=0.0)


def hosted_taxels(settings: PhysicsSettings, until_s: float = 0.8) -> tuple[HostedWorld, list[tuple[str, object]]]:
    """A hosted world on the taxel skin, a 16 hPa finger on upper_arm_top from 0.1 to 0.4 s (out of the world at
    0.7 s), run by a 500 Hz bridge to ``until_s``."""
    world = HostedWorld(DESC, settings, DESC.home)
    world.use_taxels(SKIN)
    q = np.asarray(DESC.home, dtype=float)
    out: list[tuple[str, object]] = []
    for now in range(2_000_000, round(until_s * 1e9) + 1, 2_000_000):
        if now == 100_000_000:
            world.touch(touch_message(0, UPPER_ARM_TOP, 0.1, 16.0, 0.3), now)
        out += world.advance(now, q, np.zeros_like(q))
    return world, out


def test_the_hosted_world_publishes_the_taxels_at_their_rate_with_the_worlds_force() -> None:
    world, out = hosted_taxels(PhysicsSettings())
    skin = [msg for key, msg in out if key == keys.WORLD_SKIN]
    assert all(isinstance(s, m.WorldSkin) for s in skin)
    # 1 kHz: one sample per 1 ms world step, in order, stamped on the bridge's clock at the step that took it
    # (world time 0 is the bridge's first cycle, at 2 ms).
    assert len(skin) == 798 and [s.seq for s in skin] == list(range(798))  # type: ignore[union-attr]
    assert [s.world_ns for s in skin] == [1_000_000 * (i + 1) for i in range(798)]  # type: ignore[union-attr]
    assert all(s.stamp_ns == s.world_ns + 2_000_000 for s in skin)  # type: ignore[union-attr]
    assert all(len(s.taxels) == 300 and not (s.absolute_hpa or s.change_hpa or s.force_n)  # type: ignore[union-attr]
               for s in skin)
    # While pressed: one contact on the upper arm's taxels with the world's force on the pad (the noise of
    # 0.008 kPa per taxel off by at most a few per cent); before and after: noise only, below any contact.
    threshold_kpa = 0.1  # the gateway's contact threshold, 1 hPa
    for s in skin:
        readings = np.asarray(s.taxels)  # type: ignore[union-attr]
        found = contacts(SKIN, readings, threshold_kpa)
        if 0.2e9 <= s.stamp_ns < 0.4e9:  # type: ignore[union-attr]
            assert len(found) == 1 and found[0].patch == "upper_arm_top", s.stamp_ns  # type: ignore[union-attr]
            assert found[0].force_n == pytest.approx(finger_force(16.0, PhysicsSettings()), rel=0.1)
        elif s.stamp_ns < 0.1e9 or s.stamp_ns > 0.55e9:  # type: ignore[union-attr]
            assert not found and np.abs(readings).max() < 0.05
    # The noise: the pads' skin_noise_hpa (0.08 hPa) in the taxels' kPa, over the untouched samples; under the
    # baseline it reads 0 (a half-normal: half of the readings, their mean sigma / sqrt(2 pi)).
    quiet = np.concatenate([np.asarray(s.taxels) for s in skin if s.stamp_ns < 0.1e9])  # type: ignore[union-attr]
    assert quiet.min() == 0.0 and np.mean(quiet == 0.0) == pytest.approx(0.5, abs=0.02)
    assert np.mean(quiet) == pytest.approx(0.008 / np.sqrt(2 * np.pi), rel=0.05)
    # Each sample, through the gateway, passes the door of skin/pressure (its absolute pressures are >= 0).
    profile = msgspec.convert({"robot": {"skin": "taxels"}, "gateway": {"source": "physics"},
                               "bridge": {"backend": "physics"}}, Profile)
    pressures: list[tuple[str, object]] = []
    arrival = ManualClock(0)
    gateway = GatewayWiring(profile, journal=Recording(arrival), out=lambda k, v: pressures.append((k, v)),
                            diag=lambda *a, **k: None)
    for sample in skin:
        arrival.t_ns = sample.stamp_ns + 2_000_000  # type: ignore[union-attr]
        gateway.on_world_skin(sample)  # type: ignore[arg-type]
    door = Door(DESC, SKIN)
    assert len(pressures) == len(skin) and not [door.refuse(p) for _, p in pressures if door.refuse(p)]
    # The contact figures keep the pads' rate (25 Hz): 40 ms apart while the finger is in the world.
    people = [msg for key, msg in out if key == keys.WORLD_CONTACTS]
    stamps = [c.stamp_ns for c in people]  # type: ignore[union-attr]
    assert people and all(b - a == 40_000_000 for a, b in zip(stamps, stamps[1:]))
    assert not world.fingers


def test_the_taxels_take_the_skins_rate_latency_and_sample_settings() -> None:
    _, out = hosted_taxels(PhysicsSettings(taxel_rate_hz=250.0, skin_latency_s=0.003, skin_noise_hpa=0.0,
                                           skin_sample="mean"), until_s=0.3)
    skin = [msg for key, msg in out if key == keys.WORLD_SKIN]
    assert [s.world_ns for s in skin] == [4_000_000 * (i + 1) for i in range(len(skin))]  # type: ignore[union-attr]
    assert all(s.stamp_ns == s.world_ns + 2_000_000 + 3_000_000 for s in skin)  # type: ignore[union-attr]
    assert len(skin) == 73  # world time ends at 0.298 s: the sample of 0.296 s is not delivered yet
    assert all(not any(s.taxels) for s in skin if s.stamp_ns <= 0.1e9)  # type: ignore[union-attr]
    # "mean": a sample is the mean of the readings of its 4 steps (those of 1 kHz "instant" samples).
    _, every = hosted_taxels(PhysicsSettings(skin_noise_hpa=0.0), until_s=0.3)
    by_world = {s.world_ns: np.asarray(s.taxels) for key, s in every if key == keys.WORLD_SKIN}  # type: ignore[union-attr]
    assert any(max(s.taxels) > 1.0 for s in skin)  # type: ignore[union-attr]
    for s in skin:
        steps = [by_world[s.world_ns - k * 1_000_000] for k in (3, 2, 1, 0)]  # type: ignore[union-attr]
        np.testing.assert_allclose(s.taxels, sum(steps) / 4, rtol=1e-12, atol=1e-15)  # type: ignore[union-attr]
    with pytest.raises(ConfigError, match="taxel_rate_hz = 2000 Hz is faster than the world's steps"):
        HostedWorld(DESC, PhysicsSettings(taxel_rate_hz=2000.0), DESC.home).use_taxels(SKIN)


def test_a_pad_sample_encodes_as_before_and_the_gateway_reads_taxels_in_hpa() -> None:
    pads = m.WorldSkin(seq=3, stamp_ns=5, world_ns=4, absolute_hpa=[1013.0] * 10, change_hpa=[0.0] * 10,
                       force_n=[0.0] * 10)
    assert b"taxels" not in msgspec.msgpack.encode(pads)  # the field is left off: main's bytes
    profile = msgspec.convert({"robot": {"skin": "taxels"}, "gateway": {"source": "physics"},
                               "bridge": {"backend": "physics"}}, Profile)
    out: list[tuple[str, object]] = []
    diags: list[tuple[str, ...]] = []
    clock = ManualClock(10**9)
    gateway = GatewayWiring(profile, journal=Recording(clock), out=lambda k, v: out.append((k, v)),
                            diag=lambda *a, **k: diags.append(a))
    kpa = finger_pressure(SKIN, "forearm_link", SKIN.points[nearest_taxel(SKIN, "forearm_link",
                                                                          DESC.pad("forearm_top").point)], 0.03, 5.0)
    for seq, readings in enumerate((np.zeros(len(SKIN)), kpa)):  # the first sample sets the baselines
        gateway.on_world_skin(m.WorldSkin(seq=seq, stamp_ns=clock.t_ns - 1_000_000, world_ns=1, absolute_hpa=[],
                                          change_hpa=[], force_n=[], taxels=readings.tolist()))
    (_, quiet), (key, pressure) = out
    assert isinstance(quiet, m.SkinPressure) and len(quiet.change_hpa) == 300 and not any(quiet.contact)
    assert key == keys.SKIN_PRESSURE and isinstance(pressure, m.SkinPressure)
    np.testing.assert_array_equal(pressure.absolute_hpa, kpa * 10.0)  # kPa x 10, as the scripted taxels
    assert sum(pressure.contact) == int((kpa * 10.0 > 1.0).sum()) and not pressure.touch_hpa
    # A pad sample on a taxel skin: dropped, said.
    gateway.on_world_skin(msgspec.structs.replace(pads, stamp_ns=clock.t_ns))
    assert len(out) == 2 and diags[-1][1] == "world_skin_pads" and "0 taxels" in diags[-1][2]
    # A sample that arrives later than gateway.max_sample_age_s (50 ms) after the world took it: dropped, counted,
    # said (a gateway behind a 1 kHz stream catches up instead of passing on old pressures as new); 50 ms is not.
    for age_ms in (51, 50):
        gateway.on_world_skin(m.WorldSkin(seq=9, stamp_ns=clock.t_ns - age_ms * 1_000_000, world_ns=1,
                                          absolute_hpa=[], change_hpa=[], force_n=[], taxels=kpa.tolist()))
    assert len(out) == 3 and gateway.late_samples == 1 and diags[-1][1] == "late_world_skin"
    assert "arrived 51 ms after the world took it" in diags[-1][2]
    # The door: a taxel sample passes a taxel skin's door, not a pad skin's; the count and the range are checked.
    door, pad_door = Door(DESC, SKIN), Door(DESC)
    sample = m.WorldSkin(seq=0, stamp_ns=1, world_ns=1, absolute_hpa=[], change_hpa=[], force_n=[],
                         taxels=kpa.tolist())
    assert door.refuse(sample) is None and door.refuse(pads) is None
    assert pad_door.refuse(sample).cause == "wrong pad count"  # type: ignore[union-attr]
    assert door.refuse(msgspec.structs.replace(sample, taxels=[0.0] * 299)).cause == "wrong pad count"  # type: ignore[union-attr]
    assert door.refuse(msgspec.structs.replace(sample, force_n=[0.0] * 10)).cause == "wrong pad count"  # type: ignore[union-attr]
    assert door.refuse(msgspec.structs.replace(sample, taxels=[300.0] * 300)).cause == "pressure out of range"  # type: ignore[union-attr]


SHORT_SCRIPT = """duration_s = 2.5

[[touch]]
pad = "upper_arm_top"
start_s = 0.5
duration_s = 0.5
peak_hpa = 16.0

[[touch]]
pad = "forearm_bottom"
start_s = 1.4
duration_s = 0.5
peak_hpa = 14.0
"""


@pytest.mark.slow
def test_a_lockstep_physics_demo_on_the_taxels_withdraws_from_each_finger_and_verifies(tmp_path, capsys) -> None:
    """``nwr demo --fast --world physics --skin taxels`` on two fingers one after the other: the world's 1 kHz
    taxel samples become 300-entry skin/pressure samples, a reflex per finger whose contact lies under it on its
    patch, the per-touch table complete, ``nwr verify`` bit for bit (~5 + 8 s)."""
    from nwr.services import cli
    from nwr.services.gateway.taxels import covering_taxel

    script, path = tmp_path / "short.toml", tmp_path / "taxels.mcap"
    script.write_text(SHORT_SCRIPT)
    assert cli.main(["demo", "--fast", "--world", "physics", "--skin", "taxels", "--script", str(script),
                     "--reflex", "cartesian", "-o", str(path)]) == 0
    assert "all 2 scripted touches as expected (2 reflexes" in capsys.readouterr().out
    records, _ = read_recording(path)
    world = [r.message for r in records if r.key == keys.WORLD_SKIN]
    pressure = [r.message for r in records if r.key == keys.SKIN_PRESSURE]
    assert len(pressure) == len(world) and all(len(w.taxels) == 300 for w in world)
    span_s = (world[-1].world_ns - world[0].world_ns) / 1e9
    assert len(world) == round(span_s * 1000) + 1  # every 1 ms step
    assert all(len(p.change_hpa) == 300 and p.source == "physics" for p in pressure)
    reflexes = {r.message.reflex.reflex_seq: r.message.reflex for r in records
                if isinstance(r.message, m.PlannerStatus) and r.message.reflex is not None}
    assert [reflex.contact.name for _, reflex in sorted(reflexes.items())] == ["upper_arm_top", "forearm_bottom"]
    for reflex in reflexes.values():
        pad = DESC.pad(reflex.contact.name)
        assert reflex.contact.link == pad.link and reflex.contact.force_n > 2.0  # PL 3 and up on the taxels
        under = SKIN.points[covering_taxel(SKIN, pad)]
        assert np.linalg.norm(np.asarray(reflex.contact.point) - under) < 0.02
    assert cli.main(["verify", str(path)]) == 0
    assert "4 of 4 service runs re-made their recorded outputs bit for bit" in capsys.readouterr().out


@pytest.mark.e2e
@pytest.mark.slow
def test_a_live_physics_demo_on_the_taxels_withdraws_and_verifies(tmp_path, pipeline) -> None:
    """``nwr demo --world physics --skin taxels`` through real processes (tests/data/physics.toml: a finger on
    forearm_top, 9 hPa held 1 s): every 1 ms world step's 300 readings published, what reaches the gateway
    passes every door (lockstep has none), a reflex, ``nwr verify`` bit for bit."""
    from pipeline import DATA

    from nwr.services.tools.recordings.verify import verify

    pipeline.configure("")
    output = tmp_path / "taxels.mcap"
    proc = pipeline.run("demo", "--world", "physics", "--skin", "taxels", "--script", str(DATA / "physics.toml"),
                        "--output", str(output), timeout_s=120)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log
    records, _ = read_recording(output)
    world = [r.message for r in records if r.key == keys.WORLD_SKIN]
    pressure = [r.message for r in records if r.key == keys.SKIN_PRESSURE]
    assert world and all(len(w.taxels) == 300 and not w.absolute_hpa for w in world)
    assert len(world) == (world[-1].world_ns - world[0].world_ns) // 1_000_000 + 1  # every world step, in order
    # The gateway's samples: one per world sample it took, in order (a loaded machine's gateway may skip some at
    # 1 kHz: 5 % in one run at load 5; how many is the benchmark's figure, not the test's).
    assert 0 < len(pressure) <= len(world) and all(len(p.absolute_hpa) == 300 for p in pressure)
    assert all(a.seq < b.seq for a, b in zip(pressure, pressure[1:]))
    refused = [r.message.message for r in records if r.key.startswith("diag/") and r.message.code.startswith("refused")]
    assert not refused, refused[:3]
    states = [r.message for r in records if r.key == keys.ROBOT_STATE]
    assert any(s.reflex_seq > 0 and s.accepted is not None for s in states), log
    reflex = next(r.message.reflex for r in records if isinstance(r.message, m.PlannerStatus)
                  and r.message.reflex is not None)
    assert reflex.contact.name == "forearm_top" and reflex.contact.link == "forearm_link"
    results = verify(output)
    lines = [r.format() for r in results]
    assert {r.service for r in results} == {"gateway", "gain", "bridge", "planner-cartesian"}, lines
    assert all(r.verdict == "identical" for r in results), lines


def test_nwr_demo_runs_the_taxels_in_the_physics_world_when_asked_and_refuses_what_they_cannot_feel(caplog) -> None:
    """``--skin taxels``: the scripted world by default, saying why; ``--world physics`` runs the physics world's
    taxels; a script touching pads the taxels do not cover, or a taxel rate above the world's steps, is refused
    before anything starts."""
    import logging

    from nwr.services.cli import build_parser
    from nwr.services.tools.demo import world_for

    parser = build_parser()
    profile = Profile()
    with caplog.at_level(logging.INFO, logger="nwr.services.tools.demo"):
        assert world_for(parser.parse_args(["demo", "--skin", "taxels", "--script", "two-fingers"]), profile) == \
            "scripted"
    assert "the taxel skin's default world" in caplog.text and profile.bridge.backend == "sim"
    profile = Profile()
    assert world_for(parser.parse_args(["demo", "--skin", "taxels", "--world", "physics", "--script",
                                        "two-fingers"]), profile) == "physics"
    assert (profile.robot.skin, profile.bridge.backend, profile.gateway.source) == ("taxels", "physics", "physics")
    with pytest.raises(ConfigError, match=r"touches pads \[.*'elbow_outer'.*\], which the taxel skin"):
        world_for(parser.parse_args(["demo", "--skin", "taxels", "--world", "physics", "--script", "demo"]),
                  Profile())
    slow = Profile()
    slow.bridge.plugins["physics"] = {"timestep_s": 0.002}
    with pytest.raises(ConfigError, match="taxel_rate_hz = 1000 Hz is faster than the world's steps"):
        world_for(parser.parse_args(["demo", "--skin", "taxels", "--world", "physics", "--script", "two-fingers"]),
                  slow)
