"""The taxel skin's core (common/taxels.py): the packaged UR10e taxel skin as data, every check of a skin
file, the simulated finger's pressure profile, and the contacts (clusters, centroids, normals) made of it."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from nwr.common.errors import ConfigError
from nwr.common.robot import ROBOTS_DIR, RobotModel, load_description
from nwr.common.taxels import contacts, finger_pressure, in_base, load_taxel_skin, nearest_taxel
from nwr.services.gain.core import continuous_gain, pain_level

DESC = load_description(None)
SKIN_PATH = ROBOTS_DIR / "ur10e" / "skin-taxels.toml"
SKIN = load_taxel_skin(SKIN_PATH, DESC)
TEXT = SKIN_PATH.read_text()


def test_the_packaged_skin_is_300_taxels_on_its_tubes() -> None:
    assert len(SKIN) == 300
    assert SKIN.patches == ("upper_arm_top", "upper_arm_bottom", "forearm_top", "forearm_bottom")
    assert np.bincount(SKIN.patch_index).tolist() == [105, 105, 45, 45]
    np.testing.assert_allclose(np.linalg.norm(SKIN.normals, axis=1), 1.0, atol=1e-12)
    # Every taxel on its tube's surface (distance from the axis = radius), facing away from the axis.
    for patch, (axis_z, radius) in enumerate([(0.176, 0.065), (0.176, 0.065), (0.04, 0.06), (0.04, 0.06)]):
        rows = SKIN.patch_index == patch
        radial = SKIN.points[rows] - [0.0, 0.0, axis_z]
        radial[:, 0] = 0.0
        np.testing.assert_allclose(np.linalg.norm(radial, axis=1), radius, atol=1e-12)
        np.testing.assert_allclose(radial / radius, SKIN.normals[rows], atol=1e-12)
        assert np.all(np.sign(SKIN.normals[rows, 1]) == (1 if patch % 2 == 0 else -1))
    # The areas tile each section: length x arc.
    arc = math.radians(150.0)
    expected = [0.375 * 0.065 * arc] * 2 + [0.27 * 0.06 * arc] * 2
    np.testing.assert_allclose(np.bincount(SKIN.patch_index, weights=SKIN.areas), expected, rtol=1e-12)
    assert not SKIN.points.flags.writeable and not SKIN.normals.flags.writeable


def test_neighbours_are_symmetric_within_one_link_and_connect_each_patch() -> None:
    graph = SKIN.neighbours
    assert np.array_equal(graph, graph.T) and not graph.diagonal().any()
    i, j = np.nonzero(graph)
    assert np.array_equal(SKIN.link_index[i], SKIN.link_index[j])
    assert np.all(np.linalg.norm(SKIN.points[i] - SKIN.points[j], axis=1) < SKIN.neighbour_m)
    # Interior taxels of the upper arm have their 8 grid neighbours, of the forearm their 4.
    degree = graph.sum(axis=1)
    assert degree[SKIN.patch_index < 2].max() == 8 and degree[SKIN.patch_index >= 2].max() == 4
    assert degree.min() >= 2


def test_an_airskin_pad_maps_to_the_patch_of_its_name() -> None:
    for name in SKIN.patches:
        pad = DESC.pad(name)
        taxel = nearest_taxel(SKIN, pad.link, pad.point)
        assert SKIN.patches[SKIN.patch_index[taxel]] == name
        assert SKIN.normals[taxel] @ pad.normal > 0.9
    with pytest.raises(ValueError, match="no taxel on link 'wrist_1_link'"):
        nearest_taxel(SKIN, "wrist_1_link", np.zeros(3))


# --------------------------------------------------------------------------- bad skin files


def _bad(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "skin-taxels.toml"
    path.write_text(text)
    return path


TAXEL = """
[[taxel]]
patch = "lid"
region = "shoulder"
link = "shoulder_link"
point = [0.0, 0.11, 0.0]
normal = [0.0, 1.0, 0.0]
area_m2 = 4e-4
"""


@pytest.mark.parametrize(("old", "new", "message"), [
    ('normal = [0.0, 1.0, 0.0]', 'normal = [0.0, 1.1, 0.0]', r"\[\[taxel\]\] #1: normal .* has length 1\.1"),
    ('point = [0.0, 0.11, 0.0]', 'point = [0.0, 110.0, 0.0]', r"taxel 300 \(patch 'lid'\).* m from link"),
    ('link = "shoulder_link"', 'link = "shoulder"', r"link = 'shoulder' is not a link of ur10e\.urdf"),
    ('region = "shoulder"', 'region = "hand"', r"region = 'hand'; expected one of"),
    ('area_m2 = 4e-4', 'area_m2 = 0', r"area_m2 = 0; expected a number > 0"),
    ('area_m2 = 4e-4', 'area_m2 = 4e-4\nid = 3', r"unknown key\(s\) id"),
    ('patch = "lid"', 'patch = "forearm_top"', r"patch 'forearm_top' is in region 'forearm' elsewhere"),
])
def test_a_bad_taxel_is_refused_by_name(tmp_path: Path, old: str, new: str, message: str) -> None:
    path = _bad(tmp_path, TEXT + TAXEL.replace(old, new))
    with pytest.raises(ConfigError, match=message) as caught:
        load_taxel_skin(path, DESC)
    assert str(path) in str(caught.value)


@pytest.mark.parametrize(("old", "new", "message"), [
    ('ref = [0.0, 1.0, 0.0]', 'ref = [0.0, 0.6, 0.6]', r"#1: ref .* has length 0\.84"),
    ('ref = [0.0, 1.0, 0.0]', 'ref = [0.6, 0.8, 0.0]', r"#1: ref .* is not perpendicular to axis"),
    ('pitch_m = 0.025', 'pitch_m = 0.00025', r"#1: \d+ taxels at pitch_m = 0\.00025; .* in mm"),
    ('axis_point = [0.0, 0.0, 0.176]', 'axis_point = [0.0, 0.0, 176.0]', r"taxel 0 \(patch 'upper_arm_top'\)"),
    ('along_m = [-0.12, -0.495]', 'along_m = [-0.12, -0.12]', r"#1: along_m .* non-zero length"),
    ('angles_deg = [-75.0, 75.0]', 'angles_deg = [0.0, 400.0]', r"#1: .* sweep in \(0, 360\]"),
    ('name = "upper_arm_bottom"', 'name = "upper_arm_top"', r"#2: patch name 'upper_arm_top' is used by more"),
    ('unit = "kPa"', 'unit = "psi"', r"unit = 'psi'; expected one of kPa, hPa, Pa"),
    ('[0.5, 2.0, 5.0, 10.0]', '[0.5, 5.0, 2.0, 10.0]', r"expected four rising forces"),
    ('neighbour_m = 0.036', 'neighbour_m = -1', r"neighbour_m = -1; expected a number > 0"),
])
def test_a_bad_patch_or_skin_table_is_refused_by_name(tmp_path: Path, old: str, new: str, message: str) -> None:
    assert TEXT.count(old) >= 1
    with pytest.raises(ConfigError, match=message):
        load_taxel_skin(_bad(tmp_path, TEXT.replace(old, new, 1)), DESC)


def test_a_taxel_entered_twice_or_no_taxel_at_all_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"taxels 300 \(patch 'lid'\) and 301 \(patch 'lid'\) are at one point"):
        load_taxel_skin(_bad(tmp_path, TEXT + TAXEL + TAXEL), DESC)
    head = TEXT[:TEXT.index("[[patch]]")]
    with pytest.raises(ConfigError, match=r"expected one or more \[\[patch\]\] or \[\[taxel\]\] tables"):
        load_taxel_skin(_bad(tmp_path, head), DESC)


def test_explicit_taxels_extend_the_patches(tmp_path: Path) -> None:
    # The packaged text plus one lid taxel on the shoulder: a third link, its own patch, no neighbours.
    skin = load_taxel_skin(_bad(tmp_path, TEXT + TAXEL), DESC)
    assert len(skin) == 301 and skin.links[-1] == "shoulder_link" and skin.patches[-1] == "lid"
    assert skin.patch_regions[-1] == "shoulder" and skin.areas[-1] == 4e-4
    assert not skin.neighbours[300].any()


# --------------------------------------------------------------------------- the simulated finger


@pytest.mark.parametrize("taxel", [0, 52, 104, 160, 250, 299])
@pytest.mark.parametrize("radius", [0.015, 0.03, 0.05])
def test_the_finger_presses_its_force_within_its_radius(taxel: int, radius: float) -> None:
    link = SKIN.links[SKIN.link_index[taxel]]
    centre = SKIN.points[taxel]
    pressure = finger_pressure(SKIN, link, centre, radius, 4.0)
    assert pressure @ SKIN.areas * 1e3 == pytest.approx(4.0, rel=1e-12)  # kPa x m^2 -> N
    distance = np.linalg.norm(SKIN.points - centre, axis=1)
    on_link = SKIN.link_index == SKIN.link_index[taxel]
    assert np.all(pressure[(distance >= radius) | ~on_link] == 0.0)
    assert np.all(pressure[(distance < radius) & on_link] > 0.0)
    assert int(np.argmax(pressure)) == taxel
    # The elliptic profile: p / p_peak = sqrt(1 - (d / R)^2) (to 1e-7 near the rim, where sqrt magnifies rounding).
    touched = pressure > 0
    np.testing.assert_allclose(pressure[touched] / pressure[taxel],
                               np.sqrt(1.0 - (distance[touched] / radius) ** 2), rtol=1e-12, atol=1e-7)


def test_a_finger_between_taxels_or_off_the_skin_reads_nothing() -> None:
    beside = SKIN.points[0] + 0.3 * SKIN.normals[0]
    assert not finger_pressure(SKIN, "upper_arm_link", beside, 0.02, 5.0).any()
    assert not finger_pressure(SKIN, "upper_arm_link", SKIN.points[0], 0.02, 0.0).any()
    for radius, force in [(0.0, 1.0), (math.nan, 1.0), (0.02, -1.0), (0.02, math.inf)]:
        with pytest.raises(ValueError, match="expected > 0 and >= 0"):
            finger_pressure(SKIN, "upper_arm_link", SKIN.points[0], radius, force)


# --------------------------------------------------------------------------- contacts


def test_one_finger_makes_one_contact_at_its_centre() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        taxel = int(rng.integers(len(SKIN)))
        link = SKIN.links[SKIN.link_index[taxel]]
        # A finger centre anywhere on the skin's surface near the taxel (a quarter pitch off).
        centre = SKIN.points[taxel] + rng.uniform(-0.006, 0.006, 3) * [1, 0, 0]
        pressure = finger_pressure(SKIN, link, centre, 0.03, 3.0)
        found = contacts(SKIN, pressure, 0.05)
        assert len(found) == 1
        contact = found[0]
        assert contact.link == link and contact.force_n <= 3.0 + 1e-9
        assert contact.patch == SKIN.patches[SKIN.patch_index[taxel]]
        # The centroid is within a pitch of the finger's centre (the grid's discretisation) and the normal
        # within 20 degrees of the skin's there.
        assert np.linalg.norm(contact.point - centre) < 0.025
        assert contact.normal @ SKIN.normals[taxel] > math.cos(math.radians(20))
        assert np.linalg.norm(contact.normal) == pytest.approx(1.0)


def test_the_centroid_and_normal_are_the_pressure_weighted_means() -> None:
    pressure = np.zeros(len(SKIN))
    pressure[[0, 1]] = [1.0, 3.0]  # neighbours around the tube
    (contact,) = contacts(SKIN, pressure, 0.5)
    np.testing.assert_allclose(contact.point, (SKIN.points[0] + 3 * SKIN.points[1]) / 4, atol=1e-15)
    normal = SKIN.normals[0] + 3 * SKIN.normals[1]
    np.testing.assert_allclose(contact.normal, normal / np.linalg.norm(normal), atol=1e-15)
    assert contact.taxels == (0, 1) and contact.peak == 3.0 and contact.peak_taxel == 1
    assert contact.force_n == pytest.approx((SKIN.areas[0] + 3 * SKIN.areas[1]) * 1e3)


def test_several_fingers_make_several_contacts_strongest_first() -> None:
    far_a, far_b, other_link = 7, 95, 250
    pressure = (finger_pressure(SKIN, "upper_arm_link", SKIN.points[far_a], 0.03, 2.0)
                + finger_pressure(SKIN, "upper_arm_link", SKIN.points[far_b], 0.03, 6.0)
                + finger_pressure(SKIN, "forearm_link", SKIN.points[other_link], 0.03, 4.0))
    found = contacts(SKIN, pressure, 1e-9)
    assert [c.peak_taxel for c in found] == [far_b, other_link, far_a]
    assert [round(c.force_n, 9) for c in found] == [6.0, 4.0, 2.0]
    assert sorted(t for c in found for t in c.taxels) == np.flatnonzero(pressure > 0).tolist()
    # A threshold that leaves out the faintest taxels leaves their force out.
    assert sum(c.force_n for c in contacts(SKIN, pressure, 0.5)) < 12.0


def test_unreadable_or_faint_taxels_make_no_contact() -> None:
    pressure = finger_pressure(SKIN, "forearm_link", SKIN.points[260], 0.045, 4.0)
    assert contacts(SKIN, pressure, pressure.max() * 1.01) == []
    garbled = pressure.copy()
    garbled[260] = math.nan
    garbled[10] = math.inf
    (contact,) = contacts(SKIN, garbled, 0.05)
    assert 260 not in contact.taxels and 10 not in contact.taxels and contact.link == "forearm_link"
    with pytest.raises(ValueError, match=re.escape("shape (299,); the skin has 300 taxels")):
        contacts(SKIN, pressure[:-1], 0.05)
    with pytest.raises(ValueError, match="expected > 0"):
        contacts(SKIN, pressure, 0.0)


def test_a_contact_in_the_base_frame_is_its_link_frame_posed() -> None:
    model = RobotModel(DESC)
    q = DESC.home + np.array([0.3, -0.4, 0.5, 0.1, -0.2, 0.3])
    pressure = np.zeros(len(SKIN))
    pressure[200] = 5.0  # forearm_top's taxel alone
    (contact,) = contacts(SKIN, pressure, 1.0)
    pose = model.frame_pose(q, contact.link)
    point, normal = in_base(contact, pose)
    np.testing.assert_allclose(point, pose[:3, :3] @ SKIN.points[200] + pose[:3, 3], atol=1e-15)
    assert np.linalg.norm(normal) == pytest.approx(1.0)
    # Moving the point along its base-frame normal moves it away from its link's axis: outward.
    axis_point = pose[:3, :3] @ np.array([SKIN.points[200][0], 0.0, 0.04]) + pose[:3, 3]
    assert np.linalg.norm(point + 0.01 * normal - axis_point) > np.linalg.norm(point - axis_point)


def test_a_contacts_levels_come_from_its_force_and_the_skins_thresholds() -> None:
    thresholds = SKIN.level_thresholds_n
    levels, gains = [], []
    for force in [0.2, 1.0, 3.0, 7.0, 12.0, *SKIN.force_thresholds_n]:
        pressure = finger_pressure(SKIN, "upper_arm_link", SKIN.points[52], 0.03, force)
        (contact,) = contacts(SKIN, pressure, 1e-6)
        levels.append(pain_level(contact.force_n, thresholds))
        gains.append(continuous_gain(contact.force_n, thresholds))
    # A finger pressing exactly a threshold's force reaches its level, whatever the sum's rounding.
    assert levels == [1, 2, 3, 4, 4, 2, 3, 4, 4]
    assert gains[:2] == [0.0, 0.0] and 0.0 < gains[2] < 0.35 < gains[3] < 1.0 and gains[4] == gains[8] == 1.0


def test_the_components_are_scipys_on_random_graphs_and_a_long_chain() -> None:
    from scipy.sparse.csgraph import connected_components

    from nwr.common.taxels import _components

    rng = np.random.default_rng(7)
    graphs = []
    for size, density in [(1, 0.0), (2, 1.0), (5, 0.3), (40, 0.05), (300, 0.004), (300, 0.02)]:
        upper = np.triu(rng.random((size, size)) < density, 1)
        graphs.append(upper | upper.T)
    chain = np.zeros((300, 300), dtype=bool)
    order = rng.permutation(300)
    chain[order[:-1], order[1:]] = True  # one path through every node, in a random order
    graphs.append(chain | chain.T)
    for graph in graphs:
        count, expected = connected_components(graph, directed=False)
        labels = _components(graph)
        assert labels.max() + 1 == count
        assert np.array_equal(labels, expected)


# --------------------------------------------------------------------------- the scripted taxel skin


def test_a_pads_change_maps_to_the_force_of_its_pain_level() -> None:
    from nwr.services.gateway.taxels import force_of

    pads_t, force_t = (2.0, 6.0, 12.0, 20.0), SKIN.force_thresholds_n
    assert [force_of(p, pads_t, force_t) for p in (0.0, 1.0, 2.0, 4.0, 6.0, 12.0, 20.0)] == pytest.approx(
        [0.0, 0.25, 0.5, 1.25, 2.0, 5.0, 10.0])
    assert force_of(30.0, pads_t, force_t) == pytest.approx(10.0 + 10.0 * 5.0 / 8.0)  # the last slope on
    rng = np.random.default_rng(11)
    for change in rng.uniform(0.0, 40.0, 500):
        assert pain_level(force_of(change, pads_t, force_t), force_t) == pain_level(change, pads_t)


def test_every_packaged_script_presses_its_pads_levels_on_the_taxels_it_covers() -> None:
    from nwr.common.launch import TouchScript, load_script
    from nwr.services.gateway.taxels import ScriptedTaxels, covering_taxel

    pads_t = (2.0, 6.0, 12.0, 20.0)
    covered = {pad.name for pad in DESC.pads if covering_taxel(SKIN, pad) is not None}
    assert covered == {"upper_arm_top", "upper_arm_bottom", "forearm_top", "forearm_bottom"}
    checked = 0
    for name in ["contacts", "demo", "slow-press", "survey", "two-fingers"]:
        script = load_script(name)
        mine = TouchScript(duration_s=script.duration_s, touch=[t for t in script.touch if t.pad in covered])
        source = ScriptedTaxels(SKIN, DESC.pads, mine, pads_t)
        for index, touch in enumerate(mine.touch):
            peak_t = touch.start_s + touch.duration_s / 2 + (touch.ramp_s if touch.shape == "ramp" else 0.0)
            found = contacts(SKIN, source.sample(peak_t), 1e-9)
            ours = [c for c in found if source.taxels[index] in c.taxels]
            assert len(ours) == 1, (name, index)
            # Alone on its patch, the contact is the whole finger; with another touch under way nearby, more.
            assert ours[0].force_n >= source.forces[index] * (1 - 1e-12)
            assert ours[0].patch == touch.pad
            if len(found) == 1 and ours[0].force_n == pytest.approx(source.forces[index]):
                assert pain_level(ours[0].force_n, SKIN.level_thresholds_n) == pain_level(touch.peak_hpa, pads_t)
                checked += 1
            # Before and after the touch, nothing of it.
            end = touch.start_s + touch.duration_s + (2 * touch.ramp_s if touch.shape == "ramp" else 0.0)
            assert source.force(index, touch.start_s - 1e-6) == 0.0 == source.force(index, end + 1e-6)
    assert checked > 20


def test_a_script_touching_an_uncovered_pad_is_refused_by_name() -> None:
    from nwr.common.launch import load_script
    from nwr.services.gateway.taxels import ScriptedTaxels

    with pytest.raises(ConfigError, match=r"touches pads \['elbow_outer', 'shoulder_outer', 'wrist_1', 'wrist_3'\]"):
        ScriptedTaxels(SKIN, DESC.pads, load_script("demo"), (2.0, 6.0, 12.0, 20.0))


def test_a_ramp_touch_follows_its_profile_on_the_taxels() -> None:
    from nwr.common.launch import Touch, TouchScript
    from nwr.services.gateway.taxels import ScriptedTaxels

    script = TouchScript(duration_s=3.0, touch=[
        Touch(pad="forearm_top", start_s=1.0, duration_s=0.5, peak_hpa=16.0, shape="ramp", ramp_s=0.2)])
    source = ScriptedTaxels(SKIN, DESC.pads, script, (2.0, 6.0, 12.0, 20.0))
    assert source.forces == [pytest.approx(7.5)]
    totals = [source.sample(t) @ SKIN.areas * 1e3 for t in (0.99, 1.0, 1.1, 1.2, 1.45, 1.7, 1.8, 1.9)]
    assert totals == pytest.approx([0.0, 0.0, 3.75, 7.5, 7.5, 7.5, 3.75, 0.0])


def test_contacts_partition_any_sample_into_its_components() -> None:
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(5)
    for _ in range(200):
        pressure = rng.exponential(0.3, len(SKIN)) * (rng.random(len(SKIN)) < rng.uniform(0.0, 0.6))
        garbage = rng.random(len(SKIN)) < 0.02
        pressure[garbage] = rng.choice([math.nan, math.inf, -math.inf, -5.0], int(garbage.sum()))
        threshold = float(rng.uniform(0.01, 0.5))
        found = contacts(SKIN, pressure, threshold)
        pressing = np.flatnonzero(np.isfinite(pressure) & (pressure >= threshold))
        # Every pressing taxel in exactly one contact, and the contacts are the graph's components.
        assert sorted(t for c in found for t in c.taxels) == pressing.tolist()
        count, labels = connected_components(SKIN.neighbours[np.ix_(pressing, pressing)], directed=False)
        assert len(found) == count
        for contact in found:
            assert len(set(labels[np.searchsorted(pressing, contact.taxels)])) == 1
            assert len({SKIN.link_index[t] for t in contact.taxels}) == 1
            w = pressure[list(contact.taxels)]
            assert contact.force_n == pytest.approx(float(w @ SKIN.areas[list(contact.taxels)]) * 1e3)
            assert contact.peak == w.max() and np.linalg.norm(contact.normal) == pytest.approx(1.0)
        assert [c.force_n for c in found] == sorted((c.force_n for c in found), reverse=True)
