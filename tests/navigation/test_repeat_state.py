"""Controller state of a repeat (state.csv): the smoother fed by the localization chain, queried at a fixed
rate in the gravity-aligned trunk frame o. KITTI: teach even frames 0:30:2, repeat odd frames 1:30:2;
synthetic chains for the anchoring before the first localization and for a camera offset on the vehicle."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from perception_model.frames import T_VEHICLE_LEVEL_CAMERA
from vtr.app.pipeline import repeat_command, teach_command
from vtr.app.runfiles.state_csv import SCHEMA as STATE_CSV
from vtr.app.runfiles.state_csv import read_state_csv
from vtr.cli import main
from vtr.config import Config
from vtr.errors import ConfigError
from vtr.geometry import exp_se3, inv_T, make_T
from vtr.io.trajectory import read_tum
from vtr.map import Map, TaughtPath
from vtr.navigation.chain import LocalizationChain
from vtr.navigation.localization import Localization
from vtr.navigation.repeat import RepeatStep
from vtr.navigation.repeat_state import RepeatStateEstimator, output_times
from vtr.navigation.state_view import CommandLog
from vtr.types import FrameKind, Keyframe, OdometryResult

SECTIONS = (Config().smoothing, Config().localization)  # RepeatStateEstimator.for_route's defaults

RATE_HZ = 50.0
MAX_VERTEX_OFFSET_M = 0.08  # smoothed position at a localized vertex vs the chain's pose
MAX_MEDIAN_VERTEX_OFFSET_M = 0.03
SPEED_TOLERANCE = 0.05
MAX_MEDIAN_LATERAL_M = 0.1


@pytest.fixture(scope="module")
def kitti_run(kitti_clip, tmp_path_factory):
    d = tmp_path_factory.mktemp("state")
    teach_command(kitti_clip, d / "route.vtrmap", "0:30:2", Config())
    summary = repeat_command(kitti_clip, d / "route.vtrmap", d / "out", "1:30:2", Config())
    return d, summary


def _columns(path):
    return (path / "state.csv").read_text().splitlines()[0].split(",")


def test_state_csv_layout(kitti_run):
    d, summary = kitti_run
    out = d / "out"
    assert tuple(_columns(out)) == STATE_CSV.header
    s = read_state_csv(out / "state.csv")
    t_frames, _ = read_tum(out / "trajectory_tum.txt")
    span_s = (t_frames[-1] - t_frames[0]) * 1e-9
    assert len(s) == int(np.floor(span_s * RATE_HZ + 1e-9)) + 1
    assert s.t_ns[0] == t_frames[0] and t_frames[-1] - s.t_ns[-1] < 1e9 / RATE_HZ
    assert np.all(np.abs(np.diff(s.t_ns) - 1e9 / RATE_HZ) <= 1)
    for a in (s.position, s.velocity, s.acceleration, s.yaw, s.along_track):
        assert np.all(np.isfinite(a))
    # the chain's verdict: the first keyframe is an unconfirmed place candidate (status unknown), localized from
    # the second keyframe (its confirmation) to the end; the car drives forward (direction +1 where localized)
    assert s.localized is not None and s.status is not None and s.direction is not None
    first = int(np.argmax(s.localized))
    assert first > 0 and s.localized[first:].all() and set(s.status[:first]) == {"unknown"}
    assert set(s.status[first:]) == {"localized"} and np.all(s.direction[first:] == 1)
    assert np.all(np.isfinite(s.lateral[first:])) and np.all(np.isfinite(s.vertical[first:]))
    assert np.all(np.isnan(s.lateral[:first]))
    with Map.open(d / "route.vtrmap") as m:
        ids = m.taught_path().ids
    assert set(s.trunk_id) <= set(ids.tolist())
    assert np.all(np.diff(s.along_track) > 0)  # the car drives forward along the taught path
    state = json.loads((out / "run.json").read_text())["summary"]["state"]
    assert state["rows"] == len(s) and state["rate_hz"] == RATE_HZ
    print(
        f"smoother + state output: {state['smoother_ms_per_frame']:.2f} ms/frame "
        f"(repeat {1000 * summary.seconds / summary.frames:.0f} ms/frame)"
    )


def test_state_matches_localized_poses(kitti_run):
    """At each localized vertex the smoothed position is within a few cm of the chain's pose, both in o."""
    d, _ = kitti_run
    out = d / "out"
    s = read_state_csv(out / "state.csv")
    t_frames, T_teach = read_tum(out / "trajectory_tum.txt")
    loc = np.genfromtxt(out / "localization.csv", delimiter=",", names=True, dtype=None, encoding=None)
    with Map.open(d / "route.vtrmap") as m:
        taught = m.taught_path()
        state_estimator = RepeatStateEstimator.for_route(taught, *SECTIONS, m.camera.T_vehicle_sensor)
    ids = taught.ids
    index = {int(v): i for i, v in enumerate(ids)}
    offsets = []
    for t, trunk, ok in zip(loc["t_ns"], loc["trunk_id"], loc["success"], strict=True):
        if not ok:
            continue
        T_wt, T_o_t = state_estimator.trunk_frame(index[int(trunk)])
        T_w_a = T_teach[np.flatnonzero(t_frames == t)[0]] @ state_estimator.T_sensor_vehicle
        p_chain = (T_o_t @ inv_T(T_wt) @ T_w_a)[:3, 3]
        rows = s.trunk_id == trunk
        assert s.t_ns[rows][0] <= t <= s.t_ns[rows][-1]
        p_state = np.array([np.interp(t, s.t_ns[rows], s.position[rows, i]) for i in range(3)])
        offsets.append(np.linalg.norm(p_state - p_chain))
    assert len(offsets) >= 0.9 * len(loc)
    print(
        f"smoothed vs chain at localized vertices: median {1000 * np.median(offsets):.1f} mm, "
        f"max {1000 * np.max(offsets):.1f} mm"
    )
    assert np.max(offsets) < MAX_VERTEX_OFFSET_M
    assert np.median(offsets) < MAX_MEDIAN_VERTEX_OFFSET_M


