"""The return flight on the controller side: direction, gravity and validity in what a controller reads.

End to end on a synthetic aerial route (camera 50 degrees down, 12 m up, flown 2 m left of the taught heading forward
and back past the taught start, exact ground truth), and piece by piece on synthetic chains: the direction through
the state, the map's gravity, the status of each state (localized, dead reckoning, off route, unknown)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from perception_model.frames import LEVEL_CAMERA_UP, T_VEHICLE_LEVEL_CAMERA, T_vehicle_camera_from_up
from vtr.app.return_flight import run_return_flight
from vtr.cli import main
from vtr.config import Config
from vtr.errors import EstimationError, MapError, NotLocalizedError, VtrError
from vtr.geometry import inv_T, make_T
from vtr.map import Map, TaughtPath
from vtr.navigation.localization import Localization, LocalizationStatus
from vtr.navigation.repeat import RepeatStep
from vtr.navigation.repeat_state import RepeatStateEstimator
from vtr.sim import synthetic as syn
from vtr.state.controller import StateStatus
from vtr.types import FrameKind, Keyframe, OdometryResult

SECTIONS = (Config().smoothing, Config().localization)  # RepeatStateEstimator.for_route's defaults

# the bounds (what a controller needs of the return flight)
MIN_DIRECTION_RIGHT = 0.95
MAX_LATERAL_ERROR_M = 0.10
MAX_MEDIAN_VERTICAL_M = 0.10
MAX_P95_VERTICAL_M = 0.30
MAX_MEDIAN_VZ_MPS = 0.20

MAX_STRAIGHT_ACCEL_MPS2 = 0.3  # constant speed on a straight: truth 0
MAX_ARC_ACCEL_ERROR_MPS2 = 0.3  # on the arc: v^2 / r
MAX_ACCEL_STEP_MPS2 = 0.2  # continuous: no jump at a knot


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """tools/return_flight.py's flights (the route with its arc, forward and back 10 m past the start)."""
    return {c.name: c for c in run_return_flight(tmp_path_factory.mktemp("return"))}


@pytest.mark.parametrize("name", ["forward", "backward"])
def test_the_return_flight_reads_right(flights, name):
    """Direction, lateral (left of travel: +2 out, -2 back), vertical and vz, all against ground truth."""
    c = flights[name]
    assert c.localized_rows > 0.8 * c.rows * (0.7 if name == "backward" else 1.0), c
    assert c.direction_right >= MIN_DIRECTION_RIGHT, c
    assert abs(c.median_lateral_m - c.expected_lateral_m) <= MAX_LATERAL_ERROR_M, c
    assert abs(c.median_vertical_m) <= MAX_MEDIAN_VERTICAL_M and c.p95_abs_vertical_m <= MAX_P95_VERTICAL_M, c
    assert abs(c.median_vz_mps) <= MAX_MEDIAN_VZ_MPS, c


@pytest.mark.parametrize("name", ["forward", "backward"])
def test_an_acceleration_a_controller_can_use(flights, name):
    """Constant speed: ~0 on the straights, v^2/r on the arc, continuous (no jump at the knots)."""
    c = flights[name]
    assert c.accel_straight_median_mps2 <= MAX_STRAIGHT_ACCEL_MPS2, c
    assert abs(c.accel_arc_median_mps2 - c.accel_arc_expected_mps2) <= MAX_ARC_ACCEL_ERROR_MPS2, c
    assert c.accel_max_step_mps2 <= MAX_ACCEL_STEP_MPS2, c


def test_nothing_localized_past_the_taught_start(flights):
    """Flown back past the taught start: no success and no localized state more than 3 m past it; off_route rows."""
    c = flights["backward"]
    assert c.successes_past_start == 0 and c.localized_rows_past_start == 0, c
    assert c.off_route_rows > 0, c


# ---------------------------------------------------------------------------------------------- the gravity frame


