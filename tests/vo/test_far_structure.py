"""Far structure on synthetic imagery, rendered with what real stereo does to far points.

Two ground-vehicle turns seen by a KITTI-like camera (0.537 m baseline):

* **realistic**: the right image is rendered with its principal point ``RIGHT_CX_OFFSET_PX`` right of the
  calibration's (a rectification error the calibration does not know of: every measured disparity is
  about 1 px smaller than the calibration implies, as ``tools/scale_check.py`` measures on the real
  kitti00_ramp_clip), with optical blur and sensor noise, and structures from 3 m of the road. The
  estimator before the far-structure work (commit 9244307) gave path length x1.059 and t_err 5.6 % here,
  x1.108 and 10.6 % on the real ramp; the bounds are those of the real clip. The odometry now estimates the
  rendered offset online and removes it (``odometry.disparity_offset``; tests/vo/test_disparity_offset.py).
* **ideal** (exact rectification), texture almost entirely beyond 40 baselines: the scale must hold.
"""

from __future__ import annotations

import numpy as np
import pytest

from vtr.app.evaluation import drift_metrics
from vtr.app.pipeline import run_odometry
from vtr.app.scale_check import disparity_offset, disparity_samples
from vtr.config import Config
from vtr.io import open_source
from vtr.sim import synthetic as syn
from vtr.vo.stereo import StereoProcessor

FAR_BASELINES = 40.0
SCALE_ERROR_BOUND = 0.01
T_ERR_BOUND_PCT = 1.5
RIGHT_CX_OFFSET_PX = 1.1  # measured on kitti00_ramp_clip: disparities 1.16 px below the motion's
BLUR_SIGMA_PX = 0.7
REALISTIC_T_ERR_BOUND_PCT = 4.0
# the odometry estimates the rendered offset and removes it (odometry.disparity_offset): path x0.997, t_err 1.60 %
# (with the calibration trusted, "off": x1.025, 3.1 %, inside the (1.00, 1.04) this range was before)
REALISTIC_PATH_LENGTH_RANGE = (0.99, 1.01)


def _turn():
    return syn.turning_route(1.0, straight_before_m=15, turn_radius_m=12, straight_after_m=15)


def _odometry(path):
    with open_source(path) as src:
        _, poses, _ = run_odometry(src, list(range(len(src))), Config())
        gt = src.ground_truth().T_world_cam
    return drift_metrics(poses, gt)


@pytest.fixture(scope="module")
def far_run(tmp_path_factory):
    cam = syn.kitti_like_camera()
    T = _turn()
    scene = syn.far_structure_scene(3, T[:, :2, 3])
    out = syn.write_sequence(
        tmp_path_factory.mktemp("far") / "turn", scene, cam, T, syn.route_times(T, 10.0), noise_sigma=1.0, noise_seed=1
    )
    cfg = Config()
    with open_source(out) as src:
        sp = StereoProcessor(src.camera, cfg.features, cfg.stereo)
        depths = np.concatenate([f.points[f.has_depth, 2] for f in (sp.process(src[i]) for i in (5, 25, 45))])
    return cam, depths, _odometry(out)


@pytest.fixture(scope="module")
def realistic_sequence(tmp_path_factory):
    T = _turn()
    scene = syn.far_structure_scene(3, T[:, :2, 3], ground_contrast=1.0, near_clearance_m=3.0)
    return syn.write_sequence(
        tmp_path_factory.mktemp("far_real") / "turn",
        scene,
        syn.kitti_like_camera(),
        T,
        syn.route_times(T, 10.0),
        noise_sigma=1.0,
        noise_seed=1,
        blur_sigma_px=BLUR_SIGMA_PX,
        right_cx_offset_px=RIGHT_CX_OFFSET_PX,
    )


def test_texture_is_mostly_far(far_run):
    cam, depths, _ = far_run
    assert np.mean(depths > FAR_BASELINES * cam.baseline) > 0.9


def test_path_length_scale_error_within_one_percent(far_run):
    assert abs(far_run[2].length_ratio - 1.0) <= SCALE_ERROR_BOUND


def test_translation_drift_within_bound(far_run):
    assert far_run[2].t_err_pct <= T_ERR_BOUND_PCT


def test_realistic_render_reproduces_the_disparity_offset_of_real_pairs(realistic_sequence):
    """The scale check sees the rendered rectification error as real pairs show theirs (-1.16 px on the ramp)."""
    with open_source(realistic_sequence) as src:
        line = disparity_offset(disparity_samples(src, Config()))
    assert -1.3 <= line.offset_px <= -0.7


def test_realistic_far_structure_scale(realistic_sequence):
    m = _odometry(realistic_sequence)
    lo, hi = REALISTIC_PATH_LENGTH_RANGE
    assert lo <= m.length_ratio <= hi
    assert m.t_err_pct <= REALISTIC_T_ERR_BOUND_PCT
