"""Parallax and view angles (thesis eqs. 7.3-7.4): known values, broadcasting, properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from perception_model.angles import (
    angle_between,
    angle_gradient,
    optical_axis,
    optical_axis_yaw_derivative,
    parallax_angle,
    view_angle,
)
from perception_model.errors import GeometryError

coord = st.floats(-50.0, 50.0, allow_nan=False, allow_infinity=False)
vec = st.tuples(coord, coord, coord).map(np.array)
MIN_LEN = 1e-3  # vectors shorter than this are skipped in property tests (direction ill-conditioned)


def _rotation(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = np.array(q) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


quat = st.tuples(*(st.floats(-1.0, 1.0) for _ in range(4))).filter(lambda q: np.linalg.norm(q) > 0.1)


def test_known_parallax_and_view_values():
    # landmark 10 m straight below the taught camera; current camera 10 m to the side -> 45 deg
    assert parallax_angle([0, 0, -10], [10, 0, 0]) == pytest.approx(math.pi / 4)
    # current camera looking along +x, landmark at 45 deg to the left in the horizontal plane
    assert view_angle([5, 5, 0], [0, 0, 0], [1, 0, 0]) == pytest.approx(math.pi / 4)
    # the view angle uses the direction camera -> landmark (p_is - p_ao)
    assert view_angle([0, 0, -10], [0, 0, 0], [0, 0, -1]) == pytest.approx(0.0)
    assert view_angle([0, 0, -10], [0, 0, 0], [0, 0, 1]) == pytest.approx(math.pi)


def test_small_angle_accuracy():
    # alpha = atan(eps / R) exactly; atan2 form keeps full relative precision at tiny angles
    for eps in (1e-3, 1e-6, 1e-9):
        a = parallax_angle([0.0, 0.0, -20.0], [eps, 0.0, 0.0])
        assert a == pytest.approx(math.atan(eps / 20.0), rel=1e-12)


def test_broadcast_landmarks_against_horizon():
    rng = np.random.default_rng(0)
    lm = rng.normal(size=(7, 3)) * 10
    cams = rng.normal(size=(4, 3))
    z = optical_axis(rng.uniform(-3, 3, 4))
    a = parallax_angle(lm[None, :, :], cams[:, None, :])
    t = view_angle(lm[None, :, :], cams[:, None, :], z[:, None, :])
    assert a.shape == t.shape == (4, 7)
    for i in range(4):
        for j in range(7):
            assert a[i, j] == pytest.approx(float(parallax_angle(lm[j], cams[i])), abs=1e-14)
            assert t[i, j] == pytest.approx(float(view_angle(lm[j], cams[i], z[i])), abs=1e-14)


def test_degenerate_vectors_nan_or_raise():
    out = parallax_angle([[1.0, 0, 0], [0, 0, 0]], [0.5, 0, 0])
    assert np.isfinite(out[0]) and np.isnan(out[1])
    assert np.isnan(view_angle([1.0, 2, 3], [1.0, 2, 3], [1, 0, 0]))  # camera at the landmark
    assert np.isnan(view_angle([1.0, 2, 3], [0, 0, 0], [0, 0, 0]))  # zero optical axis
    with pytest.raises(GeometryError, match="index"):
        parallax_angle([[1.0, 0, 0], [0, 0, 0]], [0.5, 0, 0], on_degenerate="raise")
    with pytest.raises(GeometryError, match="shape"):
        angle_between([1.0, 2.0], [1.0, 2.0])


@settings(max_examples=150, deadline=None)
@given(p_is=vec, p_ao=vec, z=vec, q=quat)
def test_invariant_under_rotation_of_the_scene(p_is, p_ao, z, q):
    if min(np.linalg.norm(p_is), np.linalg.norm(p_is - p_ao), np.linalg.norm(z)) < MIN_LEN:
        return
    r = _rotation(q)
    a0, t0 = parallax_angle(p_is, p_ao), view_angle(p_is, p_ao, z)
    a1, t1 = parallax_angle(r @ p_is, r @ p_ao), view_angle(r @ p_is, r @ p_ao, r @ z)
    assert a1 == pytest.approx(a0, abs=1e-9)
    assert t1 == pytest.approx(t0, abs=1e-9)


@settings(max_examples=150, deadline=None)
@given(p_is=vec, p_ao=vec, z=vec)
def test_angles_in_zero_pi(p_is, p_ao, z):
    if min(np.linalg.norm(p_is), np.linalg.norm(p_is - p_ao), np.linalg.norm(z)) < MIN_LEN:
        return
    for ang in (parallax_angle(p_is, p_ao), view_angle(p_is, p_ao, z)):
        assert 0.0 <= ang <= math.pi


@settings(max_examples=100, deadline=None)
@given(p_is=vec, t=st.floats(0.0, 10.0))
def test_zero_parallax_at_taught_camera_and_along_its_ray(p_is, t):
    if np.linalg.norm(p_is) < MIN_LEN:
        return
    assert parallax_angle(p_is, np.zeros(3)) == 0.0
    # moving away from the landmark along the ray through the taught camera keeps alpha = 0
    assert parallax_angle(p_is, -t * p_is) == pytest.approx(0.0, abs=1e-7)


@settings(max_examples=100, deadline=None)
@given(p_is=vec, p_ao=vec)
def test_triangle_angles_sum_to_pi(p_is, p_ao):
    # angles of the triangle (taught camera s, current camera a, landmark i) sum to pi
    sides = (np.linalg.norm(p_is), np.linalg.norm(p_ao), np.linalg.norm(p_is - p_ao))
    if min(sides) < 0.1:
        return
    at_i = parallax_angle(p_is, p_ao)
    at_s = float(angle_between(p_is, p_ao))
    at_a = float(angle_between(-p_ao, p_is - p_ao))
    assert at_i + at_s + at_a == pytest.approx(math.pi, abs=1e-8)


@settings(max_examples=100, deadline=None)
@given(p_is=vec, p_ao=vec, yaw=st.floats(-math.pi, math.pi))
def test_parallax_does_not_depend_on_orientation_view_does(p_is, p_ao, yaw):
    if min(np.linalg.norm(p_is), np.linalg.norm(p_is - p_ao)) < MIN_LEN:
        return
    # alpha takes no axis at all; the view angle of the axis pointing at the landmark is 0
    assert view_angle(p_is, p_ao, p_is - p_ao) == pytest.approx(0.0, abs=1e-7)
    assert 0.0 <= view_angle(p_is, p_ao, optical_axis(yaw)) <= math.pi


def test_optical_axis_and_derivative():
    beta = math.radians(50.0)
    yaw = np.linspace(-3, 3, 13)
    z = optical_axis(yaw, beta)
    assert np.allclose(np.linalg.norm(z, axis=-1), 1.0)
    assert np.allclose(z[:, 2], -math.sin(beta))
    assert np.allclose(z[6], [math.cos(beta), 0.0, -math.sin(beta)])  # yaw 0 looks along +x
    h = 1e-6
    fd = (optical_axis(yaw + h, beta) - optical_axis(yaw - h, beta)) / (2 * h)
    assert np.allclose(optical_axis_yaw_derivative(yaw, beta), fd, atol=1e-9)


def test_angle_gradient_matches_finite_differences():
    rng = np.random.default_rng(3)
    for _ in range(20):
        u, v = rng.normal(size=3), rng.normal(size=3) * 5
        g = angle_gradient(u, v)
        h = 1e-6
        fd = np.array([(angle_between(u, v + h * e) - angle_between(u, v - h * e)) / (2 * h) for e in np.eye(3)])
        assert np.allclose(g, fd, rtol=1e-6, atol=1e-9)
    # cone point: zero subgradient; zero-length input: NaN
    assert np.all(angle_gradient([1.0, 0, 0], [2.0, 0, 0]) == 0.0)
    assert np.all(np.isnan(angle_gradient([1.0, 0, 0], [0.0, 0, 0])))