@settings(max_examples=50, deadline=None)
@given(pitch=st.floats(-1.3, 1.3), heading=st.floats(-math.pi, math.pi))
def test_a_camera_on_a_level_vehicle_from_its_up(pitch, heading):
    """The vehicle frame from the up seen by a pitched camera: z up, x the optical axis made horizontal."""
    R_world_cam = syn.camera_rotation(heading, pitch)
    up_cam = R_world_cam.T @ np.array([0.0, 0.0, 1.0])
    T_vc = T_vehicle_camera_from_up(up_cam)
    R_world_vehicle = R_world_cam @ T_vc[:3, :3].T
    assert np.allclose(R_world_vehicle[:, 2], [0, 0, 1], atol=1e-9)
    assert np.allclose(R_world_vehicle[:, 0], [math.cos(heading), math.sin(heading), 0.0], atol=1e-9)


def test_the_level_camera_is_the_special_case():
    assert np.allclose(T_vehicle_camera_from_up(LEVEL_CAMERA_UP), T_VEHICLE_LEVEL_CAMERA)


def _camera():
    return syn.zed_camera()


def test_the_map_keeps_its_gravity(tmp_path):
    up = np.array([0.0, -math.cos(math.radians(50)), -math.sin(math.radians(50))])
    with Map.create(tmp_path / "a.vtrmap", _camera(), gravity_up=2.0 * up) as m:
        assert np.allclose(m.gravity_up, up)
    with Map.open(tmp_path / "a.vtrmap") as m:  # reopened: stored, unit length
        assert np.allclose(m.gravity_up, up)
    with Map.create(tmp_path / "b.vtrmap", _camera()) as m:
        assert m.gravity_up is None
    for bad in ([0.0, 0.0, 0.0], [1.0, math.nan, 0.0], [1.0, 2.0]):
        with pytest.raises(VtrError, match="gravity_up"):
            Map.create(tmp_path / "c.vtrmap", _camera(), gravity_up=bad)
        assert not (tmp_path / "c.vtrmap").exists()


def test_a_damaged_gravity_is_a_map_error(tmp_path):
    import sqlite3

    path = tmp_path / "a.vtrmap"
    with Map.create(path, _camera(), gravity_up=[0.0, -1.0, 0.0]):
        pass
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE meta SET value = '[0, 0, \"x\"]' WHERE key = 'gravity_up'")
    conn.close()
    with Map.open(path) as m, pytest.raises(MapError, match="gravity") as err:
        _ = m.gravity_up
    assert "\n" not in str(err.value)


def test_teach_up_is_kept_and_shown(kitti_clip, tmp_path):
    path = tmp_path / "route.vtrmap"
    r = CliRunner().invoke(
        main, ["teach", str(kitti_clip), "--map", str(path), "--frames", "0:6:2", "--up", "0,-0.6428,-0.766"]
    )
    assert r.exit_code == 0, r.output
    assert "gravity: up 0.0000,-0.6428,-0.7660" in r.output
    info = CliRunner().invoke(main, ["map", "info", str(path)])
    assert "gravity: up 0.0000,-0.6428,-0.7660 in the first teach camera" in info.output
    bad = CliRunner().invoke(
        main, ["teach", str(kitti_clip), "--map", str(tmp_path / "x.vtrmap"), "--frames", "0:6:2", "--up", "0,0,0"]
    )
    assert bad.exit_code == 1 and "--up" in bad.output and "zero length" in bad.output
    assert len(bad.output.strip().splitlines()) == 1 and not (tmp_path / "x.vtrmap").exists()
    plain = tmp_path / "plain.vtrmap"
    assert CliRunner().invoke(main, ["teach", str(kitti_clip), "--map", str(plain), "--frames", "0:6:2"]).exit_code == 0
    assert "gravity: not stored" in CliRunner().invoke(main, ["map", "info", str(plain)]).output


