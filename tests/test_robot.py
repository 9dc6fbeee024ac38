"""Robot description and kinematics (nwr.common.robot): fast, no network."""

from __future__ import annotations

import math
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from nwr.common.errors import ConfigError
from nwr.common.robot import REGIONS, RobotDescription, RobotModel, load_description

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "common" / "robots" / "ur10e"

# UR10e DH table (Universal Robots), standard DH: Rz(theta) Tz(d) Tx(a) Rx(alpha).
DH_D = (0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655)
DH_A = (0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)

# base_link is the DH base turned by pi about z.
BASE_LINK_FROM_DH = np.diag([-1.0, -1.0, 1.0, 1.0])

DESC = load_description()
MODEL = RobotModel(DESC)


def dh_tool(q: np.ndarray) -> np.ndarray:
    """tool0 in the DH base frame, as an independent product of DH matrices."""
    transform = np.eye(4)
    for theta, d, a, alpha in zip(q, DH_D, DH_A, DH_ALPHA):
        c, s = math.cos(theta), math.sin(theta)
        rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
        tz = np.eye(4)
        tz[2, 3] = d
        tx = np.eye(4)
        tx[0, 3] = a
        ca, sa = math.cos(alpha), math.sin(alpha)
        rx = np.array([[1, 0, 0, 0], [0, ca, -sa, 0], [0, sa, ca, 0], [0, 0, 0, 1]])
        transform = transform @ rz @ tz @ tx @ rx
    return transform


def segment_distance(point: np.ndarray, polyline: np.ndarray) -> float:
    """Distance from a point to a polyline (the kinematic chain's skeleton)."""
    best = math.inf
    for start, end in zip(polyline[:-1], polyline[1:]):
        direction = end - start
        length2 = float(direction @ direction)
        t = 0.0 if length2 == 0.0 else float(np.clip((point - start) @ direction / length2, 0.0, 1.0))
        best = min(best, float(np.linalg.norm(point - (start + t * direction))))
    return best


def working_poses() -> list[np.ndarray]:
    """q = 0, home, and random poses with a fixed seed in two working families:
    around home and around the arm pointing straight up.  The boxes exclude a
    folded elbow (|q3| > ~2.2 rad) and a wrist turned back onto the forearm, where
    pads legitimately face another part of the arm."""
    rng = np.random.default_rng(20240611)
    upright = np.array([0.0, -math.pi / 2, 0.0, -math.pi / 2, 0.0, 0.0])
    around_home = np.array([math.pi, 1.0, 0.35, 1.2, 1.2, math.pi])
    around_upright = np.array([math.pi, math.pi / 2, 2.0, 1.2, 1.2, math.pi])
    poses = [np.zeros(6), np.array(DESC.home)]
    poses += [DESC.home + rng.uniform(-around_home, around_home) for _ in range(10)]
    poses += [upright + rng.uniform(-around_upright, around_upright) for _ in range(10)]
    return poses


def description_with_base(tmp_path: Path, base_frame: str) -> RobotDescription:
    copy = copy_description(tmp_path)
    edit(copy / "robot.toml", 'base_frame = "base_link"', f'base_frame = "{base_frame}"')
    return load_description(copy / "robot.toml")


def copy_description(tmp_path: Path) -> Path:
    target = tmp_path / "ur10e"
    shutil.copytree(PACKAGE_DIR, target)
    return target


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert text.count(old) == 1, f"{old!r} must occur exactly once in {path}"
    path.write_text(text.replace(old, new))


# ---------------------------------------------------------------- forward kinematics


