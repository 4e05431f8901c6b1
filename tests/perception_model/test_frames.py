"""The controller frame o and its yaw: one convention (perception_model.frames) used by vtr alike."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from perception_model import frames
from perception_model.angles import optical_axis as constraint_axis
from perception_model.map_landmarks import camera_rotation_from_yaw, yaw_pitch_of_axis

angles = st.floats(-math.pi, math.pi, allow_nan=False)
coords = st.floats(-50.0, 50.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(angles, angles, coords, coords, coords, angles)
def test_trunk_frame_round_trip_and_trunk_has_zero_yaw(psi, psi_t, x, y, z, mount):
    p_o, yaw_o = frames.to_trunk_frame([x, y, z], psi, [1.0, -2.0, 3.0], psi_t)
    back, yaw_g = frames.from_trunk_frame(p_o, yaw_o, [1.0, -2.0, 3.0], psi_t)
    assert np.allclose(back, [x, y, z], atol=1e-9) and math.isclose(float(yaw_g), psi, abs_tol=1e-12)
    same, zero = frames.to_trunk_frame([1.0, -2.0, 3.0], psi_t, [1.0, -2.0, 3.0], psi_t)
    assert np.allclose(same, 0.0) and abs(float(zero)) < 1e-12
    # the constraint's yaw-defined axis is the mount's axis with axis yaw = vehicle yaw + mount yaw
    b = math.radians(50.0)
    assert np.allclose(frames.optical_axis(psi, b, mount), constraint_axis(frames.axis_yaw(psi, mount), b))
    R = frames.camera_rotation(psi, b, mount)
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and math.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R[:, 2], frames.optical_axis(psi, b, mount)) and abs(R[2, 0]) < 1e-12  # no roll
    # the vehicle's x axis has yaw psi
    assert math.isclose(float(frames.wrap_angle(frames.yaw_of(frames.rot_z(psi)) - psi)), 0.0, abs_tol=1e-12)


def test_vtr_controller_uses_the_same_convention():
    from vtr.state import controller

    assert controller.yaw_of is frames.yaw_of
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    for C in Rotation.random(5, random_state=rng).as_matrix():
        if abs(C[2, 0]) > 0.9:  # near-vertical x axis: yaw ill-defined
            continue
        T = controller.gravity_aligned_T_o_t(C)
        assert np.allclose(T[:3, :3], frames.gravity_aligned(C))
        assert abs(frames.yaw_of(T[:3, :3])) < 1e-12


def test_map_tools_yaw_is_the_frames_yaw_in_the_maps_gravity_frame():
    T_g_map = frames.T_g_map_from_up((0.0, -1.0, 0.0))
    assert np.allclose(T_g_map[:3, :3] @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])  # map forward = x_g
    assert np.allclose(T_g_map[:3, :3] @ [0.0, -1.0, 0.0], [0.0, 0.0, 1.0])  # map -y = up
    for yaw, pitch in ((0.0, 0.0), (0.7, 0.3), (-2.0, math.radians(50.0))):
        R_map = camera_rotation_from_yaw(yaw, pitch)[0]
        assert np.allclose(T_g_map[:3, :3] @ R_map, frames.camera_rotation(yaw, pitch), atol=1e-12)
        h, b = frames.heading_of_axis(T_g_map[:3, :3] @ R_map[:, 2])
        assert np.isclose(h, yaw) and np.isclose(b, pitch)
        assert np.allclose(yaw_pitch_of_axis(R_map[:, 2]), (yaw, pitch))


def test_up_from_a_pitched_first_camera():
    # a camera pitched 50 deg down looking east: up in its frame, and g's x is east
    from vtr.sim.synthetic import camera_rotation

    R_world_cam = camera_rotation(0.0, math.radians(50.0))
    up_map = R_world_cam.T @ [0.0, 0.0, 1.0]
    T_g_map = frames.T_g_map_from_up(up_map)
    assert np.allclose(T_g_map[:3, :3] @ R_world_cam.T, np.eye(3), atol=1e-12)


def test_the_level_camera_convention_is_one_statement():
    """The vehicle's up seen from a level camera is LEVEL_CAMERA_UP (its -y), a proper rotation maps camera z
    (forward) to vehicle x, and the map's gravity-aligned frame from that up looks along the camera's axis."""
    T = frames.T_VEHICLE_LEVEL_CAMERA
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == 1.0
    np.testing.assert_array_equal(R.T @ [0.0, 0.0, 1.0], frames.LEVEL_CAMERA_UP)
    np.testing.assert_array_equal(R @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    T_g_map = frames.T_g_map_from_up(frames.LEVEL_CAMERA_UP)
    np.testing.assert_allclose(T_g_map[:3, :3], R, atol=1e-15)  # g is the level vehicle's frame
