"""Camera trajectories ``T_world_cam`` (left rectified camera -> world ENU): camera orientation, aerial
and ground-vehicle routes with repeat offsets, and their timestamps."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ...conventions import NS_PER_S
from ...errors import ConfigError
from ...geometry import make_T
from .constants import DEFAULT_AERIAL_PITCH_RAD, DEFAULT_ALTITUDE_M, DEFAULT_GROUND_CAMERA_HEIGHT_M


def camera_rotation(heading_rad: float, pitch_down_rad: float) -> np.ndarray:
    """R_world_cam (3x3) of a camera looking along ``heading_rad`` (ENU yaw, counter-clockwise from
    east) tilted ``pitch_down_rad`` below the horizon, with no roll (image x stays horizontal)."""
    ch, sh = math.cos(heading_rad), math.sin(heading_rad)
    cp, sp = math.cos(pitch_down_rad), math.sin(pitch_down_rad)
    z = np.array([cp * ch, cp * sh, -sp])  # optical axis
    x = np.array([sh, -ch, 0.0])  # image right
    y = np.cross(z, x)  # image down
    return np.stack([x, y, z], axis=1)


def camera_pose(position_world: Sequence[float], heading_rad: float, pitch_down_rad: float) -> np.ndarray:
    """T_world_cam (4x4) of a camera at ``position_world`` (ENU, m) looking along ``heading_rad`` (ENU yaw)
    pitched ``pitch_down_rad`` below the horizon, no roll (see :func:`camera_rotation`)."""
    return make_T(camera_rotation(heading_rad, pitch_down_rad), np.asarray(position_world, float))


def _arc_path(
    segments: Sequence[tuple[float, float]], s: np.ndarray, start_xy: tuple[float, float], heading_rad: float
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) and headings (N,) at arc lengths ``s`` (m) along consecutive segments of
    (length m, curvature 1/m; positive turns left). Beyond the end the last segment continues."""
    s = np.asarray(s, float)
    xy = np.zeros((len(s), 2))
    psi = np.zeros(len(s))
    p0 = np.array(start_xy, float)
    h0 = float(heading_rad)
    s0 = 0.0
    done = np.zeros(len(s), bool)
    for i, (length, kappa) in enumerate(segments):
        last = i == len(segments) - 1
        sel = ~done & ((s <= s0 + length) | last)
        ds = s[sel] - s0
        if abs(kappa) < 1e-12:
            xy[sel] = p0 + ds[:, None] * np.array([math.cos(h0), math.sin(h0)])
            psi[sel] = h0
        else:
            h = h0 + kappa * ds
            xy[sel, 0] = p0[0] + (np.sin(h) - math.sin(h0)) / kappa
            xy[sel, 1] = p0[1] - (np.cos(h) - math.cos(h0)) / kappa
            psi[sel] = h
        done |= sel
        # advance to the segment end
        if abs(kappa) < 1e-12:
            p0 = p0 + length * np.array([math.cos(h0), math.sin(h0)])
        else:
            h1 = h0 + kappa * length
            p0 = p0 + np.array([math.sin(h1) - math.sin(h0), -(math.cos(h1) - math.cos(h0))]) / kappa
            h0 = h1
        s0 += length
    return xy, psi


def _poses_along(
    segments: Sequence[tuple[float, float]],
    spacing_m: float,
    start_offset_m: float,
    start_xy: tuple[float, float],
    heading_rad: float,
    height_m: float,
    pitch_down_rad: float,
    lateral_offset_m: float,
    vertical_offset_m: float,
    yaw_offset_rad: float,
) -> np.ndarray:
    if spacing_m <= 0:
        raise ConfigError(f"spacing_m must be positive, got {spacing_m}")
    total = sum(length for length, _ in segments)
    s = np.arange(start_offset_m, total + 1e-9, spacing_m)
    if len(s) == 0:
        raise ConfigError(f"start_offset_m {start_offset_m} is beyond the route length {total}")
    xy, psi = _arc_path(segments, s, start_xy, heading_rad)
    left = np.stack([-np.sin(psi), np.cos(psi)], axis=1)  # ENU left of the heading
    xy = xy + lateral_offset_m * left
    T = np.tile(np.eye(4), (len(s), 1, 1))
    for i in range(len(s)):
        T[i] = camera_pose([xy[i, 0], xy[i, 1], height_m + vertical_offset_m], psi[i] + yaw_offset_rad, pitch_down_rad)
    return T