def test_export_in_the_map_gravity_frame(tmp_path):
    """A pitched first camera's map exported gravity-aligned: the flat synthetic ground is a horizontal plane."""
    from vtr.app.mission import render_sequence, up_in_map
    from vtr.app.pipeline import teach_command
    from vtr.map.export import export_landmarks_ply

    T = syn.aerial_route(6.0, 1.0)
    seq = render_sequence(tmp_path / "seq", syn.aerial_scene(0), T)
    teach_command(seq, tmp_path / "m.vtrmap", None, Config(), gravity_up=up_in_map(T[0]))
    import open3d as o3d

    with Map.open(tmp_path / "m.vtrmap") as m:
        export_landmarks_ply(m, tmp_path / "g.ply", gravity_aligned=True)
        export_landmarks_ply(m, tmp_path / "c.ply")
    # the field and the controller state share the map's gravity frame: each taught vehicle's position and yaw in g
    from perception_model.frames import yaw_of
    from perception_model.model import PerceptionModel
    from vtr.control.field import TaughtPathField

    with Map.open(tmp_path / "m.vtrmap") as m:
        field = TaughtPathField.from_map(m, PerceptionModel.thesis())
        est = RepeatStateEstimator.for_route(m.taught_path(), *SECTIONS, m.camera.T_vehicle_sensor, m.gravity_up)
    for k in range(len(field)):
        T_g_o = est.route.T_g_o(k)
        assert np.allclose(T_g_o[:3, 3], field.vehicle_position_g[k], atol=1e-9)
        # yaw: the rigid mount's x (the state) against each taught optical axis' heading (the field): they differ
        # only by the taught poses' own roll and pitch wobble (odometry noise, ~1e-4 rad here)
        assert abs(float(yaw_of(T_g_o[:3, :3])) - field.vehicle_yaw_g[k]) < 1e-3
    z_g = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "g.ply")).points)[:, 2]
    y_cam = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "c.ply")).points)[:, 1]
    # most landmarks lie on the ground, 12 m below the first camera: in g at z = -12, in the camera frame not flat
    assert abs(np.median(z_g) + 12.0) < 0.3 and np.percentile(np.abs(z_g + 12.0), 50) < 0.3
    assert np.std(y_cam) > 3 * np.std(z_g[np.abs(z_g + 12.0) < 1.0])


def test_euroc_knows_its_gravity(euroc_pairs, euroc_micro):
    """EuRoC's ground truth is gravity-aligned: a source with it gives the first camera's up (one without, none)."""
    from vtr.io import open_source

    with open_source(euroc_micro) as src:
        assert src.ground_truth() is None and src.gravity_up(0) is None
    with open_source(euroc_pairs) as src:
        up = src.gravity_up(0)
        gt = src.ground_truth()
    assert up is not None and gt is not None and abs(np.linalg.norm(up) - 1) < 1e-9
    # the camera looks roughly forward: up is mostly along its -y
    assert up[1] < -0.5


def test_an_explicit_up_overrides_the_map_with_a_warning(kitti_clip, tmp_path):
    from vtr.app.pipeline import repeat_command, teach_command

    path = tmp_path / "route.vtrmap"
    teach_command(kitti_clip, path, "0:12:2", Config(), gravity_up=np.array(LEVEL_CAMERA_UP))
    said: list[str] = []
    repeat_command(
        kitti_clip,
        path,
        tmp_path / "o",
        "1:12:2",
        Config(),
        gravity_up=np.array([0.0, -0.6428, -0.766]),
        warn=said.append,
        read_only_map=True,
    )
    assert len(said) == 1 and "differs from the map's gravity" in said[0] and "50.0 deg" in said[0]


# ---------------------------------------------------------------------------------------------- status and direction

DT_NS = 50_000_000  # a vertex every 0.05 s
SPEED = 10.0  # m/s


def _path(n: int) -> TaughtPath:
    """A straight taught path along the camera z axis, a vertex every metre (level camera: z forward)."""
    return TaughtPath(
        np.arange(n), np.stack([make_T(np.eye(3), [0.0, 0.0, float(k)]) for k in range(n)]), np.arange(n) * 10**9
    )


