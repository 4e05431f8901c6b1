"""The frames of a CLOUD run (docs/inputs.md, "CLOUD run folders"): WGS84 fixes to ECEF and to ENU metres about
an origin fix (exact, no flat earth) and back, the vehicle's NED heading, and the gimbal's rotation
``R_base_camera`` from its angles (roll and pitch against NED, yaw against the vehicle's heading) and back."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

# WGS84 ellipsoid
WGS84_A = 6378137.0  # semi-major axis (m)
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared
ECEF_TO_GEODETIC_ITERATIONS = 8  # fixed-point iterations; converge to < 1e-9 m near the surface

#: R_enu_ned (its own inverse)
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: R_flu_frd: vehicle FLU <- FRD
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])
#: R_gimbal_camera: gimbal FRD (x along the optical axis) <- camera optical (x right, y down, z forward)
R_GIMBAL_CAMERA = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def spatial_transform() -> Any:
    """``scipy.spatial.transform``, imported on first use (~0.3 s: not on the path of other formats)."""
    from scipy.spatial import transform

    return transform


# ---------------------------------------------------------------------------------------------
# geodesy


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> np.ndarray:
    """WGS84 latitude/longitude (deg) and ellipsoidal height (m) -> ECEF (N, 3) in metres."""
    lat, lon = np.radians(np.asarray(lat_deg, float)), np.radians(np.asarray(lon_deg, float))
    h = np.asarray(alt_m, float)
    sl = np.sin(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sl**2)  # prime vertical radius of curvature
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sl
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(p_ecef: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (N, 3) m -> WGS84 latitude (deg), longitude (deg), ellipsoidal height (m)."""
    p = np.asarray(p_ecef, float)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lon = np.arctan2(y, x)
    r = np.hypot(x, y)
    lat = np.arctan2(z, r * (1.0 - WGS84_E2))
    h = np.zeros_like(lat)
    for _ in range(ECEF_TO_GEODETIC_ITERATIONS):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        h = r / np.cos(lat) - n
        lat = np.arctan2(z, r * (1.0 - WGS84_E2 * n / (n + h)))
    return np.degrees(lat), np.degrees(lon), h


def R_enu_ecef(lat0_deg: float, lon0_deg: float) -> np.ndarray:
    """Rotation ECEF -> local ENU at the given geodetic origin."""
    lat, lon = np.radians(lat0_deg), np.radians(lon0_deg)
    sl, cl, sp, cp = np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def geodetic_to_enu(
    lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike, lat0_deg: float, lon0_deg: float, alt0_m: float
) -> np.ndarray:
    """WGS84 fixes -> ENU positions (N, 3) in metres relative to the origin fix (exact, no flat-earth)."""
    d = geodetic_to_ecef(lat_deg, lon_deg, alt_m) - geodetic_to_ecef(lat0_deg, lon0_deg, alt0_m)
    return d @ R_enu_ecef(lat0_deg, lon0_deg).T


def enu_to_geodetic(
    p_enu: np.ndarray, lat0_deg: float, lon0_deg: float, alt0_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU positions (N, 3) m relative to an origin fix -> WGS84 latitude, longitude (deg), height (m)."""
    p = geodetic_to_ecef(lat0_deg, lon0_deg, alt0_m) + np.asarray(p_enu, float) @ R_enu_ecef(lat0_deg, lon0_deg)
    return ecef_to_geodetic(p)


# ---------------------------------------------------------------------------------------------
# gimbal


def vehicle_yaw_ned(R_enu_vehicle: np.ndarray) -> np.ndarray:
    """Heading (rad, ZYX yaw of the vehicle FRD frame in NED, clockwise from north) of (..., 3, 3)."""
    R = R_ENU_NED @ np.asarray(R_enu_vehicle) @ R_FLU_FRD  # R_ned_frd (R_ENU_NED is its own inverse)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def rotation_from_gimbal_angles(
    roll: ArrayLike,
    pitch: ArrayLike,
    yaw_rel: ArrayLike,
    R_enu_vehicle: np.ndarray,
    R_vehicle_base: np.ndarray | None = None,
    R_gimbal_camera: np.ndarray = R_GIMBAL_CAMERA,
) -> np.ndarray:
    """``R_base_camera`` (N, 3, 3) from gimbal angles (rad; roll/pitch w.r.t. NED, yaw relative to the
    vehicle heading) and the vehicle attitude ``R_enu_vehicle`` (N, 3, 3) at the same times."""
    R_enu_vehicle = np.asarray(R_enu_vehicle, float).reshape(-1, 3, 3)
    psi = vehicle_yaw_ned(R_enu_vehicle) + np.asarray(yaw_rel, float)
    ang = np.stack(np.broadcast_arrays(psi, np.asarray(pitch, float), np.asarray(roll, float)), axis=-1)
    R_ned_gimbal = spatial_transform().Rotation.from_euler("ZYX", ang.reshape(-1, 3)).as_matrix()
    R_vb = np.eye(3) if R_vehicle_base is None else np.asarray(R_vehicle_base, float)
    R_vehicle_camera = np.swapaxes(R_enu_vehicle, -1, -2) @ R_ENU_NED @ R_ned_gimbal @ R_gimbal_camera
    return R_vb.T @ R_vehicle_camera


def gimbal_angles_from_rotation(
    R_base_camera: np.ndarray,
    R_enu_vehicle: np.ndarray,
    R_vehicle_base: np.ndarray | None = None,
    R_gimbal_camera: np.ndarray = R_GIMBAL_CAMERA,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of ``rotation_from_gimbal_angles``: (roll, pitch, yaw_rel) in rad, yaw wrapped to (-pi, pi]."""
    R_enu_vehicle = np.asarray(R_enu_vehicle, float).reshape(-1, 3, 3)
    R_vb = np.eye(3) if R_vehicle_base is None else np.asarray(R_vehicle_base, float)
    R_ned_gimbal = R_ENU_NED @ R_enu_vehicle @ R_vb @ np.asarray(R_base_camera, float) @ R_gimbal_camera.T
    psi, pitch, roll = spatial_transform().Rotation.from_matrix(R_ned_gimbal.reshape(-1, 3, 3)).as_euler("ZYX").T
    yaw_rel = np.angle(np.exp(1j * (psi - vehicle_yaw_ned(R_enu_vehicle))))
    return roll, pitch, yaw_rel
