import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from vtr.errors import EstimationError
from vtr.geometry import T_to_tum, check_se3, exp_se3, inv_T, log_se3, rotation_angle, skew, tum_to_T

finite = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)
twists = arrays(np.float64, 6, elements=finite).filter(lambda x: np.linalg.norm(x[:3]) < 3.0)


@given(twists)
def test_exp_log_round_trip(xi):
    np.testing.assert_allclose(log_se3(exp_se3(xi)), xi, atol=1e-8)


@given(twists, twists)
def test_inverse_composes_to_identity(a, b):
    T = exp_se3(a) @ exp_se3(b)
    np.testing.assert_allclose(inv_T(T) @ T, np.eye(4), atol=1e-10)
    np.testing.assert_allclose(inv_T(np.stack([T, T]))[1], np.linalg.inv(T), atol=1e-10)


@given(twists)
def test_tum_round_trip(xi):
    T = exp_se3(xi)
    np.testing.assert_allclose(tum_to_T(T_to_tum(T)), T, atol=1e-10)


@given(arrays(np.float64, 3, elements=finite), arrays(np.float64, 3, elements=finite))
def test_skew_is_cross_product(a, b):
    np.testing.assert_allclose(skew(a) @ b, np.cross(a, b), atol=1e-12)


@settings(max_examples=50)
@given(twists)
def test_rotation_angle_matches_twist_norm(xi):
    np.testing.assert_allclose(rotation_angle(exp_se3(xi)[:3, :3]), np.linalg.norm(xi[:3]), atol=1e-6)


def test_check_se3_rejects_bad_matrices():
    with pytest.raises(EstimationError, match="NaN"):
        check_se3(np.full((4, 4), np.nan), "pose")
    with pytest.raises(EstimationError, match="4x4"):
        check_se3(np.eye(3), "pose")
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(EstimationError, match="orthonormal"):
        check_se3(bad, "pose")
    reflect = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(EstimationError, match="det"):
        check_se3(reflect, "pose")