def test_speed_and_path_error(kitti_run, kitti_clip):
    d, _ = kitti_run
    s = read_state_csv(d / "out" / "state.csv")
    gt = np.loadtxt(kitti_clip / "poses.txt").reshape(-1, 3, 4)[1:30:2, :, 3]
    times = np.loadtxt(kitti_clip / "times.txt")[1:30:2]
    gt_speed = np.median(np.linalg.norm(np.diff(gt, axis=0), axis=1) / np.diff(times))
    speed = np.linalg.norm(s.velocity, axis=1)
    print(
        f"speed: state median {np.median(speed):.3f} m/s, ground truth {gt_speed:.3f} m/s; lateral error median "
        f"{1000 * np.nanmedian(np.abs(s.lateral)):.1f} mm, vertical {1000 * np.nanmedian(np.abs(s.vertical)):.1f} mm"
    )
    assert abs(np.median(speed) / gt_speed - 1) < SPEED_TOLERANCE
    assert np.all(np.abs(speed / gt_speed - 1) < 2 * SPEED_TOLERANCE)
    assert np.nanmedian(np.abs(s.lateral)) < MAX_MEDIAN_LATERAL_M
    assert np.nanmedian(np.abs(s.vertical)) < MAX_MEDIAN_LATERAL_M
    assert np.all(np.abs(s.velocity[:, 0]) > 0.95 * speed)  # along o's x: the trunk's heading
    assert np.all(np.abs(s.yaw) < 0.05)


@pytest.mark.parametrize("rate", ["0", "-5"])
def test_bad_rate_is_one_line_error(kitti_run, kitti_clip, tmp_path, rate):
    d, _ = kitti_run
    path = tmp_path / "route.vtrmap"
    path.write_bytes((d / "route.vtrmap").read_bytes())
    with Map.open(path) as m:
        runs = [r.kind for r in m.runs()]
    args = ["repeat", kitti_clip, "--map", path, "--out", tmp_path / "o", "--frames", "1:5:2", "--rate", rate]
    r = CliRunner().invoke(main, [str(a) for a in args])
    assert r.exit_code == 1 and "Traceback" not in r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vtr: error:") and "rate" in lines[0]
    with Map.open(path) as m:
        assert [r.kind for r in m.runs()] == runs  # nothing appended
    with pytest.raises(ConfigError, match="rate"):
        repeat_command(kitti_clip, path, tmp_path / "o", "1:5:2", Config(), rate_hz=float("nan"))


def test_output_times():
    t = output_times(1_000, 1_000 + 2 * 10**9, 3.0)
    assert len(t) == 7 and t[0] == 1_000 and t[-1] == 1_000 + 2 * 10**9
    assert len(output_times(0, 10**9 - 1, 1.0)) == 1
    with pytest.raises(ConfigError):
        output_times(0, 10, float("inf"))


def _chain(ids: np.ndarray, T_priv: np.ndarray) -> LocalizationChain:
    """A chain on a taught path of these ids and poses (times one second apart)."""
    return LocalizationChain(
        TaughtPath(ids, T_priv, np.arange(len(ids)) * 10**9), Config().localization, Config().smoothing
    )


