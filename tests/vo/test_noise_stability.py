"""Odometry under imperceptible sensor noise (1 grey level, Gaussian, both images): the accuracy must not hinge on it.

The noisy copies come from ``tools/bench_noise.py`` (the benchmark prints clean + 4 seeds per clip and the spread);
here one seed outside the benchmark's per clip, so a fix fitted to the benchmark's seeds does not pass by itself.
Bounds are issue 33's: kitti06 <= 0.70 %, kitti00_ramp_clip <= 1.3 %. docs/odometry_stability.md.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from vtr.app.evaluation import drift_metrics
from vtr.app.pipeline import run_odometry
from vtr.config import Config
from vtr.io import open_source
from vtr.vo import odometry as od
from vtr.vo.odometry import OdometrySettings, StereoOdometry

ROOT = Path(__file__).resolve().parents[2]
SEED = 7  # not among the benchmark's 1-4
KITTI06_BOUND_PCT = 0.70
RAMP_BOUND_PCT = 1.3
RAMP_SPREAD_POINTS = 0.3  # max - min over clean and the four seeds (issue bound)
RANSAC_SEEDS = (0, 1, 2, 3)  # run.seed: the order in which RANSAC sees the correspondences
RANSAC_SPREAD_POINTS = 0.3  # the clean ramp over those orders: RANSAC's sample must not decide the result
# share of the matched near landmarks (within far_point_baselines) that tracking keeps as inliers over the ramp;
# with RANSAC's inliers alone (odometry.inlier_rounds 1) it was 0.42 clean and with seed 7 (0-8 of 5-22 per frame:
# its translation rests on far landmarks), with the inliers chosen again at the refined pose (4, the default) 0.81
NEAR_INLIER_SHARE = 0.7


def _tool():
    spec = importlib.util.spec_from_file_location("bench_noise_tool", ROOT / "tools" / "bench_noise.py")
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    return tool


@pytest.fixture(scope="module")
def tool():
    return _tool()


def test_noise_is_one_grey_level_and_the_same_every_time(tool, kitti_clip):
    with open_source(kitti_clip) as src:
        images = src[3]
    a, b = tool.noisy_images(images, SEED, 1.0), tool.noisy_images(images, SEED, 1.0)
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    diff = a.left.astype(int) - images.left.astype(int)
    assert a.left.dtype == np.uint8 and 0.9 <= diff.std() <= 1.1 and np.abs(diff).max() <= 6
    assert not np.array_equal(tool.noisy_images(images, SEED + 1, 1.0).left, a.left)


def test_kitti06_with_noise_within_bound(tool, kitti_clip):
    r = tool.run_variant(kitti_clip, SEED, 1.0, Config())
    assert r["failures"] == 0
    assert r["t_err_pct"] <= KITTI06_BOUND_PCT


def test_ramp_with_noise_within_bound_and_spread(tool, kitti_ramp_clip):
    """The issue's bound on the ramp: clean and the benchmark's four noise seeds each <= 1.3 %, spread <= 0.3.

    Measured 0.73 %; 0.77-0.88 % (spread 0.15; seeds 5-8 0.89-0.95 %) with the online disparity offset
    (odometry.disparity_offset, vtr.vo.disparity_offset): the ramp's pairs put every disparity 1.16 px low, which
    the odometry now estimates from the window's parallax and removes. With the calibration trusted
    (disparity_offset "off") 1.41 %; 1.19-1.72 % (spread 0.53): the near landmarks put the path x1.010-1.014 long
    (docs/odometry_stability.md)."""
    errors = [tool.run_variant(kitti_ramp_clip, seed, 1.0, Config())["t_err_pct"] for seed in (None, 1, 2, 3, 4)]
    assert max(errors) <= RAMP_BOUND_PCT and max(errors) - min(errors) <= RAMP_SPREAD_POINTS, errors


def test_ransac_sample_does_not_decide(kitti_ramp_clip):
    """The clean ramp with the correspondences shown to RANSAC in four orders (``odometry.seed``): the inliers are
    chosen at the refined pose, so the result moves by less than the issue's spread (measured 0.73-0.79 % with the
    online disparity offset, 1.41-1.56 % with the calibration trusted; with ``odometry.inlier_rounds`` 1, RANSAC's
    inliers alone, 1.08-1.80 %)."""
    errors = []
    for seed in RANSAC_SEEDS:
        config = Config().replace("run", seed=seed)
        with open_source(kitti_ramp_clip) as src:
            _, poses, _ = run_odometry(src, list(range(len(src))), config)
            T_gt = src.ground_truth().T_world_cam
        errors.append(drift_metrics(poses, T_gt).t_err_pct)
    assert max(errors) - min(errors) <= RANSAC_SPREAD_POINTS, errors


def test_tracking_keeps_the_near_landmarks_ransac_left_out(tool, kitti_ramp_clip, monkeypatch):
    """The inliers are those of the refined pose, not of RANSAC's best sample: on the ramp most matched near landmarks
    (the scale's only anchor) are inliers, for the noisy copy as for the clean one (with ``odometry.inlier_rounds`` 1,
    RANSAC's inliers alone, 42 %)."""
    counts = []
    estimate = StereoOdometry._estimate

    def spy(self, frame, lm, feat):
        track = estimate(self, frame, lm, feat)
        disparity = frame.features.uv[:, 0] - frame.u_right
        near = disparity >= self.camera.fb / (self.config.estimation.far_point_baselines * self.camera.baseline)
        counts.append((near[feat].sum(), near[track.features].sum() if track is not None else 0))
        return track

    monkeypatch.setattr(od.StereoOdometry, "_estimate", spy)
    for seed in (None, SEED):
        counts.clear()
        with open_source(kitti_ramp_clip) as src:
            vo = StereoOdometry(src.camera, OdometrySettings.of(Config()))
            for images in tool.NoisySource(src, seed, 1.0).iter_frames():
                vo.process(images)
        matched, kept = np.sum(counts, axis=0)
        assert matched > 100 and kept / matched >= NEAR_INLIER_SHARE
