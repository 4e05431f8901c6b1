"""The localization's covariance as the residuals scale it: the a-posteriori variance factor of the stereo bundle
adjustment recovers the pixel noise the measurements were drawn with, when far landmarks' disparity rows are down-
weighted (docs/localization.md, "What the covariance holds")."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.camera import StereoCamera
from vtr.config import Config
from vtr.geometry import exp_se3
from vtr.navigation.localization import Localizer, TaughtSubmap

CAM = StereoCamera(fx=700.0, fy=700.0, cx=600.0, cy=185.0, baseline=0.54, width=1226, height=370)
LANDMARKS = 600
NEAR_DEPTH_M = (3.0, 7.0)  # inside estimation.far_point_baselines (15) baselines: the disparity counts fully
FAR_DEPTH_M = (12.0, 40.0)  # beyond: the disparity keeps far_disparity_weight
FACTOR_TOLERANCE = 0.25  # relative; the estimate's own spread at ~1000 degrees of freedom is ~5 %


def _submap(points: np.ndarray, z: np.ndarray) -> TaughtSubmap:
    """One taught vertex (the trunk) observing ``points`` (its frame) at ``z``, each its own triangulation."""
    n = len(points)
    return TaughtSubmap(
        vertex_ids=np.array([0]),
        T_vertex_trunk=np.eye(4)[None],
        trunk_slot=0,
        points_trunk=points,
        descriptors=np.zeros((n, 32), np.uint8),
        slot=np.zeros(n, int),
        z=z,
        feature=np.arange(n),
        depth_m=CAM.fb / (z[:, 0] - z[:, 2]),
        refined=np.zeros(n, bool),
    )


@settings(max_examples=15, deadline=None)
@given(
    sigma_px=st.floats(0.15, 0.6),
    far_share=st.floats(0.3, 0.85),
    seed=st.integers(0, 2**31 - 1),
)
def test_variance_factor_recovers_the_pixel_noise_with_far_landmarks(sigma_px, far_share, seed):
    """Taught vertex and leaf both observe the landmarks with Gaussian pixel noise ``sigma_px`` on every row; the
    far ones' disparity rows carry ``far_disparity_weight`` (1e-4). The variance factor (robust cost per degree of
    freedom, in units of the modelled 1 px) is ``sigma_px**2``. Counting the far disparity rows as whole degrees of
    freedom (as before) read it 0.5-0.7 times that."""
    rng = np.random.default_rng(seed)
    far = rng.random(LANDMARKS) < far_share
    depth = np.where(far, rng.uniform(*FAR_DEPTH_M, LANDMARKS), rng.uniform(*NEAR_DEPTH_M, LANDMARKS))
    u = rng.uniform(50, CAM.width - 50, LANDMARKS)
    v = rng.uniform(20, CAM.height - 20, LANDMARKS)
    X = CAM.triangulate(u, v, CAM.fb / depth)
    T_leaf_trunk = exp_se3(np.r_[0.01, -0.02, 0.005, 0.3, 0.05, 0.8])
    Y = X @ T_leaf_trunk[:3, :3].T + T_leaf_trunk[:3, 3]
    keep = Y[:, 2] > 1.0
    X, Y = X[keep], Y[keep]
    z_taught = CAM.project(X) + rng.normal(0.0, sigma_px, (len(X), 3))
    z_leaf = CAM.project(Y) + rng.normal(0.0, sigma_px, (len(X), 3))
    config = Config()
    localizer = Localizer(CAM, config.localization, config.estimation, pixel_sigma=1.0)
    submap = _submap(CAM.triangulate(z_taught[:, 0], z_taught[:, 1], z_taught[:, 0] - z_taught[:, 2]), z_taught)
    start = exp_se3(np.r_[0.0, 0.0, 0.0, 0.01, -0.01, 0.02]) @ T_leaf_trunk
    T, _, ok, _, factor = localizer._refine(submap, np.arange(len(X)), z_leaf, start)
    assert ok.mean() > 0.95
    assert np.linalg.norm(T[:3, 3] - T_leaf_trunk[:3, 3]) < 0.05
    assert abs(factor / sigma_px**2 - 1.0) < FACTOR_TOLERANCE, (factor, sigma_px**2)
