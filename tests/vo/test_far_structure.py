"""Far structure: a ground-vehicle turn whose texture lies almost entirely beyond 40 baselines
(KITTI-like camera, 0.537 m baseline: 21.5 m). Depth from small disparities is biased long and
noisy; the odometry must not turn that into a path-length (scale) error."""

from __future__ import annotations

import numpy as np
import pytest

from vtr.app.evaluation import drift_metrics
from vtr.app.pipeline import run_odometry
from vtr.config import Config
from vtr.io import open_source
from vtr.sim import synthetic as syn
from vtr.vo.stereo import StereoProcessor

FAR_BASELINES = 40.0
SCALE_ERROR_BOUND = 0.01
T_ERR_BOUND_PCT = 1.5


@pytest.fixture(scope="module")
def far_run(tmp_path_factory):
    cam = syn.kitti_like_camera()
    T = syn.turning_route(1.0, straight_before_m=15, turn_radius_m=12, straight_after_m=15)
    scene = syn.far_structure_scene(3, T[:, :2, 3])
    out = syn.write_sequence(tmp_path_factory.mktemp("far") / "turn", scene, cam, T, syn.route_times(T, 10.0),
                             noise_sigma=1.0, noise_seed=1)
    cfg = Config()
    with open_source(out) as src:
        sp = StereoProcessor(src.camera, cfg.features, cfg.stereo)
        depths = np.concatenate([f.points[f.has_depth, 2] for f in (sp.process(src[i]) for i in (5, 25, 45))])
        _, poses, _ = run_odometry(src, list(range(len(src))), cfg)
        gt = src.ground_truth().T_world_cam
    return cam, depths, drift_metrics(poses, gt)


def test_texture_is_mostly_far(far_run):
    cam, depths, _ = far_run
    assert np.mean(depths > FAR_BASELINES * cam.baseline) > 0.9


def test_path_length_scale_error_within_one_percent(far_run):
    assert abs(far_run[2].length_ratio - 1.0) <= SCALE_ERROR_BOUND


def test_translation_drift_within_bound(far_run):
    assert far_run[2].t_err_pct <= T_ERR_BOUND_PCT
