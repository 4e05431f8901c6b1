import numpy as np
import pytest
from hypothesis import example, given, settings
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


@given(arrays(np.float64, (6, 6), elements=st.floats(-1.0, 1.0)), st.floats(-12.0, 0.0))
@example(np.full((6, 6), 1.97899807e-162), 0.0)  # subnormal products: no information, not a broken floor
@example(np.full((6, 6), 1e-100) + np.eye(6) * 1e-100, 0.0)  # tiny but informative
def test_usable_covariance_is_the_one_repair_rule(A, log_scale):
    """Symmetric, eigenvalues floored at MIN_EIGENVALUE_RATIO of the largest, unchanged where already fine."""
    from vtr.geometry import MIN_EIGENVALUE_RATIO, MIN_INFORMATIVE_VARIANCE, check_covariance, usable_covariance

    C = 10.0**log_scale * (A @ A.T)
    out = usable_covariance(C)
    w = np.linalg.eigvalsh(0.5 * (C + C.T))
    if w[-1] < MIN_INFORMATIVE_VARIANCE:  # no information (e.g. subnormal entries: found by hypothesis)
        assert out is None and np.array_equal(usable_covariance(C, 100.0), np.eye(6) * 100.0)
        return
    assert out is not None and np.array_equal(out, out.T)
    w_out = np.linalg.eigvalsh(out)
    assert w_out[0] >= (MIN_EIGENVALUE_RATIO - 64 * np.finfo(float).eps) * w_out[-1]  # floor, to rounding
    if w[0] > 1e-6 * w[-1]:  # well-conditioned input passes through (to rounding)
        np.testing.assert_allclose(out, C, rtol=1e-9, atol=1e-12 * w[-1])
    check_covariance(out, definite=True)  # the smoother accepts every repaired covariance


def test_covariance_validation_and_unknown_estimates():
    from vtr.errors import MapError
    from vtr.geometry import check_covariance, usable_covariance

    nan = np.eye(6)
    nan[2, 2] = np.nan
    assert usable_covariance(nan) is None
    assert np.array_equal(usable_covariance(nan, 100.0), np.eye(6) * 100.0)
    assert usable_covariance(np.eye(3)) is None
    with pytest.raises(MapError, match="positive semi-definite"):
        check_covariance(-np.eye(6), "edge", MapError)
    check_covariance(np.zeros((6, 6)), "edge", MapError)  # semi-definite: accepted by the map
    with pytest.raises(EstimationError, match="non-zero"):
        check_covariance(np.zeros((6, 6)), definite=True)  # not by the smoother
    with pytest.raises(EstimationError, match="positive definite"):
        check_covariance(np.diag([1.0, 1, 1, 1, 1, 1e-16]), definite=True)
    asym = np.eye(6)
    asym[0, 1] = 1e-3
    with pytest.raises(EstimationError, match="symmetric"):
        check_covariance(asym)


@settings(max_examples=200, deadline=None)
@given(
    axis=st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda a: np.linalg.norm(a) > 1e-3),
    angle=st.one_of(st.floats(0.0, 1e-6), st.floats(0.0, np.pi), st.floats(np.pi - 0.02, np.pi)),
)
def test_rotvec_batch_is_scipys(axis, angle):
    from scipy.spatial.transform import Rotation

    from vtr.geometry import rotvec_batch

    w = np.asarray(axis) / np.linalg.norm(axis) * angle
    R = Rotation.from_rotvec(w).as_matrix()
    got = rotvec_batch(R[None])[0]
    want = Rotation.from_matrix(R).as_rotvec()
    if angle > np.pi - 1e-6:  # a half turn: w and -w are the same rotation
        assert np.allclose(np.abs(got), np.abs(want), atol=1e-6)
    else:
        assert np.allclose(got, want, atol=1e-9)