def aerial_route(
    length_m: float = 100.0,
    spacing_m: float = 1.0,
    *,
    altitude_m: float = DEFAULT_ALTITUDE_M,
    pitch_down_rad: float = DEFAULT_AERIAL_PITCH_RAD,
    curvature_per_m: float = 0.0,
    start_xy: tuple[float, float] = (0.0, 0.0),
    heading_rad: float = 0.0,
    lateral_offset_m: float = 0.0,
    vertical_offset_m: float = 0.0,
    yaw_offset_rad: float = 0.0,
    start_offset_m: float = 0.0,
) -> np.ndarray:
    """Multirotor camera poses ``T_world_cam`` (N, 4, 4): left rectified camera -> world (ENU, m).

    The path starts at ``start_xy`` heading ``heading_rad`` (ENU yaw) and runs ``length_m`` along an arc
    of constant ``curvature_per_m`` (0: straight; positive turns left), sampled every ``spacing_m``
    from arc length ``start_offset_m``. The camera flies at ``altitude_m`` above the ground, looks
    along the path tangent pitched ``pitch_down_rad`` below the horizon, with no roll.
    A repeat run of the same path is offset ``lateral_offset_m`` to the left (negative: right),
    ``vertical_offset_m`` up, and yawed by ``yaw_offset_rad``.
    """
    return _poses_along(
        [(length_m, curvature_per_m)],
        spacing_m,
        start_offset_m,
        start_xy,
        heading_rad,
        altitude_m,
        pitch_down_rad,
        lateral_offset_m,
        vertical_offset_m,
        yaw_offset_rad,
    )


def drifting_aerial_route(
    length_m: float,
    spacing_m: float,
    lateral_offset_m: float,
    vertical_offset_m: float,
    ramp_m: float,
    start_offset_m: float = 0.0,
    **kwargs,
) -> np.ndarray:
    """An aerial repeat that starts on the taught path and drifts to a constant offset over ``ramp_m``
    metres (as a vehicle leaving its path does; a repeat starts where the teach started). Same
    frames as :func:`aerial_route`; only the camera centres move."""
    on_path = aerial_route(length_m, spacing_m, start_offset_m=start_offset_m, **kwargs)
    off = aerial_route(
        length_m,
        spacing_m,
        lateral_offset_m=lateral_offset_m,
        vertical_offset_m=vertical_offset_m,
        start_offset_m=start_offset_m,
        **kwargs,
    )
    along = np.arange(len(on_path)) * spacing_m
    s = np.clip(along / max(ramp_m, 1e-9), 0.0, 1.0)
    T = on_path.copy()
    T[:, :3, 3] = (1 - s)[:, None] * on_path[:, :3, 3] + s[:, None] * off[:, :3, 3]
    return T