def _steps(
    path: TaughtPath,
    s_m: np.ndarray,
    t_ns: np.ndarray,
    *,
    right_m: float,
    heading_back: bool = False,
    localized=None,
    direction: int = 1,
) -> list[RepeatStep]:
    """Repeat steps at arc lengths ``s_m`` and times ``t_ns`` on :func:`_path`, ``right_m`` right of the taught
    path (camera x), every vertex localized (``localized``: the chain's verdict per step, default all)."""
    steps = []
    n = len(path)
    R = np.diag([-1.0, 1.0, -1.0]) if heading_back else np.eye(3)
    for j, (s, t) in enumerate(zip(s_m, t_ns, strict=True)):
        T_teach = make_T(R, [right_m, 0.0, float(s)])
        T_w = T_teach  # the repeat world is the teach world here
        trunk = int(np.clip(np.round(s), 0, n - 1))
        cov = np.diag([1e-8] * 3 + [1e-6] * 3)
        kf = Keyframe(j, None, T_w, cov, 100)
        odo = OdometryResult(
            t_ns=int(t),
            index=j,
            kind=FrameKind.CREATE_VERTEX,
            matches=100,
            inliers=100,
            keyframe_id=max(j - 1, 0),
            T_keyframe_frame=np.eye(4),
            T_world_frame=T_w,
            covariance=cov if j else np.zeros((6, 6)),
            new_keyframe=kf,
        )
        ok = True if localized is None else bool(localized[j])
        loc = Localization(
            t_ns=int(t),
            leaf_id=1000 + j,
            trunk_id=trunk,
            twig_id=-1,
            branch_id=-1,
            success=ok,
            matches=50,
            inliers=50,
            T_leaf_trunk=inv_T(T_teach) @ path.T_world_vertex[trunk],
            covariance=np.diag([1e-6] * 3 + [1e-4] * 3),
            consecutive_failures=0,
            distance_since_success_m=0.0,
        )
        steps.append(RepeatStep(odo, loc, 1000 + j, T_teach, localized=ok, direction=direction))
    return steps


def _estimator(path: TaughtPath, steps: list[RepeatStep]) -> RepeatStateEstimator:
    est = RepeatStateEstimator.for_route(path, *SECTIONS, np.eye(4))
    for step in steps:
        est.add(step)
    est.finish()
    return est


def test_backward_lateral_is_left_of_travel():
    """0.3 m right of the taught path (camera x), flown back with the camera as taught: left of travel, +0.3."""
    path = _path(30)
    s = 25.0 - SPEED * np.arange(30) * DT_NS * 1e-9
    est = _estimator(path, _steps(path, s, np.arange(30) * DT_NS, right_m=0.3, direction=-1))
    table = est.output(50.0)
    assert table.direction is not None and np.all(table.direction == -1)
    assert np.allclose(table.lateral, 0.3, atol=1e-3)
    assert np.allclose(table.along_track, 25.0 - SPEED * table.t_ns * 1e-9, atol=1e-3)  # the taught arc length
    cs = est.controller_state_at(int(table.t_ns[10]))
    assert cs.direction == -1 and cs.status == StateStatus.LOCALIZED and cs.localized
    fwd = _estimator(
        path, _steps(path, 5.0 + SPEED * np.arange(30) * DT_NS * 1e-9, np.arange(30) * DT_NS, right_m=0.3)
    ).output(50.0)
    assert np.allclose(fwd.lateral, -0.3, atol=1e-3)


def test_a_pause_is_not_localized():
    """Frames for 1 s, then none for 60 s: the states across the pause are unknown, not interpolated as localized."""
    path = _path(60)
    t = np.r_[np.arange(20) * DT_NS, 60 * 10**9 + np.arange(20) * DT_NS]
    s = 2.0 + np.r_[np.arange(20), 20 + np.arange(20)] * SPEED * DT_NS * 1e-9
    est = _estimator(path, _steps(path, s, t, right_m=0.0))
    table = est.states(np.array([5 * DT_NS, 30 * 10**9, 60 * 10**9 + 5 * DT_NS]))
    assert table.status is not None and table.status.tolist() == ["localized", "unknown", "localized"]
    assert np.isnan(table.lateral[1]) and not table.localized[1]
    assert est.pauses_s == [pytest.approx(60.0 - 19 * DT_NS * 1e-9)]  # a new smoother segment after it
    rows = est.output(50.0)
    assert rows.status is not None and not rows.localized[(rows.t_ns > 2 * 10**9) & (rows.t_ns < 59 * 10**9)].any()


def test_a_pause_longer_than_any_prior_can_bridge():
    """10^5 s without frames: no solver failure (no motion factor spans it), both sides localized."""
    path = _path(60)
    t = np.r_[np.arange(20) * DT_NS, 10**14 + np.arange(20) * DT_NS]
    s = 2.0 + np.r_[np.arange(20), 20 + np.arange(20)] * SPEED * DT_NS * 1e-9
    est = _estimator(path, _steps(path, s, t, right_m=0.1))
    table = est.states(np.array([5 * DT_NS, 10**14 + 5 * DT_NS]))
    assert table.status is not None and table.status.tolist() == ["localized", "localized"]
    assert np.allclose(table.lateral, -0.1, atol=1e-3)


