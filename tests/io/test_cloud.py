"""CLOUD run folders (thesis §9.5): a synthetic run with the thesis' layout read back with units and frames."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vtr.errors import DataError
from vtr.io import open_source
from vtr.io.cloud import STREAM_FILES, CloudRun
from vtr.io.cloud_geometry import WGS84_A, WGS84_E2, enu_to_geodetic, geodetic_to_enu, gimbal_angles_from_rotation
from vtr.io.cloud_writer import CloudRunWriter

G = 9.80665  # m/s^2
T0_NS = 1_560_000_000_000_000_000  # Unix ns (2019)
DURATION_S = 100.0
DISPLACEMENT_ENU = np.array([600.0, 800.0, 30.0])  # ~1 km flight, straight and level-ish
ORIGIN = (43.7839, -79.4693, 150.0)  # lat deg, lon deg, ellipsoidal height m (near UTIAS)
RATES_HZ = {"gps": 10, "attitude": 20, "velocities": 10, "acceleration": 40, "gimbal": 10, "images": 1}
CAMERA_PITCH_DOWN = np.radians(50.0)  # thesis: camera pitched 50 deg down
GIMBAL_YAW_AMPL = np.radians(10.0)
TILT_AMPL = np.radians(4.0)  # vehicle roll/pitch oscillation
T_BASE_CAMERA_XYZ = np.array([0.10, 0.0, -0.20])  # m, camera below and ahead of the base origin
IMAGE_SIZE = (48, 64)
GPS_TOL_M = 0.01
ANGLE_TOL_RAD = 1e-6
# camera optical (x right, y down, z forward) -> base FLU, looking forward
R_BASE_CAMERA_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def times(rate_hz: float) -> np.ndarray:
    return T0_NS + np.round(np.arange(0.0, DURATION_S + 1e-9, 1.0 / rate_hz) * 1e9).astype(np.int64)


def heading() -> float:
    """ENU yaw (counter-clockwise from east) of the flight direction."""
    return float(np.arctan2(DISPLACEMENT_ENU[1], DISPLACEMENT_ENU[0]))


def R_enu_vehicle(t_ns: np.ndarray) -> np.ndarray:
    s = (t_ns - T0_NS) / 1e9
    roll = TILT_AMPL * np.sin(0.3 * s)
    pitch = TILT_AMPL * np.cos(0.2 * s)
    return Rotation.from_euler("ZYX", np.stack([np.full_like(s, heading()), pitch, roll], 1)).as_matrix()


def gimbal_yaw(t_ns: np.ndarray) -> np.ndarray:
    return GIMBAL_YAW_AMPL * np.sin(0.1 * (t_ns - T0_NS) / 1e9)


def T_base_camera(t_ns: np.ndarray) -> np.ndarray:
    R = Rotation.from_euler("ZY", np.stack([gimbal_yaw(t_ns), np.full(len(t_ns), CAMERA_PITCH_DOWN)], 1))
    T = np.tile(np.eye(4), (len(t_ns), 1, 1))
    T[:, :3, :3] = R.as_matrix() @ R_BASE_CAMERA_FORWARD
    T[:, :3, 3] = T_BASE_CAMERA_XYZ
    return T


def p_enu(t_ns: np.ndarray) -> np.ndarray:
    return np.outer((t_ns - T0_NS) / 1e9 / DURATION_S, DISPLACEMENT_ENU)


def write_run(path: Path, quat_order: str = "xyzw") -> Path:
    w = CloudRunWriter(path, quat_order=quat_order)
    t_img = times(RATES_HZ["images"])[:5]
    rng = np.random.default_rng(0)
    w.write_images(t_img, [rng.integers(0, 256, (*IMAGE_SIZE, 3), dtype=np.uint8) for _ in t_img])
    t = times(RATES_HZ["gps"])
    w.write_gps(t, *enu_to_geodetic(p_enu(t), *ORIGIN))
    t = times(RATES_HZ["attitude"])
    w.write_attitude(t, R_enu_vehicle(t))
    t = times(RATES_HZ["velocities"])
    w.write_velocities(t, np.tile(DISPLACEMENT_ENU / DURATION_S, (len(t), 1)))
    t = times(RATES_HZ["acceleration"])
    # constant velocity: the accelerometer measures gravity's reaction, +g up, in the vehicle frame
    w.write_acceleration(t, np.einsum("nji,j->ni", R_enu_vehicle(t), [0.0, 0.0, G]))
    t = times(RATES_HZ["gimbal"])
    T = T_base_camera(t)
    w.write_gimbal_state(t, T)
    w.write_gimbal_angles(t, *gimbal_angles_from_rotation(T[:, :3, :3], R_enu_vehicle(t)))
    return path


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return write_run(tmp_path_factory.mktemp("cloud") / "run_000001")


def test_layout_matches_thesis(run_dir):
    names = {p.name for p in run_dir.iterdir()}
    assert {"images", "velocities.txt", "attitude.txt", "acceleration.txt", "gps.txt", "gimbalstate.txt"} <= names
    first = (run_dir / "attitude.txt").read_text().splitlines()[0].split(",")
    assert int(first[0]) == T0_NS and len(first) == 5  # Unix-ns timestamp, then the quaternion
    run = CloudRun(run_dir)
    assert run.missing_streams() == []
    run.validate()


def test_attitude_rotates_vehicle_flu_into_enu(run_dir):
    run = CloudRun(run_dir)
    att, vel = run.attitude(), run.velocities()
    assert vel.frame == "ground ENU" and vel.unit == "m/s"
    R = att.R_enu_vehicle
    assert R.shape == (len(att.t_ns), 3, 3) and att.t_ns.dtype == np.int64
    np.testing.assert_allclose(R, R_enu_vehicle(att.t_ns), atol=1e-9)
    # forward (x of FLU) points along the ENU velocity, left (y) 90 deg counter-clockwise, up (z) up
    v = vel.xyz[0] / np.linalg.norm(vel.xyz[0])
    fwd, left, up = R[:, :, 0], R[:, :, 1], R[:, :, 2]
    fwd_heading = np.arctan2(fwd[:, 1], fwd[:, 0])
    assert np.max(np.abs(fwd_heading - np.arctan2(v[1], v[0]))) < 1e-9
    assert np.all(np.abs(fwd[:, :2] @ v[:2] / np.linalg.norm(fwd[:, :2], axis=1)) > 0.999)
    left_heading = np.arctan2(left[:, 1], left[:, 0])
    assert np.max(np.abs(np.angle(np.exp(1j * (left_heading - fwd_heading - np.pi / 2))))) < 2 * TILT_AMPL
    assert np.all(up[:, 2] > np.cos(2 * TILT_AMPL))
    # accelerometer in vehicle FLU, m/s^2: rotated into ENU it is +g up at constant velocity
    acc = run.acceleration()
    assert acc.frame == "vehicle FLU" and acc.unit == "m/s^2"
    a_enu = np.einsum("nij,nj->ni", att.at(acc.t_ns), acc.xyz)
    # (attitude is slerped between its 20 Hz samples: ~1e-6 rad of interpolation error)
    np.testing.assert_allclose(a_enu, np.tile([0.0, 0.0, G], (len(a_enu), 1)), atol=1e-4)


def test_gps_to_enu_over_a_kilometre(run_dir):
    run = CloudRun(run_dir)
    gps = run.gps()
    assert gps.origin == pytest.approx(ORIGIN, abs=1e-9)
    enu = gps.enu()
    np.testing.assert_allclose(enu[0], 0.0, atol=1e-9)
    assert np.linalg.norm(DISPLACEMENT_ENU) > 1000.0
    assert np.max(np.linalg.norm(enu - p_enu(gps.t_ns), axis=1)) < GPS_TOL_M
    # the ENU velocity stream integrates to the same displacement
    vel = run.velocities()
    integral = np.trapezoid(vel.xyz, (vel.t_ns - vel.t_ns[0]) / 1e9, axis=0)
    assert np.linalg.norm(integral - enu[-1]) < GPS_TOL_M


def test_geodetic_to_enu_closed_forms():
    # on the equator, ENU at (0, 0, 0): east = a sin(dlon), up = a (cos(dlon) - 1), exactly
    dlon = 1000.0 / WGS84_A
    enu = geodetic_to_enu(0.0, np.degrees(dlon), 0.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(enu, [WGS84_A * np.sin(dlon), 0.0, WGS84_A * (np.cos(dlon) - 1.0)], atol=1e-6)
    # along a meridian at height h: 1 km of arc is ~1 km north and drops below the tangent plane by
    # s^2 / (2 (M + h)), M the meridian radius of curvature
    lat0 = np.radians(ORIGIN[0])
    M = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * np.sin(lat0) ** 2) ** 1.5 + ORIGIN[2]
    s = 1000.0
    enu = geodetic_to_enu(ORIGIN[0] + np.degrees(s / M), ORIGIN[1], ORIGIN[2], *ORIGIN)
    np.testing.assert_allclose(enu, [0.0, s, -(s**2) / (2 * M)], atol=GPS_TOL_M)
    # a flat-earth conversion would be off by ~8 cm in height over this kilometre: this one is not
    assert abs(enu[2]) > 5 * GPS_TOL_M
    # and the inverse returns the fix
    lat, lon, h = enu_to_geodetic(np.array([[300.0, -400.0, 12.0]]), *ORIGIN)
    np.testing.assert_allclose(geodetic_to_enu(lat, lon, h, *ORIGIN), [[300.0, -400.0, 12.0]], atol=1e-6)


def test_gimbal_angles_agree_with_gimbal_state(run_dir):
    run = CloudRun(run_dir)
    gs = run.gimbal_state()
    np.testing.assert_allclose(gs.T_base_camera, T_base_camera(gs.t_ns), atol=1e-9)
    t, R = run.gimbal_rotation_from_angles()
    assert np.array_equal(t, gs.t_ns)
    dR = np.einsum("nji,njk->nik", R, gs.T_base_camera[:, :3, :3])
    assert np.max(Rotation.from_matrix(dR).magnitude()) < ANGLE_TOL_RAD
    # the raw angles themselves follow the DJI convention (degrees in the file, rad in the API):
    # pitch about -50 deg w.r.t. NED (camera down), yaw relative to the vehicle = minus the FLU yaw
    ga = run.gimbal_angles()
    assert np.all(np.abs(ga.pitch + CAMERA_PITCH_DOWN) < 2 * TILT_AMPL)
    assert np.all(np.abs(ga.yaw + gimbal_yaw(ga.t_ns)) < 2 * TILT_AMPL)
    deg = np.loadtxt(run_dir / STREAM_FILES["gimbal_angles"][0], delimiter=",")[:, 2]
    np.testing.assert_allclose(np.radians(deg), ga.pitch, atol=1e-12)


def test_reference_trajectories(run_dir):
    run = CloudRun(run_dir)
    ref = run.reference_trajectory()
    np.testing.assert_allclose(ref.T_enu_vehicle[:, :3, 3], run.gps().enu(), atol=1e-12)
    np.testing.assert_allclose(ref.T_enu_vehicle[:, :3, :3], R_enu_vehicle(ref.t_ns), atol=1e-9)
    cam = run.ground_truth()
    assert np.array_equal(cam.t_ns, run.images.t_ns)
    T_expected = np.tile(np.eye(4), (len(cam.t_ns), 1, 1))
    T_expected[:, :3, :3] = R_enu_vehicle(cam.t_ns)
    T_expected[:, :3, 3] = p_enu(cam.t_ns)
    T_expected = T_expected @ T_base_camera(cam.t_ns)
    np.testing.assert_allclose(cam.T_world_cam, T_expected, atol=GPS_TOL_M)
    # the optical axis looks down by about the camera pitch
    z_axis = cam.T_world_cam[:, :3, 2]
    assert np.all(np.abs(np.arcsin(-z_axis[:, 2]) - CAMERA_PITCH_DOWN) < 2 * TILT_AMPL)


def test_images_are_grey_with_timestamps(run_dir):
    run = CloudRun(run_dir)
    imgs = run.images
    assert len(imgs) == 5 and imgs.t_ns[0] == T0_NS
    im = imgs[-1]
    colour = cv2.imread(str(run_dir / "images" / "000004.png"), cv2.IMREAD_COLOR)
    assert im.index == 4 and im.image.shape == IMAGE_SIZE
    assert np.array_equal(im.image, cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))
    with pytest.raises(IndexError):
        imgs[5]


def test_open_source_refuses_monocular_run(run_dir):
    with pytest.raises(DataError, match=r"CLOUD runs are monocular.*stereo source.*CloudRun"):
        open_source(run_dir)


def test_wxyz_quaternion_order(tmp_path):
    path = write_run(tmp_path / "run", quat_order="wxyz")
    run = CloudRun(path, quat_order="wxyz")
    np.testing.assert_allclose(run.attitude().R_enu_vehicle, R_enu_vehicle(run.attitude().t_ns), atol=1e-9)
    with pytest.raises(DataError, match="quat_order"):
        CloudRun(path, quat_order="zyxw")


def _copy(run_dir: Path, tmp_path: Path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(run_dir, out)
    return out


def test_missing_stream(run_dir, tmp_path):
    d = _copy(run_dir, tmp_path)
    (d / "gps.txt").unlink()
    run = CloudRun(d)
    assert run.missing_streams() == ["gps"]
    run.attitude()  # other streams still read
    with pytest.raises(DataError, match=r"gps.txt: missing CLOUD gps stream"):
        run.gps()
    with pytest.raises(DataError, match=r"missing CLOUD stream\(s\): gps.txt"):
        run.validate()
    with pytest.raises(DataError, match="gps.txt"):
        run.ground_truth()


@pytest.mark.parametrize(
    ("stream", "row", "match"),
    [
        ("attitude.txt", "{t},0.1,0.2,0.3", r"attitude.txt:5: expected 5 comma-separated values"),
        ("attitude.txt", "{t},0.1,0.2,0.3,0.4", r"attitude.txt:5: quaternion norm"),
        ("gps.txt", "{t},43.7,abc,150", r"gps.txt:5: non-numeric value"),
        ("gps.txt", "{t},143.7,-79.4,150", r"gps.txt:5: latitude/longitude out of range"),
        ("velocities.txt", "12.5,1,2,3", r"velocities.txt:5: timestamp '12.5' is not an integer"),
        ("acceleration.txt", "{t0},1,2,3", r"acceleration.txt:5: timestamp .* is earlier"),
        ("gimbalstate.txt", "{t},1,2,3,nan,0,0,1", r"gimbalstate.txt:5: non-finite value"),
    ],
)
def test_malformed_rows_name_file_and_row(run_dir, tmp_path, stream, row, match):
    d = _copy(run_dir, tmp_path)
    f = d / stream
    lines = f.read_text().splitlines()
    t_prev = int(lines[3].split(",")[0])
    lines[4] = row.format(t=t_prev + 1, t0=T0_NS - 1)
    f.write_text("\n".join(lines) + "\n")
    run = CloudRun(d)
    with pytest.raises(DataError, match=match):
        run.validate()


def test_image_id_without_file(run_dir, tmp_path):
    d = _copy(run_dir, tmp_path)
    (d / "images" / "000002.png").unlink()
    with pytest.raises(DataError, match=r"imageids.txt: row 3 \(image id '000002'\): no such image"):
        _ = CloudRun(d).images
    (d / "images" / "000003.png").write_bytes(b"garbage")
    (d / "images" / "000002.png").write_bytes(b"garbage")
    with pytest.raises(DataError, match=r"000003.png: cannot decode"):
        CloudRun(d).images[3]


def test_not_a_run(tmp_path):
    with pytest.raises(DataError, match="no images/"):
        CloudRun(tmp_path)
    with pytest.raises(FileNotFoundError):
        CloudRun(tmp_path / "nope")
