import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from vtr.camera import StereoCamera
from vtr.errors import CalibrationError
from vtr.vo.estimation import stereo_jacobian

CAM = StereoCamera(fx=707.0912, fy=707.0912, cx=601.8873, cy=183.1104, baseline=0.537, width=1226, height=370)

points = st.tuples(st.floats(-20, 20), st.floats(-5, 5), st.floats(1.0, 80.0))


@given(points)
def test_project_then_triangulate_round_trip(p):
    p = np.array([p])
    z = CAM.project(p)
    np.testing.assert_allclose(CAM.triangulate(z[:, 0], z[:, 1], z[:, 0] - z[:, 2]), p, rtol=1e-9, atol=1e-9)


def _numeric_jacobian(f, x, h=1e-6):
    return np.stack([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(len(x))], axis=-1)


@given(points)
def test_stereo_jacobian_matches_finite_differences(p):
    p = np.array(p)
    J = stereo_jacobian(p[None], CAM)[0]
    Jn = _numeric_jacobian(lambda x: CAM.project(x[None])[0], p)
    np.testing.assert_allclose(J, Jn, rtol=1e-5, atol=1e-6)


@given(points)
def test_point_covariance_is_propagated_pixel_noise(p):
    p = np.array(p)
    z = CAM.project(p[None])[0]
    J = _numeric_jacobian(lambda m: CAM.triangulate(m[:1], m[1:2], m[:1] - m[2:3])[0], z, h=1e-4)
    np.testing.assert_allclose(CAM.point_covariance(p[None], 0.5)[0], 0.25 * J @ J.T, rtol=1e-4, atol=1e-9)


def test_depth_variance_grows_with_fourth_power_of_depth():
    near, far = CAM.point_covariance(np.array([[0, 0, 10.0], [0, 0, 40.0]]), 1.0)[:, 2, 2]
    assert far / near == pytest.approx(4.0**4, rel=1e-6)


def test_invalid_calibration_is_rejected():
    with pytest.raises(CalibrationError):
        StereoCamera(fx=0.0, fy=1, cx=0, cy=0, baseline=0.1, width=10, height=10)
    with pytest.raises(CalibrationError):
        StereoCamera(fx=1.0, fy=1, cx=0, cy=0, baseline=float("nan"), width=10, height=10)


def test_dict_round_trip_and_match():
    other = StereoCamera.from_dict(CAM.to_dict())
    assert other.matches(CAM)
    assert not other.matches(StereoCamera.from_dict({**CAM.to_dict(), "baseline": 0.12}))


@given(st.floats(-2000, 3000), st.floats(-1000, 1400), st.floats(-5.0, 60.0), st.floats(0.0, 50.0))
def test_in_view_is_depth_and_image_bounds(u, v, z, margin):
    """A point is in view when it is beyond MIN_DEPTH_M and its pixel lies in the image grown by the margin."""
    from vtr.camera import MIN_DEPTH_M

    p = np.array([[(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z]])
    expected = (
        z > MIN_DEPTH_M
        and -margin <= CAM.project(p)[0, 0] < CAM.width + margin
        and -margin <= CAM.project(p)[0, 1] < CAM.height + margin
    )
    assert CAM.in_view(p, margin).tolist() == [bool(expected)]
    assert CAM.in_view(np.zeros((0, 3))).shape == (0,)