def test_past_the_end_is_off_route():
    """A repeat that flies on 8 m past the taught end: localized on the route, off_route beyond 3 m past the end."""
    path = _path(10)  # ends at 9 m
    s = 4.0 + SPEED * np.arange(26) * DT_NS * 1e-9  # 4 m .. 16.5 m
    est = _estimator(path, _steps(path, s, np.arange(26) * DT_NS, right_m=0.0))
    table = est.output(50.0)
    s_rows = 4.0 + SPEED * table.t_ns * 1e-9
    assert table.status is not None
    assert set(table.status[s_rows < 11.9]) == {"localized"}
    assert set(table.status[s_rows > 12.1]) == {"off_route"} and not table.localized[s_rows > 12.1].any()


def test_dead_reckoning_after_the_chain_loses_it():
    path = _path(30)
    ok = np.r_[np.ones(10, bool), np.zeros(10, bool)]
    s = 2.0 + SPEED * np.arange(20) * DT_NS * 1e-9
    est = _estimator(path, _steps(path, s, np.arange(20) * DT_NS, right_m=0.0, localized=ok))
    table = est.states(np.array([5 * DT_NS, 15 * DT_NS]))
    assert table.status is not None and table.status.tolist() == ["localized", "dead_reckoning"]


def test_before_the_first_localization_a_typed_error():
    path = _path(10)
    est = RepeatStateEstimator.for_route(path, *SECTIONS, np.eye(4))
    with pytest.raises(NotLocalizedError):
        est.controller_state_at(0)
    for step in _steps(path, np.arange(3) * 0.5, np.arange(3) * DT_NS, right_m=0.0, localized=[False] * 3):
        est.add(step)
    with pytest.raises(NotLocalizedError) as err:  # the vertices wait for a localization: no state yet
        est.controller_state_at(DT_NS)
    assert isinstance(err.value, EstimationError) and isinstance(err.value, VtrError)
    assert est.states(np.zeros(0, np.int64)).status is not None


def test_the_state_in_the_map_gravity_frame():
    """At a taught vertex the state's (p, psi) in g is that vertex's position and heading in g."""
    path = _path(30)
    s = 2.0 + SPEED * np.arange(30) * DT_NS * 1e-9
    est = _estimator(path, _steps(path, s, np.arange(30) * DT_NS, right_m=0.0))
    t = int(np.flatnonzero(np.isclose(s, 7.0))[0]) * DT_NS
    cs = est.controller_state_at(t)
    p_g, psi_g = cs.in_map_gravity_frame()
    # level first camera: g has x = camera z, y = -camera x, z = -camera y, so the vertex at 7 m is at (7, 0, 0)
    assert np.allclose(p_g, [7.0, 0.0, 0.0], atol=1e-3) and abs(psi_g) < 1e-6
    with pytest.raises(EstimationError):
        type(cs)(
            t_ns=0, position=np.zeros(3), velocity=np.zeros(3), acceleration=np.zeros(3), yaw=0.0, T_o_a=np.eye(4)
        ).in_map_gravity_frame()


def test_the_chain_decides_the_direction_with_its_first_candidate():
    """A place candidate already carries the direction of the repeat's motion (not a default +1)."""
    from vtr.navigation.chain import Candidate, LocalizationChain

    path = _path(20)
    chain = LocalizationChain(path, Config().localization, Config().smoothing)
    assert chain.state.direction == 0
    for j, s in enumerate((12.0, 11.0)):  # flown backward, camera as taught
        T = make_T(np.eye(3), [0.0, 0.0, s])
        cand = Candidate(j, T, int(s), inv_T(T) @ path.T_world_vertex[int(s)], np.eye(6) * 1e-4)
        chain.failed(T, int(s), lost=True, candidate=cand)
    assert chain.state.direction == -1
    assert not chain.localized
    assert LocalizationStatus.UNCONFIRMED.value == "unconfirmed"
