"""The library's public entry points refuse what they cannot use with the package's own errors:
images of the wrong size, type or shape; config sections built in code with values outside their domain;
non-SE(3) poses, bad covariances and far extrapolation in the smoother and the controller state."""

from __future__ import annotations

import numpy as np
import pytest

from vtr.config import Config, SmoothingConfig
from vtr.errors import ConfigError, DataError, EstimationError
from vtr.io import open_source
from vtr.map import Map
from vtr.state.controller import controller_state, gravity_aligned_T_o_t
from vtr.state.smoothing import TrajectorySmoother
from vtr.types import FrameKind, StereoImages
from vtr.vo.odometry import OdometrySettings, StereoOdometry

COV = np.diag([1e-6] * 3 + [1e-4] * 3)


@pytest.fixture(scope="module")
def kitti(kitti_clip):
    with open_source(kitti_clip) as src:
        return src.camera, [src[i] for i in range(3)]


def _with(f: StereoImages, **kw) -> StereoImages:
    return StereoImages(kw.get("t_ns", f.t_ns), f.index, kw.get("left", f.left), kw.get("right", f.right))


def _bad_images(f: StereoImages) -> dict[str, tuple[StereoImages, str]]:
    h, w = f.left.shape
    return {
        "cropped 100 px": (_with(f, left=f.left[:, 100:], right=f.right[:, 100:]), f"is {w - 100}x{h}"),
        "right only cropped": (_with(f, right=f.right[:-1]), f"is {w}x{h - 1}"),
        "float": (_with(f, left=f.left.astype(np.float32)), "uint8"),
        "uint16": (_with(f, left=f.left.astype(np.uint16) * 256), "uint8"),
        "rgb": (_with(f, left=np.dstack([f.left] * 3)), "2-D greyscale"),
        "0x0": (_with(f, left=np.zeros((0, 0), np.uint8)), "is 0x0"),
        "list": (_with(f, left=f.left.tolist()), "numpy array"),
        "float time": (_with(f, t_ns=1.5), "integer time"),
    }


@pytest.mark.parametrize(
    "case", ["cropped 100 px", "right only cropped", "float", "uint16", "rgb", "0x0", "list", "float time"]
)
def test_odometry_refuses_unusable_images(kitti, case):
    camera, frames = kitti
    vo = StereoOdometry(camera, OdometrySettings.of(Config()))
    assert vo.process(frames[0]).kind == FrameKind.CREATE_VERTEX
    images, named = _bad_images(frames[1])[case]
    with pytest.raises(DataError) as err:
        vo.process(images)
    assert named in str(err.value) and "\n" not in str(err.value)
    # the refused frame left the odometry untouched: the next good frame tracks
    assert vo.process(frames[1]).kind != FrameKind.FAILURE


def test_a_section_outside_its_domain_cannot_be_built():
    from vtr.config import FeatureConfig, OdometryConfig

    with pytest.raises(ConfigError, match=r"^config: features\.n_levels must be an integer in \[1, 16\], got 0$"):
        FeatureConfig(n_levels=0)  # segfaulted inside OpenCV's ORB
    with pytest.raises(ConfigError, match=r"odometry\.keyframe_translation_m"):
        OdometryConfig(keyframe_translation_m=float("nan"))  # was accepted: no keyframe after the first
    with pytest.raises(ConfigError, match=r"features\.grid_rows"):  # a changed copy is checked too
        Config().replace("features", grid_rows=0)


# ---------------------------------------------------------------- smoother and controller state


def _smoother(n: int = 5) -> TrajectorySmoother:
    sm = TrajectorySmoother(SmoothingConfig())
    for k in range(n):
        T = np.eye(4)
        T[0, 3] = 0.1 * k
        sm.add_pose(k * 100_000_000, T, COV)
    return sm


@pytest.mark.parametrize(
    ("T", "named"),
    [
        (np.full((4, 4), np.nan), "NaN"),
        (np.diag([2.0, 1, 1, 1]), "orthonormal"),
        (np.eye(3), "4x4"),
        (np.diag([1.0, 1, 1, 0]), "last row"),
    ],
)
def test_smoother_refuses_non_se3_poses(T, named):
    sm = _smoother(2)
    with pytest.raises(EstimationError, match=named):
        sm.add_pose(10**9, T, COV)
    assert sm.num_keyframes == 2


@pytest.mark.parametrize(
    ("cov", "named"),
    [
        (np.full((6, 6), np.nan), "NaN"),
        (-np.eye(6), "positive definite"),
        (np.eye(5), "6x6"),
        (np.zeros((6, 6)), "non-zero"),
    ],
)
def test_smoother_refuses_bad_covariances(cov, named):
    sm = _smoother(2)
    with pytest.raises(EstimationError, match=named):
        sm.add_pose(10**9, np.eye(4), cov)


def test_state_at_refuses_far_extrapolation():
    sm = _smoother()
    last = sm.last_time_ns
    horizon_ns = int(SmoothingConfig().max_extrapolation_s * 1e9)
    assert sm.state_at(last + horizon_ns).kind == "extrapolated"  # up to the horizon: answered
    thirty_years = 30 * 365 * 24 * 3600 * 10**9
    for t in (last + horizon_ns + 1, last + thirty_years):
        with pytest.raises(EstimationError, match=r"after the newest keyframe.*smoothing\.max_extrapolation_s"):
            sm.state_at(t)
    longer = TrajectorySmoother(SmoothingConfig(max_extrapolation_s=5.0))
    longer.add_pose(0, np.eye(4), COV)
    assert longer.state_at(4 * 10**9).kind == "extrapolated"


def test_smoother_refuses_a_section_outside_its_domain():
    with pytest.raises(ConfigError, match=r"smoothing\.lag_s"):
        TrajectorySmoother(SmoothingConfig(lag_s=float("nan")))
    with pytest.raises(ConfigError, match=r"smoothing\.max_extrapolation_s"):
        TrajectorySmoother(SmoothingConfig(max_extrapolation_s=-1.0))


def test_controller_state_refuses_non_se3_trunk():
    state = _smoother().state_at(400_000_000)
    T_o_t = gravity_aligned_T_o_t(np.eye(3))
    for bad in (np.full((4, 4), np.inf), np.diag([1.0, 1, 1, 2])):
        with pytest.raises(EstimationError, match="T_world_trunk"):
            controller_state(state, bad, T_o_t)
    with pytest.raises(EstimationError, match="T_sensor_vehicle"):
        controller_state(state, np.eye(4), T_o_t, np.zeros((4, 4)))


def test_map_refuses_a_frame_with_landmarks_behind_the_camera(kitti, tmp_path):
    from vtr.errors import MapError
    from vtr.types import StereoFrame
    from vtr.vo.stereo import StereoProcessor

    camera, frames = kitti
    cfg = Config()
    f = StereoProcessor(camera, cfg.features, cfg.stereo).process(frames[0])
    points = f.points.copy()
    points[:, 2] *= -1
    behind = StereoFrame(f.t_ns, f.index, f.features, f.u_right, points)
    with Map.create(tmp_path / "m.vtrmap", camera) as m:
        run = m.begin_run("teach", source="x", privileged=True)
        with pytest.raises(MapError, match="behind its camera"):
            m.add_vertex(run, f.t_ns, np.eye(4), behind, camera.T_vehicle_sensor)
        m.add_vertex(run, f.t_ns, np.eye(4), f, camera.T_vehicle_sensor)