def segmented_aerial_route(
    segments: Sequence[tuple[float, float]],
    spacing_m: float = 1.0,
    *,
    altitude_m: float = DEFAULT_ALTITUDE_M,
    pitch_down_rad: float = DEFAULT_AERIAL_PITCH_RAD,
    start_xy: tuple[float, float] = (0.0, 0.0),
    heading_rad: float = 0.0,
    camera_heading_rad: float | None = None,
    yaw_offset_rad: float = 0.0,
    lateral_offset_m: float = 0.0,
    vertical_offset_m: float = 0.0,
    ramp_m: float = 0.0,
    start_offset_m: float = 0.0,
) -> np.ndarray:
    """Multirotor camera poses ``T_world_cam`` (N, 4, 4) along consecutive ``segments`` of (length m,
    curvature 1/m; positive turns left), e.g. a path with corners, at ``altitude_m`` (ENU, m).

    The camera looks along the path tangent turned by ``yaw_offset_rad`` or, with ``camera_heading_rad``,
    along that fixed ENU heading (a gimbal), pitched ``pitch_down_rad`` below the horizon, no roll. A
    repeat is offset ``lateral_offset_m`` to the left of the path and ``vertical_offset_m`` up; with
    ``ramp_m`` > 0 it starts on the path and reaches the offsets after ``ramp_m`` metres (as
    :func:`drifting_aerial_route`).
    """
    if spacing_m <= 0:
        raise ConfigError(f"spacing_m must be positive, got {spacing_m}")
    total = sum(length for length, _ in segments)
    s = np.arange(start_offset_m, total + 1e-9, spacing_m)
    if len(s) == 0:
        raise ConfigError(f"start_offset_m {start_offset_m} is beyond the route length {total}")
    xy, psi = _arc_path(segments, s, start_xy, heading_rad)
    blend = np.clip((s - s[0]) / ramp_m, 0.0, 1.0) if ramp_m > 0 else np.ones(len(s))
    left = np.stack([-np.sin(psi), np.cos(psi)], axis=1)
    xy = xy + (lateral_offset_m * blend)[:, None] * left
    z = altitude_m + vertical_offset_m * blend
    T = np.tile(np.eye(4), (len(s), 1, 1))
    for i in range(len(s)):
        cam = camera_heading_rad if camera_heading_rad is not None else psi[i] + yaw_offset_rad
        T[i] = camera_pose([xy[i, 0], xy[i, 1], z[i]], cam, pitch_down_rad)
    return T


def turning_route(
    spacing_m: float = 0.25,
    *,
    straight_before_m: float = 10.0,
    turn_angle_rad: float = math.pi / 2,
    turn_radius_m: float = 8.0,
    straight_after_m: float = 10.0,
    camera_height_m: float = DEFAULT_GROUND_CAMERA_HEIGHT_M,
    pitch_down_rad: float = 0.0,
    start_xy: tuple[float, float] = (0.0, 0.0),
    heading_rad: float = 0.0,
    lateral_offset_m: float = 0.0,
    vertical_offset_m: float = 0.0,
    yaw_offset_rad: float = 0.0,
    start_offset_m: float = 0.0,
) -> np.ndarray:
    """Ground-vehicle camera poses ``T_world_cam`` (N, 4, 4): left rectified camera -> world (ENU, m).

    Forward-looking camera ``camera_height_m`` above the ground: straight for ``straight_before_m``,
    then a turn of ``turn_angle_rad`` (positive: left) on ``turn_radius_m``, then straight for
    ``straight_after_m``; sampled every ``spacing_m`` of arc length. Offsets as in :func:`aerial_route`.
    """
    if turn_radius_m <= 0:
        raise ConfigError(f"turn_radius_m must be positive, got {turn_radius_m}")
    kappa = math.copysign(1.0 / turn_radius_m, turn_angle_rad)
    segments = [(straight_before_m, 0.0), (abs(turn_angle_rad) * turn_radius_m, kappa), (straight_after_m, 0.0)]
    return _poses_along(
        segments,
        spacing_m,
        start_offset_m,
        start_xy,
        heading_rad,
        camera_height_m,
        pitch_down_rad,
        lateral_offset_m,
        vertical_offset_m,
        yaw_offset_rad,
    )


def route_times(T_world_cam: np.ndarray, speed_mps: float, start_ns: int = 0) -> np.ndarray:
    """int64 ns timestamps for poses travelled at constant ``speed_mps`` (camera-centre path length)."""
    if speed_mps <= 0:
        raise ConfigError(f"speed_mps must be positive, got {speed_mps}")
    p = np.asarray(T_world_cam)[:, :3, 3]
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    t = start_ns + np.round(d / speed_mps * NS_PER_S).astype(np.int64)
    if np.any(np.diff(t) <= 0):
        raise ConfigError("consecutive poses coincide: timestamps would not increase")
    return t
