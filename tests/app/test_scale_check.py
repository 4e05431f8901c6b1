"""The data's own share of a scale error, measured on the shipped KITTI clips (tools/scale_check.py)."""

from __future__ import annotations

import numpy as np
import pytest

from vtr.app.scale_check import disparity_offset, disparity_samples, near_point_scale
from vtr.config import Config
from vtr.io import open_source


@pytest.fixture(scope="module")
def ramp(kitti_ramp_clip):
    with open_source(kitti_ramp_clip) as src:
        return disparity_offset(disparity_samples(src, Config())), near_point_scale(src, Config())


def test_ramp_disparities_sit_about_one_pixel_below_the_ground_truth_motion(ramp):
    line, _ = ramp
    assert line.points > 500
    assert -1.5 <= line.offset_px <= -0.7 and abs(line.slope - 1) <= 0.03


def test_ramp_near_point_scale_grows_as_far_points_join(ramp):
    _, scale = ramp
    s = np.array([scale[t] for t in sorted(scale, reverse=True)])  # thresholds 30, 15, 5, 1 px
    assert 1.0 <= s[0] <= 1.03
    assert np.all(np.diff(s) > 0)


def test_kitti06_disparities_agree_with_the_ground_truth_motion(kitti_clip):
    with open_source(kitti_clip) as src:
        line = disparity_offset(disparity_samples(src, Config(), steps=(1,)))
    assert abs(line.offset_px) <= 0.4
