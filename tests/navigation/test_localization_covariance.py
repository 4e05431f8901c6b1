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


CELLS = 8  # localization.covariance_blocks' default: the leaf image in 8 x 8 cells
TRIALS = 30
ISOLATED_SIGMA_PX = 0.2  # each feature's own pixel noise besides its cell's
NEES_3DOF_99 = 11.345  # 99 % quantile of chi-square with 3 degrees of freedom


def _leaf_pose_errors(config: Config, sigma_px: float, cell_sigma_px: float, seed: int) -> np.ndarray:
    """Translation NEES of ``TRIALS`` localizations whose leaf measurements carry, besides independent pixel noise,
    one error shared by the features of each image cell (``cell_sigma_px`` on u and v; the same on u_r)."""
    rng = np.random.default_rng(seed)
    localizer = Localizer(CAM, config.localization, config.estimation, pixel_sigma=1.0)
    out = []
    for _ in range(TRIALS):
        depth = np.where(
            rng.random(LANDMARKS) < 0.5, rng.uniform(*FAR_DEPTH_M, LANDMARKS), rng.uniform(*NEAR_DEPTH_M, LANDMARKS)
        )
        X = CAM.triangulate(
            rng.uniform(50, CAM.width - 50, LANDMARKS), rng.uniform(20, CAM.height - 20, LANDMARKS), CAM.fb / depth
        )
        T_true = exp_se3(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.3, 3)])
        Y = X @ T_true[:3, :3].T + T_true[:3, 3]
        z_leaf = CAM.project(Y)
        ok = (
            (Y[:, 2] > 1.0)
            & (z_leaf[:, 0] > 0)
            & (z_leaf[:, 0] < CAM.width)
            & (z_leaf[:, 1] > 0)
            & (z_leaf[:, 1] < CAM.height)
        )
        X, z_leaf = X[ok], z_leaf[ok]
        cell = np.clip(z_leaf[:, 0] / CAM.width * CELLS, 0, CELLS - 1).astype(int) * CELLS + np.clip(
            z_leaf[:, 1] / CAM.height * CELLS, 0, CELLS - 1
        ).astype(int)
        shift = rng.normal(0.0, cell_sigma_px, (CELLS * CELLS, 2))[cell]
        z_leaf = z_leaf + np.column_stack([shift[:, 0], shift[:, 1], shift[:, 0]])
        z_leaf = z_leaf + rng.normal(0.0, sigma_px, z_leaf.shape)
        z_taught = CAM.project(X) + rng.normal(0.0, sigma_px, (len(X), 3))
        submap = _submap(CAM.triangulate(z_taught[:, 0], z_taught[:, 1], z_taught[:, 0] - z_taught[:, 2]), z_taught)
        T, cov, _, _, _ = localizer._refine(submap, np.arange(len(X)), z_leaf, T_true)
        e = (T @ np.linalg.inv(T_true))[:3, 3]
        out.append(float(e @ np.linalg.solve(cov[3:, 3:], e)))
    return np.array(out)


# derandomize: the medians over 30 trials move with the draw (the inverse Hessian's 4.4-11.2 over 13 seeds measured,
# 4.37 once, with cell_sigma_px 0.5, seed 2546, in a fresh CI run), so a random seed fails now and then whatever the
# code; fixed examples keep this a check on the code
@settings(max_examples=3, deadline=None, derandomize=True)
@given(cell_sigma_px=st.floats(0.3, 0.5), seed=st.integers(0, 2**31 - 1))
def test_the_block_jackknife_covers_errors_shared_within_image_cells(cell_sigma_px, seed):
    """Feature errors shared within a cell of the image do not average out over its features. The localization's
    covariance (the delete-one-block jackknife over 8 x 8 cells) covers them: NEES median near 2.37, >= 85 % inside
    the 99 % bound; the adjustment's inverse Hessian with its variance factor (covariance_blocks 0, as before)
    is too narrow (median above 4.5)."""
    jackknife = _leaf_pose_errors(Config(), ISOLATED_SIGMA_PX, cell_sigma_px, seed)
    assert 1.2 <= np.median(jackknife) <= 4.5 and np.mean(jackknife <= NEES_3DOF_99) >= 0.85, np.median(jackknife)
    iid = _leaf_pose_errors(
        Config().replace("localization", covariance_blocks=0), ISOLATED_SIGMA_PX, cell_sigma_px, seed
    )
    assert np.median(iid) > 4.5, np.median(iid)