def test_level_camera_frame_o():
    """Identity T_vehicle_sensor: o has z up = -y of the first camera, x along the trunk camera's z."""
    yaw = np.radians(30.0)
    c, s = np.cos(yaw), np.sin(yaw)
    R_turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # turn about the camera's y (vertical) axis
    T_priv = np.stack([np.eye(4), make_T(R_turn, [1.0, 0.0, 2.0])])
    state_estimator = RepeatStateEstimator.for_route(_chain(np.array([0, 1]), T_priv).path, *SECTIONS, np.eye(4))
    for k in range(2):
        T_wt, T_o_t = state_estimator.trunk_frame(k)
        C_world_o = T_wt[:3, :3] @ T_o_t[:3, :3].T
        assert np.allclose(C_world_o[:, 2], [0, -1, 0])
        assert np.allclose(C_world_o[:, 0], T_priv[k][:3, 2])


# ------------------------------------------------------------------------------ synthetic chains

SPEED = 10.0  # m/s along the camera's z (forward)
DT_NS = 50_000_000  # one repeat vertex every 0.05 s
OFFSET = make_T(np.eye(3), [0.3, 0.0, 0.5])  # repeat world in the teach world: 0.3 m right, 0.5 m ahead


def _synthetic_steps(n: int, failed: set[int], turn_rad_s: float = 0.0):
    """Repeat steps on a straight taught path (vertices every metre along the camera z axis); ``turn_rad_s``: the
    repeat turns at this rate about the camera's y axis (an arc off the taught path)."""
    T_priv = np.stack([make_T(np.eye(3), [0.0, 0.0, float(k)]) for k in range(n)])
    steps = []
    for j in range(n):
        t = j * DT_NS
        if turn_rad_s:
            T_w = exp_se3(np.array([0.0, turn_rad_s, 0.0, 0.0, 0.0, SPEED]) * t * 1e-9)
        else:
            T_w = make_T(np.eye(3), [0.0, 0.0, SPEED * t * 1e-9])
        T_teach = OFFSET @ T_w
        trunk = int(np.clip(np.round(T_teach[2, 3]), 0, n - 1))
        cov = np.diag([1e-8] * 3 + [1e-6] * 3)
        kf = Keyframe(j, None, T_w, cov, 100)
        odo = OdometryResult(
            t_ns=t,
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
        ok = j not in failed
        T_l_t = inv_T(T_teach) @ T_priv[trunk]
        loc = Localization(
            t_ns=t,
            leaf_id=1000 + j,
            trunk_id=trunk,
            twig_id=-1,
            branch_id=-1,
            success=ok,
            matches=50,
            inliers=50 if ok else 0,
            T_leaf_trunk=T_l_t,
            covariance=np.diag([1e-6] * 3 + [1e-4] * 3) if ok else np.full((6, 6), np.nan),
            consecutive_failures=0,
            distance_since_success_m=0.0,
        )
        ever = not failed.issuperset(range(j + 1))
        T_chain = T_teach if ever else T_w  # the chain's assumption until then
        # the chain's verdict: localized from the first success on (failures later are fewer than lost_after)
        steps.append(RepeatStep(odo, loc, 1000 + j, T_chain, localized=ever, direction=1 if ever else 0))
    return np.arange(n), T_priv, steps


@pytest.mark.parametrize("T_vehicle_sensor", [np.eye(4), T_VEHICLE_LEVEL_CAMERA @ make_T(np.eye(3), [0, -1.5, 1.0])])
def test_anchored_at_first_localization(T_vehicle_sensor):
    """The first three localizations fail: the vertices wait and are placed by the first success."""
    ids, T_priv, steps = _synthetic_steps(30, failed={0, 1, 2})
    state_estimator = RepeatStateEstimator.for_route(_chain(ids, T_priv).path, *SECTIONS, T_vehicle_sensor)
    for step in steps:
        state_estimator.add(step)
    state_estimator.finish()
    s = state_estimator.output(RATE_HZ)
    assert len(s) == int((len(steps) - 1) * DT_NS * 1e-9 * RATE_HZ) + 1
    # the waiting vertices are placed through odometry from the first success (the smoothed state is whole), but
    # only from the chain's first success on is the state localized: before it, unknown and no path error
    first = s.t_ns >= 3 * DT_NS
    assert np.all(s.localized == first) and set(s.status[~first]) == {"unknown"}
    assert np.all(np.isnan(s.lateral[~first]))
    assert np.allclose(s.lateral[first], -0.3, atol=1e-3)  # camera 0.3 m right of the taught path
    assert np.allclose(s.vertical[first], 0.0, atol=1e-3)
    assert np.allclose(np.linalg.norm(s.velocity, axis=1), SPEED, rtol=1e-3)
    assert np.allclose(s.along_track, 0.5 + SPEED * (s.t_ns - s.t_ns[0]) * 1e-9, atol=1e-3)
    assert np.allclose(s.yaw, 0.0, atol=1e-6)
    assert np.allclose(s.position[:, 1:], [[-0.3, 0.0]], atol=1e-3)


def _bits(x: object) -> object:
    """A query's answer as comparable bits: dataclasses field by field, arrays by their bytes (NaN included)."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _bits(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, np.ndarray):
        return (x.dtype.str, x.shape, x.tobytes())
    return x


def _answers(view, t_ns: int, commands: CommandLog, knots_only: bool = False) -> list[object]:
    """Every query a controller makes of a view at ``t_ns`` (an error's text where one raises); ``knots_only``: those
    that read nothing but the knots around ``t_ns`` (not the fitted acceleration, whose window reaches further back
    than a short history)."""
    queries = (
        lambda: view.window(t_ns, 3, 0.02),
        lambda: view.trajectory.joint_covariance(np.array([t_ns - 30_000_000, t_ns - 10_000_000, t_ns])),
        lambda: view.trajectory.state_at(t_ns),
    )
    if not knots_only:
        queries += (
            lambda: view.controller_state_at(t_ns, with_covariance=True),
            lambda: view.controller_state_at(t_ns, with_covariance=True, commands=commands),
            lambda: view.controller_state_at(t_ns),
            lambda: view.states(np.array([t_ns, t_ns + 7_000_000])),
        )
    out: list[object] = []
    for query in queries:
        try:
            out.append(_bits(query()))
        except Exception as err:  # noqa: BLE001 - the same error is part of the same answer
            out.append(f"{type(err).__name__}: {err}")
    return out


@pytest.mark.parametrize("T_vehicle_sensor", [np.eye(4), T_VEHICLE_LEVEL_CAMERA @ make_T(np.eye(3), [0, -1.5, 1.0])])
def test_a_view_queried_many_times_answers_as_a_fresh_one(T_vehicle_sensor):
    """A published view memoizes per knot, per segment and per trunk: queried many times (and after the estimator
    went on), it gives exactly, bit for bit, the answers of a view never queried before, at knots, between them,
    before the first and after the newest; and its window, joint covariance and state those of the view over the
    smoother's live cache (which memoizes no covariance), the next published view's likewise."""
    ids, T_priv, steps = _synthetic_steps(30, failed={0, 1}, turn_rad_s=0.3)
    est = RepeatStateEstimator.for_route(_chain(ids, T_priv).path, *SECTIONS, T_vehicle_sensor)
    history_s = 0.4
    for step in steps[:20]:
        est.add(step)
    used = est.view(history_s)
    knots = [int(t) for t in used.trajectory.times_ns]
    assert len(knots) >= 4
    times = sorted(
        {knots[0] - 5_000_000}
        | {t + d for t in knots for d in (0, -13_000_000, 17_000_000)}
        | {knots[-1] + k * 10_000_000 for k in range(1, 10)}
    )
    commands = CommandLog(np.array([knots[-1] + 5_000_000], np.int64), np.array([[0.2, -0.1, 0.0]]))
    first = {t: _answers(used, t, commands) for t in times}
    for t in times[::-1] + times:  # the memos filled in another order, then again
        assert _answers(used, t, commands) == first[t]
    for t in times:
        assert _answers(est.view(history_s), t, commands) == first[t]  # a fresh view per time: no memo
    whole = est.view()  # over the smoother's live cache, the covariances' roots never memoized
    for t in [t for t in times if t - 40_000_000 >= knots[0]]:
        assert _answers(whole, t, commands, knots_only=True) == first[t][:3]
    for step in steps[20:]:
        est.add(step)
    later, whole = est.view(history_s), est.view()
    for t in [int(t) + d for t in later.trajectory.times_ns for d in (0, 20_000_000)]:
        answers = _answers(later, t, commands)  # the next view's memos filled while the first view's are
        assert answers == _answers(est.view(history_s), t, commands)
        if t - 40_000_000 >= int(later.trajectory.times_ns[0]):
            assert answers[:3] == _answers(whole, t, commands, knots_only=True)
    for t in times:  # the estimator went on: the published view is a snapshot
        assert _answers(used, t, commands) == first[t]


@settings(max_examples=6, deadline=None)
@given(
    map_sigma_m=st.floats(0.003, 0.1),
    map_sigma_rad=st.floats(1e-4, 0.01),
    seed=st.integers(0, 2**31 - 1),
)
def test_the_map_s_part_is_split_into_what_consecutive_leaves_share_and_what_differs(map_sigma_m, map_sigma_rad, seed):
    """Each localization's covariance holds the measurements' part and the map's placement part F
    (frame_covariance), a Gauss-Markov error along the path: consecutive leaves d apart share rho = exp(-d / L) of it,
    L the taught spacing. The smoother is fed the measurements' part plus (1 - rho) F and every state adds rho F of the
    latest localization once: the state equals, mean and covariance, a run whose localizations carry the measurements'
    part plus (1 - rho) F and no map part, plus rho F. Here the taught vertices are 1 m apart and the leaves 0.5 m
    (rho = exp(-0.5)), 1 m across a failed localization (exp(-1)); the first localization shares nothing before it
    (rho = 1: all of F added at the output, the same total as feeding it)."""
    rng = np.random.default_rng(seed)
    L = np.diag(np.r_[[map_sigma_rad] * 3, [map_sigma_m] * 3]) @ (np.eye(6) + 0.3 * rng.normal(size=(6, 6)))
    F = L @ L.T  # the map's part: any covariance, correlated across axes
    failed = {4, 9}
    ids, T_priv, steps = _synthetic_steps(20, failed=failed)
    spacing_m = 1.0  # _synthetic_steps' taught vertices
    with_map, fed, rho_of = [], [], {}
    previous = None
    for j, step in enumerate(steps):
        loc = step.localization
        m = f = loc
        if loc is not None and loc.success:
            p = step.odometry.T_world_frame[:3, 3]
            rho = 1.0 if previous is None else float(np.exp(-np.linalg.norm(p - previous) / spacing_m))
            previous, rho_of[j] = p, rho
            m = dataclasses.replace(loc, covariance=loc.covariance + F, frame_covariance=F)
            f = dataclasses.replace(loc, covariance=loc.covariance + (1.0 - rho) * F)
        with_map.append(dataclasses.replace(step, localization=m))
        fed.append(dataclasses.replace(step, localization=f))
    assert np.isclose(rho_of[3], np.exp(-0.5)) and np.isclose(rho_of[5], np.exp(-1.0)) and rho_of[0] == 1.0
    plain = RepeatStateEstimator.for_route(_chain(ids, T_priv).path, *SECTIONS, np.eye(4))
    mapped = RepeatStateEstimator.for_route(_chain(ids, T_priv).path, *SECTIONS, np.eye(4))
    for a, b in zip(fed, with_map, strict=True):
        plain.add(a)
        mapped.add(b)
    for t in (0, 7 * DT_NS, 9 * DT_NS + DT_NS // 3, 19 * DT_NS, 19 * DT_NS + 40_000_000):
        p = plain.controller_state_at(t, with_covariance=True)
        m = mapped.controller_state_at(t, with_covariance=True)
        latest = max(j for j in rho_of if j * DT_NS <= t)
        F_out = mapped.view().frame_output_covariance(t, m.T_o_a)
        F_whole = dataclasses.replace(mapped.view(), vertex_frame_covariance=np.broadcast_to(F, (20, 6, 6)))
        assert np.allclose(F_out, rho_of[latest] * F_whole.frame_output_covariance(t, m.T_o_a), rtol=1e-9, atol=1e-15)
        assert np.allclose(m.position, p.position, atol=1e-9)
        assert np.allclose(m.position_covariance, p.position_covariance + F_out[:3, :3], rtol=1e-6, atol=1e-12)
        assert np.isclose(m.yaw_variance, p.yaw_variance + F_out[3, 3], rtol=1e-6, atol=1e-14)


def test_never_localized_uses_chain_assumption():
    ids, T_priv, steps = _synthetic_steps(10, failed=set(range(10)))
    state_estimator = RepeatStateEstimator.for_route(_chain(ids, T_priv).path, *SECTIONS, np.eye(4))
    for step in steps:
        state_estimator.add(step)
    state_estimator.finish()
    s = state_estimator.output(RATE_HZ)
    # the smoother runs on the chain's assumption (started at the first taught vertex), but no path error is
    # reported: the repeat never localized
    assert s.localized is not None and not s.localized.any() and np.all(np.isnan(s.lateral))
    assert np.allclose(np.linalg.norm(s.velocity, axis=1), SPEED, rtol=1e-3)