def test_tool0_at_zero_matches_hand_computed_dh() -> None:
    # (a2 + a3, -(d4 + d6), d1 - d5) in the DH base frame.
    in_base = np.linalg.inv(MODEL.frame_pose(np.zeros(6), "base")) @ MODEL.frame_pose(np.zeros(6), "tool0")
    np.testing.assert_allclose(in_base[:3, 3], [-1.18425, -0.2907, 0.06085], atol=1e-12)
    np.testing.assert_allclose(MODEL.tool_position(np.zeros(6)), [1.18425, 0.2907, 0.06085], atol=1e-12)
    # base_link is the universe frame: identity pose.
    np.testing.assert_allclose(MODEL.frame_pose(np.zeros(6), "base_link"), np.eye(4), atol=1e-15)
    # tool0 is DH frame 6: z out of the flange, along -y of the DH base at q = 0.
    np.testing.assert_allclose(in_base[:3, 2], [0.0, -1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize(
    "q",
    [
        np.array([0.3, -1.1, 1.4, -0.7, 0.9, -2.0]),
        np.array([-2.5, -0.4, -2.1, 1.9, -1.3, 0.6]),
        np.array([4.0, -3.5, 2.9, -5.0, 5.5, -6.0]),
        np.array([0.0, -1.15, 1.85, -2.27, -1.57, 0.0]),
    ],
)
def test_tool_pose_matches_independent_dh_product(q: np.ndarray) -> None:
    expected_in_dh_base = dh_tool(q)
    pose = MODEL.frame_pose(q, "tool0")  # base_frame = base_link
    np.testing.assert_allclose(pose, BASE_LINK_FROM_DH @ expected_in_dh_base, atol=1e-12)
    np.testing.assert_allclose(MODEL.tool_position(q), (BASE_LINK_FROM_DH @ expected_in_dh_base)[:3, 3], atol=1e-12)
    in_base = np.linalg.inv(MODEL.frame_pose(q, "base")) @ pose
    np.testing.assert_allclose(in_base, expected_in_dh_base, atol=1e-12)
    # tool0 and the ROS flange frame share their origin; flange x = tool0 z.
    flange = MODEL.frame_pose(q, "flange")
    np.testing.assert_allclose(flange[:3, 3], pose[:3, 3], atol=1e-12)
    np.testing.assert_allclose(flange[:3, 0], pose[:3, 2], atol=1e-12)


def test_base_frame_option_expresses_everything_in_the_dh_base(tmp_path: Path) -> None:
    model = RobotModel(description_with_base(tmp_path, "base"))
    q = np.array([0.3, -1.1, 1.4, -0.7, 0.9, -2.0])
    np.testing.assert_allclose(model.tool_position(np.zeros(6)), [-1.18425, -0.2907, 0.06085], atol=1e-12)
    np.testing.assert_allclose(model.frame_pose(q, "tool0"), dh_tool(q), atol=1e-12)
    rotate = BASE_LINK_FROM_DH[:3, :3]  # its own inverse
    np.testing.assert_allclose(model.pad_points(q), MODEL.pad_points(q) @ rotate.T, atol=1e-12)
    np.testing.assert_allclose(model.pad_normals(q), MODEL.pad_normals(q) @ rotate.T, atol=1e-12)
    np.testing.assert_allclose(model.joint_positions(q), MODEL.joint_positions(q) @ rotate.T, atol=1e-12)
    for pad in range(len(DESC.pads)):
        jacobian = MODEL.pad_jacobian(q, pad)
        np.testing.assert_allclose(model.pad_jacobian(q, pad)[:3], rotate @ jacobian[:3], atol=1e-12)
        np.testing.assert_allclose(model.pad_jacobian(q, pad)[3:], rotate @ jacobian[3:], atol=1e-12)


def test_joint_positions_are_the_chain_skeleton() -> None:
    q = np.array(DESC.home)
    points = MODEL.joint_positions(q)
    assert points.shape == (MODEL.nq + 1, 3)
    np.testing.assert_allclose(points[0], [0.0, 0.0, 0.1807], atol=1e-12)  # shoulder pan/lift origin
    np.testing.assert_allclose(points[-1], MODEL.tool_position(q), atol=1e-12)
    for row, joint in enumerate(DESC.joints):
        np.testing.assert_allclose(points[row], MODEL.frame_pose(q, joint)[:3, 3], atol=1e-12)


def test_cache_follows_in_place_changes_of_q() -> None:
    model = RobotModel(DESC)
    q = np.zeros(6)
    first = model.tool_position(q)
    q[0] = math.pi / 2  # the same array object, modified in place
    second = model.tool_position(q)
    np.testing.assert_allclose(second, [-0.2907, 1.18425, 0.06085], atol=1e-12)
    assert not np.allclose(first, second)
    first[:] = 0.0  # returned arrays are the caller's to modify
    np.testing.assert_allclose(model.tool_position(q), second, atol=0.0)
    model.fk([0.0] * 6)  # lists are accepted too
    np.testing.assert_allclose(model.tool_position([0.0] * 6), [1.18425, 0.2907, 0.06085], atol=1e-12)


def test_bad_q_is_rejected() -> None:
    with pytest.raises(ValueError, match=r"expected \(6,\)"):
        MODEL.tool_position(np.zeros(5))
    with pytest.raises(ValueError, match="non-finite"):
        MODEL.pad_point(np.array([0, 0, np.nan, 0, 0, 0]), 0)
    with pytest.raises(IndexError, match="0..9"):
        MODEL.pad_point(np.zeros(6), 10)
    with pytest.raises(ConfigError, match="tool0"):
        MODEL.frame_pose(np.zeros(6), "tool1")


def test_bad_q_is_rejected_at_a_cached_pose_too() -> None:
    model = RobotModel(DESC)
    q = np.zeros(6)
    model.speed_jacobians(q)  # the pose cached: an equal q skips the checks, any other is checked in full
    for bad in (np.array([0, 0, np.nan, 0, 0, 0]), np.array([np.inf, 0, 0, 0, 0, 0]), np.full(6, np.nan)):
        with pytest.raises(ValueError, match="non-finite"):
            model.speed_jacobians(bad)
    for shape in ((5,), (6, 1), (1, 6)):
        with pytest.raises(ValueError, match=r"expected \(6,\)"):
            model.com_jacobians(np.zeros(shape))
    assert model.speed_jacobians([0.0] * 6) is model.speed_jacobians(-q)  # -0.0 == 0.0: the same pose, as before


# ---------------------------------------------------------------- description


def test_limits_come_from_the_urdf() -> None:
    two_pi = 2 * math.pi
    np.testing.assert_allclose(DESC.q_min, [-two_pi, -two_pi, -math.pi, -two_pi, -two_pi, -two_pi])
    np.testing.assert_allclose(DESC.q_max, [two_pi, two_pi, math.pi, two_pi, two_pi, two_pi])
    np.testing.assert_allclose(DESC.v_max, [2.094, 2.094, 3.142, 3.142, 3.142, 3.142], atol=1e-3)
    model = pin.buildModelFromUrdf(str(DESC.urdf_path))
    np.testing.assert_allclose(model.effortLimit, [330, 330, 150, 56, 56, 56])
    masses = [model.inertias[i].mass for i in range(1, model.njoints)]
    np.testing.assert_allclose(masses, [7.369, 13.051, 3.989, 2.1, 1.98, 0.615])


def test_packaged_description() -> None:
    assert DESC.name == "ur10e"
    assert DESC.urdf_path == (PACKAGE_DIR / "ur10e.urdf").resolve()
    assert DESC.skin_path == (PACKAGE_DIR / "skin.toml").resolve()
    assert (DESC.base_frame, DESC.tool_frame) == ("base_link", "tool0")
    assert DESC.joints == (
        "shoulder_pan_joint",
        "shoulder_lift_joint",
        "elbow_joint",
        "wrist_1_joint",
        "wrist_2_joint",
        "wrist_3_joint",
    )
    for array in (DESC.q_min, DESC.q_max, DESC.v_max, DESC.a_max, DESC.j_max, DESC.home):
        assert array.shape == (6,)
        assert not array.flags.writeable
    assert np.all(DESC.a_max > 0) and np.all(DESC.j_max > 0)
    assert np.all((DESC.q_min <= DESC.home) & (DESC.home <= DESC.q_max))
    assert load_description(PACKAGE_DIR / "robot.toml").home.tolist() == DESC.home.tolist()


def test_home_is_a_comfortable_pose() -> None:
    tool = MODEL.tool_position(DESC.home)
    assert 0.7 <= tool[0] <= 0.9  # in front of the robot (+x of base_link)
    assert 0.1 <= tool[2] <= 0.4  # a little above the mounting plane
    elbow = MODEL.joint_positions(DESC.home)[2]
    assert elbow[2] > 0.5  # elbow up
    assert 0.3 < abs(DESC.home[2]) < math.pi - 0.3  # elbow bent, not singular
    assert 0.3 < abs(DESC.home[4]) < math.pi - 0.3  # wrist 2 away from the wrist singularity
    wrist_centre = MODEL.joint_positions(DESC.home)[4]
    assert math.hypot(wrist_centre[0], wrist_centre[1]) > 0.3  # far from the shoulder singularity


def test_ten_pads_in_five_regions() -> None:
    assert len(DESC.pads) == 10
    assert [pad.id for pad in DESC.pads] == list(range(10))
    assert Counter(pad.region for pad in DESC.pads) == {
        "shoulder": 2,
        "upper_arm": 2,
        "elbow": 1,
        "forearm": 2,
        "wrist": 3,
    }
    assert set(REGIONS) == {pad.region for pad in DESC.pads}
    assert len({pad.name for pad in DESC.pads}) == 10
    assert {pad.link for pad in DESC.pads if pad.region == "wrist"} == {"wrist_1_link", "wrist_2_link", "wrist_3_link"}
    for pad in DESC.pads:
        assert pad.point.shape == (3,) and pad.normal.shape == (3,)
        assert DESC.pad(pad.id) is pad
        assert DESC.pad(pad.name) is pad


def test_unknown_pad_lists_the_choices() -> None:
    with pytest.raises(ConfigError, match="upper_arm_top") as error:
        DESC.pad("knee")
    assert "0..9" in str(error.value) and "'knee'" in str(error.value)
    with pytest.raises(ConfigError, match="0..9"):
        DESC.pad(10)
    with pytest.raises(ConfigError):
        DESC.pad(True)  # type: ignore[arg-type]


# ---------------------------------------------------------------- pads


def test_pad_frames_sit_on_their_links() -> None:
    q = np.array([0.3, -1.1, 1.4, -0.7, 0.9, -2.0])
    for pad in DESC.pads:
        link = MODEL.frame_pose(q, pad.link)
        np.testing.assert_allclose(MODEL.pad_point(q, pad.id), link[:3, :3] @ pad.point + link[:3, 3], atol=1e-12)
        np.testing.assert_allclose(MODEL.pad_normal(q, pad.id), link[:3, :3] @ pad.normal, atol=1e-12)
        frame = MODEL.frame_pose(q, f"pad_{pad.name}")
        np.testing.assert_allclose(frame[:3, 2], MODEL.pad_normal(q, pad.id), atol=1e-12)
        np.testing.assert_allclose(frame[:3, :3].T @ frame[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(frame[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(MODEL.pad_points(q), [MODEL.pad_point(q, i) for i in range(10)], atol=0.0)
    np.testing.assert_allclose(MODEL.pad_normals(q), [MODEL.pad_normal(q, i) for i in range(10)], atol=0.0)


@pytest.mark.parametrize("q", working_poses(), ids=lambda q: np.array2string(q, precision=2))
def test_pad_normals_are_unit_and_point_away_from_the_chain(q: np.ndarray) -> None:
    skeleton = MODEL.joint_positions(q)
    points, normals = MODEL.pad_points(q), MODEL.pad_normals(q)
    for pad in DESC.pads:
        assert np.linalg.norm(normals[pad.id]) == pytest.approx(1.0, abs=1e-12)
        distance = segment_distance(points[pad.id], skeleton)
        assert distance >= 0.04, f"pad {pad.name} is only {distance:.3f} m from the chain"
        moved = segment_distance(points[pad.id] + 0.005 * normals[pad.id], skeleton)
        assert moved > distance, f"pad {pad.name}'s normal points towards the chain"


@pytest.mark.parametrize("q", working_poses()[:4], ids=lambda q: np.array2string(q, precision=2))
def test_pad_jacobian_matches_finite_differences(q: np.ndarray) -> None:
    step = 1e-6
    for pad in DESC.pads:
        jacobian = MODEL.pad_jacobian(q, pad.id)
        assert jacobian.shape == (6, MODEL.nq)
        rotation = MODEL.frame_pose(q, f"pad_{pad.name}")[:3, :3]
        for joint in range(MODEL.nq):
            dq = np.zeros(MODEL.nq)
            dq[joint] = step
            linear = (MODEL.pad_point(q + dq, pad.id) - MODEL.pad_point(q - dq, pad.id)) / (2 * step)
            np.testing.assert_allclose(jacobian[:3, joint], linear, atol=1e-7)
            # Angular velocity from the orientation change: R(q + dq) R(q)^T = exp([w dq]x).
            turned = MODEL.frame_pose(q + dq, f"pad_{pad.name}")[:3, :3]
            angular = pin.log3(turned @ rotation.T) / step
            np.testing.assert_allclose(jacobian[3:, joint], angular, atol=1e-5)
        # The cached forward kinematics still describe q after the +-dq probes.
        np.testing.assert_allclose(MODEL.pad_jacobian(q, pad.id), jacobian, atol=0.0)


def test_pad_jacobian_after_other_queries_is_fresh() -> None:
    model = RobotModel(DESC)
    q1, q2 = np.zeros(6), np.array(DESC.home)
    reference = RobotModel(DESC).pad_jacobian(q2, 3)
    model.pad_jacobian(q1, 3)
    model.pad_point(q2, 3)  # fk for q2 without Jacobians
    np.testing.assert_allclose(model.pad_jacobian(q2, 3), reference, atol=0.0)


# ---------------------------------------------------------------- validation errors


@pytest.mark.parametrize(
    ("file", "old", "new", "expected"),
    [
        pytest.param(
            "skin.toml",
            'region = "elbow"',
            'region = "knee"',
            ["skin.toml", "elbow_outer", "'knee'", "upper_arm"],
            id="unknown-region",
        ),
        pytest.param(
            "skin.toml",
            "normal = [1.0, 0.0, 0.0]",
            "normal = [0.9, 0.0, 0.0]",
            ["skin.toml", "wrist_3", "normal", "0.9", "unit vector"],
            id="non-unit-normal",
        ),
        pytest.param(
            "skin.toml",
            'link = "forearm_link"\npoint = [-0.28, 0.09',
            'link = "forarm_link"\npoint = [-0.28, 0.09',
            ["skin.toml", "forearm_top", "'forarm_link'", "forearm_link"],
            id="missing-link",
        ),
        pytest.param(
            "skin.toml",
            'name = "wrist_2"',
            'name = "wrist_1"',
            ["skin.toml", "name", "'wrist_1'", "#8 and #9"],
            id="duplicate-name",
        ),
        pytest.param(
            "skin.toml",
            "id = 9",
            "id = 8",
            ["skin.toml", "id", "8", "more than one"],
            id="duplicate-id",
        ),
        pytest.param(
            "skin.toml",
            "id = 9",
            "id = 10",
            ["skin.toml", "0..9"],
            id="ids-not-contiguous",
        ),
        pytest.param(
            "skin.toml",
            "point = [0.0, 0.11, 0.0]",
            "point = [0.0, 0.11]",
            ["skin.toml", "shoulder_back", "point", "3 numbers"],
            id="short-point",
        ),
        pytest.param(
            "skin.toml",
            'region = "wrist"\nlink = "wrist_3_link"',
            'region = "wrist"\nlink = "wrist_3_link"\ncolour = "blue"',
            ["skin.toml", "wrist_3", "colour"],
            id="unknown-pad-key",
        ),
        pytest.param(
            "robot.toml",
            '"elbow_joint",',
            '"knee_joint",',
            ["robot.toml", "knee_joint", "elbow_joint"],
            id="joint-not-in-urdf",
        ),
        pytest.param(
            "robot.toml",
            "home = [0.0, -1.15, 1.85,",
            "home = [0.0, -1.15, 3.5,",
            ["robot.toml", "home", "elbow_joint", "3.5"],
            id="home-outside-limits",
        ),
        pytest.param(
            "robot.toml",
            "max_jerk = [160.0, 160.0, ",
            "max_jerk = [160.0, ",
            ["robot.toml", "max_jerk", "6 numbers"],
            id="short-jerk",
        ),
        pytest.param(
            "robot.toml",
            "max_acceleration = [8.0,",
            "max_acceleration = [-8.0,",
            ["robot.toml", "max_acceleration", "> 0"],
            id="negative-acceleration",
        ),
        pytest.param(
            "robot.toml",
            'tool_frame = "tool0"',
            'tool_frame = "tool9"',
            ["robot.toml", "tool_frame", "'tool9'", "tool0"],
            id="unknown-tool-frame",
        ),
        pytest.param(
            "robot.toml",
            'skin = "skin.toml"',
            'skin = "skins.toml"',
            ["robot.toml", "skins.toml", "does not exist"],
            id="missing-skin",
        ),
        pytest.param(
            "robot.toml",
            'urdf = "ur10e.urdf"',
            'urdf = "ur5e.urdf"',
            ["robot.toml", "ur5e.urdf", "does not exist"],
            id="missing-urdf",
        ),
        pytest.param(
            "robot.toml",
            'name = "ur10e"',
            'name = "ur10e"\nnmae = "x"',
            ["robot.toml", "nmae"],
            id="unknown-robot-key",
        ),
        pytest.param(
            "robot.toml",
            'name = "ur10e"',
            'name = "ur10e',
            ["robot.toml", "not valid TOML"],
            id="bad-toml",
        ),
    ],
)
def test_broken_descriptions_raise_helpful_config_errors(
    tmp_path: Path, file: str, old: str, new: str, expected: list[str]
) -> None:
    copy = copy_description(tmp_path)
    edit(copy / file, old, new)
    with pytest.raises(ConfigError) as error:
        load_description(copy / "robot.toml")
    message = str(error.value)
    for fragment in expected:
        assert fragment in message, f"{fragment!r} missing from: {message}"


def test_nearly_unit_normal_is_normalised(tmp_path: Path) -> None:
    copy = copy_description(tmp_path)
    edit(copy / "skin.toml", "normal = [1.0, 0.0, 0.0]", "normal = [1.0000005, 0.0, 0.0]")
    desc = load_description(copy / "robot.toml")
    assert np.linalg.norm(desc.pad("wrist_3").normal) == pytest.approx(1.0, abs=1e-15)


def test_missing_description_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_description(tmp_path / "robot.toml")


def test_a_packaged_robot_is_named_by_its_folder() -> None:
    from nwr.common.robot import ROBOTS_DIR, packaged_robots, resolve_description

    assert "ur10e" in packaged_robots()
    assert resolve_description("ur10e") == resolve_description(None) == ROBOTS_DIR / "ur10e" / "robot.toml"
    assert load_description("ur10e").name == load_description().name == "ur10e"
    with pytest.raises(ConfigError, match=r"robot.description = 'ur11' is no packaged robot \(fr3, ur10e\)"):
        load_description("ur11")


# ---------------------------------------------------------------- every packaged robot; the FR3's data


@pytest.mark.parametrize("name", ["ur10e", "fr3"])
def test_every_packaged_robot_loads_with_its_pads_on_its_links(name: str) -> None:
    from nwr.common.robot import packaged_robots

    assert name in packaged_robots()
    desc = load_description(name)
    model = RobotModel(desc)
    n = len(desc.joints)
    assert len(desc.reflex_range_deg) == len(desc.reflex_group) == len(desc.task_amplitude_rad) == n
    assert len(desc.pads) == 10 and {pad.region for pad in desc.pads} == set(REGIONS)
    assert desc.location is not None and set(desc.location["pl4"]) == set(REGIONS)
    skeleton = model.joint_positions(desc.home)
    points, normals = model.pad_points(desc.home), model.pad_normals(desc.home)
    for pad in desc.pads:  # on the arm's surface, facing away from its chain
        distance = segment_distance(points[pad.id], skeleton)
        assert 0.04 <= distance <= 0.3, f"{name}: pad {pad.name} is {distance:.3f} m from the chain"
        assert segment_distance(points[pad.id] + 0.005 * normals[pad.id], skeleton) > distance, pad.name


def test_the_fr3s_limits_are_frankas_published_ones() -> None:
    desc = load_description("fr3")
    np.testing.assert_array_equal(desc.q_min, [-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159])
    np.testing.assert_array_equal(desc.q_max, [2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159])
    np.testing.assert_array_equal(desc.v_max, [2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])
    np.testing.assert_array_equal(desc.a_max, [10.0] * 7)
    np.testing.assert_array_equal(desc.j_max, [5000.0] * 7)
    # The uniform reflex draws the flange in toward the base axis, as the UR10e's does.
    model = RobotModel(desc)
    q = np.clip(desc.home + desc.reflex_direction * np.radians(desc.reflex_range_deg) / 2, desc.q_min, desc.q_max)
    assert np.hypot(*model.tool_position(q)[:2]) < np.hypot(*model.tool_position(desc.home)[:2]) - 0.05


def copy_fr3(tmp_path: Path) -> Path:
    target = tmp_path / "fr3"
    shutil.copytree(PACKAGE_DIR.parent / "fr3", target)
    return target


@pytest.mark.parametrize(
    ("file", "old", "new", "expected"),
    [
        pytest.param("skin.toml", "point = [0.07, 0.0, 0.077]", "point = [70.0, 0.0, 77.0]",
                     ["skin.toml", "wrist_flange", "m from link 'link7'", "at most 0.3 m"], id="pad-off-its-link"),
        pytest.param("skin.toml", 'link = "link7"', 'link = "link9"', ["wrist_flange", "'link9'", "link7"],
                     id="pad-on-no-link"),
        pytest.param("skin.toml", "normal = [-0.70710678, -0.70710678, 0.0]", "normal = [-0.7, -0.7, 0.0]",
                     ["elbow_outer", "unit vector"], id="non-unit-normal"),
        pytest.param("robot.toml", '"joint6", "joint7"]', '"joint6"]', ["joints", "chain order", "joint7"],
                     id="joints-not-the-urdfs"),
        pytest.param("robot.toml", 'tool_frame = "link8"', 'tool_frame = "flange"',
                     ["tool_frame = 'flange'", "not a frame of fr3.urdf"], id="frame-not-the-urdfs"),
        pytest.param("robot.toml", "max_jerk = [5000.0, 5000.0, 5000.0, 5000.0, 5000.0, 5000.0, 5000.0]",
                     "max_jerk = [5000.0, 5000.0, 5000.0, 5000.0, 5000.0, 5000.0]", ["max_jerk", "list of 7"],
                     id="limits-for-six-joints"),
        pytest.param("robot.toml", "home = [0.0, -0.7854, 0.0, -2.3562, 0.0, 1.5708, 0.7854]",
                     "home = [0.0, -0.7854, 0.0, 0.0, 0.0, 1.5708, 0.7854]", ["home is outside", "joint4 = 0.0"],
                     id="home-outside-the-limits"),
        pytest.param("robot.toml", '"elbow", "wrist", "wrist"]', '"elbow", "hand", "wrist"]',
                     ["reflex_group", "base, shoulder, elbow, wrist"], id="unknown-joint-group"),
        pytest.param("robot.toml", "reflex_range_deg = [40.0, 70.0, 0.0, 146.0, 0.0, 73.0, 0.0]",
                     "reflex_range_deg = [40.0, 70.0, 0.0, 246.0, 0.0, 73.0, 0.0]", ["reflex_range_deg", "0 to 180"],
                     id="reflex-range-past-180"),
        pytest.param("robot.toml", "wrist = [0.0, 0.3, 0.6, 0.8]\n", "",
                     ["location.pl3", "'wrist'"], id="location-row-missing"),
        pytest.param("robot.toml", "double_frequency = [0, 1, 0, 1, 0, 0, 0]",
                     "double_frequency = [0, 2, 0, 1, 0, 0, 0]", ["task.double_frequency", "0 or 1"],
                     id="task-frequency-not-0-or-1"),
    ],
)
def test_a_broken_fr3_description_raises_a_helpful_config_error(
    tmp_path: Path, file: str, old: str, new: str, expected: list[str]
) -> None:
    copy = copy_fr3(tmp_path)
    edit(copy / file, old, new)
    with pytest.raises(ConfigError) as error:
        load_description(copy / "robot.toml")
    message = str(error.value)
    for fragment in expected:
        assert fragment in message, f"{fragment!r} missing from: {message}"
