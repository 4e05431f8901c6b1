"""Stereo odometry on the real KITTI 06 clip against its ground truth."""

import numpy as np
import pytest

from vtr.app.evaluation import drift_metrics
from vtr.app.pipeline import run_odometry
from vtr.config import Config
from vtr.errors import ConfigError
from vtr.io import open_source
from vtr.types import FrameKind

# ORB-SLAM3 stereo on this clip: 0.69-0.73 % and 0.0126-0.0138 deg/m; naive PnP VO: 2.5 %, 0.022 deg/m.
# 0.75 %: no regression from 0.68 % before the far-structure estimator (now 0.61 %)
T_ERR_BOUND_PCT = 0.75
R_ERR_BOUND_DEG_PER_M = 0.015
NAIVE_T_ERR_PCT = 2.5
# kitti00_ramp_clip (far structure): ORB-SLAM3 stereo 5.97 %, naive PnP 8.8 %; vtr before the far-structure
# estimator 10.6 % and path x1.108. Near points alone put this clip's motion about 1-2 % above its ground truth
# (tools/scale_check.py: its disparities sit 1.16 px low); the odometry estimates that offset online and removes it
# (odometry.disparity_offset): path x0.998, t_err 0.73 % (with the calibration trusted x1.010, 1.41 %, inside the
# (1.00, 1.04) this range was before)
RAMP_T_ERR_BOUND_PCT = 4.0
RAMP_PATH_LENGTH_RANGE = (0.99, 1.01)


@pytest.fixture(scope="module")
def kitti_run(kitti_clip):
    with open_source(kitti_clip) as src:
        results, poses, _ = run_odometry(src, list(range(len(src))), Config())
        gt = src.ground_truth().T_world_cam
    return results, poses, drift_metrics(poses, gt)


def test_every_frame_tracked_with_many_inliers(kitti_run):
    results, poses, _ = kitti_run
    assert len(results) == 51
    assert results[0].kind == FrameKind.CREATE_VERTEX
    assert all(r.kind != FrameKind.FAILURE for r in results)
    assert min(r.inliers for r in results[1:]) >= 100
    assert np.all(np.isfinite(poses))


def test_better_than_naive_odometry(kitti_run):
    assert kitti_run[2].t_err_pct < NAIVE_T_ERR_PCT


def test_rotation_drift_within_bound(kitti_run):
    assert kitti_run[2].r_err_deg_per_m <= R_ERR_BOUND_DEG_PER_M


def test_translation_drift_within_bound(kitti_run):
    assert kitti_run[2].t_err_pct <= T_ERR_BOUND_PCT


def test_without_history_the_odometry_keeps_only_its_window(kitti_clip, kitti_run):
    """Teach and repeat run odometry with keep_history=False: same keyframes, no per-frame memory."""
    from vtr.vo.odometry import OdometrySettings, StereoOdometry

    with open_source(kitti_clip) as src:
        vo = StereoOdometry(src.camera, OdometrySettings.of(Config()), keep_history=False)
        finalized = []
        for images in src.iter_frames(range(len(src))):
            finalized += vo.process(images).finalized
        finalized += vo.flush()
        assert len(vo._keyframe_poses) == 0  # every keyframe's pose was handed out and dropped
    with pytest.raises(ConfigError, match="keep_history"):
        vo.final_poses()
    poses = kitti_run[1]
    assert len(finalized) == len(poses)  # every KITTI frame is a keyframe
    assert np.allclose(np.array([kf.T_world_kf for kf in finalized]), poses, atol=1e-9)


@pytest.fixture(scope="module")
def ramp_run(kitti_ramp_clip):
    with open_source(kitti_ramp_clip) as src:
        results, poses, _ = run_odometry(src, list(range(len(src))), Config())
        gt = src.ground_truth().T_world_cam
    return results, drift_metrics(poses, gt)


def test_far_structure_ramp_every_frame_tracked(ramp_run):
    results, _ = ramp_run
    assert len(results) == 26 and all(r.kind != FrameKind.FAILURE for r in results)


def test_far_structure_ramp_translation_drift_within_bound(ramp_run):
    assert ramp_run[1].t_err_pct <= RAMP_T_ERR_BOUND_PCT


def test_far_structure_ramp_path_length(ramp_run):
    lo, hi = RAMP_PATH_LENGTH_RANGE
    assert lo <= ramp_run[1].length_ratio <= hi
