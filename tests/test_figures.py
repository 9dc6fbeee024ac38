"""The figures are drawn by the services' own code and show what they claim."""

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib.colors import to_rgb

from nwr.common.robot import RobotModel, load_description
from nwr.services.tools import figures


def pixels_of(image: np.ndarray, color: str, tol: float = 0.06) -> int:
    rgb = np.asarray(to_rgb(color))
    return int(np.sum(np.all(np.abs(image[..., :3] - rgb) < tol, axis=-1)))


def test_gain_figure(tmp_path):
    path = figures.gain_figure(tmp_path / "gain.png")
    assert path.stat().st_size > 20_000
    image = mpimg.imread(path)
    assert image.shape[0] >= 500 and image.shape[1] >= 900
    # Both curves are drawn, the continuous one longer (it rises smoothly).
    cont, disc = pixels_of(image, figures.CONTINUOUS_COLOR), pixels_of(image, figures.DISCRETE_COLOR)
    assert cont > 2000 and disc > 2000


@pytest.mark.slow
def test_reflexes_figure(tmp_path):
    path = figures.reflexes_figure(tmp_path / "reflexes.png")
    assert path.stat().st_size > 100_000
    image = mpimg.imread(path)
    assert image.shape[1] > 3 * image.shape[0]  # four panels side by side
    for color in figures.TOUCH_COLORS:
        assert pixels_of(image, color) > 300, color
    assert pixels_of(image, "0.55", tol=0.03) > 1000  # the initial pose


def test_reflex_end_poses_differ_as_the_paper_says():
    desc = load_description()
    model = RobotModel(desc)
    ends = {(s, p): figures.reflex_end_pose(s, desc, model, p)[1] for s in ("uniform", "location")
            for p in figures.TOUCHES}
    # UR is stereotypical: the same end pose whatever was touched; LR depends on the region.
    np.testing.assert_allclose(ends[("uniform", "upper_arm_top")], ends[("uniform", "wrist_2")], atol=1e-6)
    assert np.abs(ends[("location", "upper_arm_top")] - ends[("location", "wrist_2")]).max() > 0.1
