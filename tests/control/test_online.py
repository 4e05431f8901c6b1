"""One route online (vtr.control.online.OnlineRepeat): a real camera thread and a real control thread on the KITTI clip,
immutable views (no torn read), the map never written, typed errors before the first localization; the joint
covariance of a window of outputs against the marginals of single queries."""

from __future__ import annotations

import hashlib
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from perception_model.model import PerceptionModel
from vtr.app.pipeline import teach_command
from vtr.config import Config, SmoothingConfig
from vtr.control.online import OnlineRepeat
from vtr.errors import EstimationError, NotLocalizedError
from vtr.geometry import make_T
from vtr.io import open_source
from vtr.map import Map
from vtr.state.smoothing import TrajectorySmoother

CONTROL_PERIOD_S = 0.01  # the control thread at 100 Hz
CAMERA_PERIOD_S = 0.1  # the camera at 10 Hz (fed as fast as the feeder can below that)


@pytest.fixture(scope="module")
def taught(kitti_clip, tmp_path_factory):
    path = tmp_path_factory.mktemp("online") / "route.vtrmap"
    teach_command(kitti_clip, path, "0:40:2", Config())
    return path


def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_a_camera_thread_and_a_control_thread(taught, kitti_clip):
    """The control thread reads at 100 Hz while frames arrive: only NotLocalizedError before the first localization,
    then states, windows and constraints; every view it reads is one the feeder finished (no torn read)."""
    before = _digest(taught)
    with Map.open(taught) as m:
        runs_before = len(m.runs())
    with open_source(kitti_clip) as src:
        frames = [src[i] for i in range(1, 40, 2)]
    finished: dict[int, tuple] = {}  # per frame time, what the feeder published after it
    seen: list[tuple] = []
    errors: list[str] = []
    not_localized_after: list[int] = []
    done = threading.Event()

    def signature(view) -> tuple:
        return (
            view.last_frame_t_ns,
            view.trajectory.last_time_ns,
            len(view.vertex_t_ns),
            view.trajectory.n,
            int(view.vertex_trunk[-1]) if len(view.vertex_trunk) else None,
        )

    with OnlineRepeat(taught, model=PerceptionModel.thesis()) as live:

        def control() -> None:
            while not done.is_set():
                view = live.view
                seen.append(signature(view))
                t = view.last_frame_t_ns
                try:
                    if t is None:
                        raise NotLocalizedError("no frame yet")
                    s = live.state(t)
                    w = live.window(t, 3, 0.02)
                    assert np.all(np.isfinite(w.covariance)) and s.position_covariance is not None
                    p_g, psi_g = s.in_map_gravity_frame()
                    live.constraint(p_g[None] + np.arange(5)[:, None] * [1.0, 0.0, 0.0], np.full(5, psi_g))
                except NotLocalizedError:
                    if live.localized:
                        not_localized_after.append(t or -1)
                except Exception as err:  # noqa: BLE001 - the test reports any
                    errors.append(repr(err))
                time.sleep(CONTROL_PERIOD_S)

        thread = threading.Thread(target=control)
        thread.start()
        try:
            for f in frames:
                step = live.feed(f)
                finished[step.odometry.t_ns] = signature(live.view)
                time.sleep(CAMERA_PERIOD_S / 4)
        finally:
            done.set()
            thread.join()
        assert live.localized
        state = live.state(frames[-1].t_ns)
        assert state.status.value == "localized" and state.direction == 1
    assert errors == [] and not_localized_after == []
    assert len(seen) > len(frames)
    published = {None: (None, None, 0, 0, None), **finished}
    assert all(sig == published[sig[0]] for sig in seen), "a tick read a view the feeder had not finished"
    assert _digest(taught) == before  # never written
    with Map.open(taught) as m:
        assert len(m.runs()) == runs_before


def test_before_the_first_frame_every_query_is_typed(taught):
    with OnlineRepeat(taught) as live:
        for query in (lambda: live.state(0), lambda: live.window(0, 3, 0.02)):
            with pytest.raises(NotLocalizedError):
                query()
        with pytest.raises(EstimationError, match="perception model"):
            live.constraint(np.zeros((1, 3)), np.zeros(1))
    with pytest.raises(EstimationError, match="closed"):
        live.feed(None)  # type: ignore[arg-type]


def test_bad_arguments_are_one_line_errors(taught):
    with pytest.raises(EstimationError, match="history_s"):
        OnlineRepeat(taught, history_s=0.0)
    with OnlineRepeat(taught) as live:
        for n, dt in ((0, 0.02), (3, 0.0), (3, float("nan"))):
            with pytest.raises(EstimationError):
                live.window(0, n, dt)


# ---------------------------------------------------------------------------------------------- joint covariance


def _smoother(n: int = 12) -> TrajectorySmoother:
    """Knots 0.1 s apart on a gentle curve, absolute poses every third knot, odometry in between."""
    sm = TrajectorySmoother(SmoothingConfig())
    prev = None
    for k in range(n):
        yaw = 0.05 * k
        T = make_T(
            np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]),
            [k * 0.5, 0.02 * k**2, 0.0],
        )
        kw = {}
        if prev is not None:
            kw.update(T_prev_cur=np.linalg.inv(prev) @ T, relative_covariance=np.diag([1e-6] * 3 + [1e-4] * 3))
        if k % 3 == 0:
            kw.update(T_world_sensor=T, covariance=np.diag([1e-5] * 3 + [1e-3] * 3))
        sm.add_knot(k * 100_000_000, **kw)
        prev = T
    return sm


@settings(max_examples=30, deadline=None)
@given(times=st.lists(st.integers(0, 1_150_000_000), min_size=1, max_size=4))
def test_joint_covariance_blocks_are_the_marginals(times):
    sm = _smoother()
    traj = sm.snapshot()
    t = np.array(times, np.int64)
    J = traj.joint_covariance(t)
    assert J.shape == (12 * len(t), 12 * len(t)) and np.allclose(J, J.T)
    for r, tr in enumerate(t):
        marg = sm.state_at(int(tr)).covariance
        assert np.allclose(J[12 * r : 12 * r + 12, 12 * r : 12 * r + 12], marg, rtol=1e-6, atol=1e-12)
    assert np.min(np.linalg.eigvalsh(J)) > -1e-9 * np.max(np.abs(J))


def test_a_snapshot_answers_as_the_smoother_and_stays_put():
    sm = _smoother(8)
    snap = sm.snapshot(since_ns=350_000_000)
    assert snap.first_time_ns == 300_000_000
    a = snap.state_at(500_000_000)
    b = sm.state_at(500_000_000)
    assert np.allclose(a.pose, b.pose) and np.allclose(a.covariance, b.covariance)
    sm.add_knot(
        900_000_000, T_prev_cur=make_T(np.eye(3), [0.5, 0, 0]), relative_covariance=np.diag([1e-6] * 3 + [1e-4] * 3)
    )
    assert snap.last_time_ns == 700_000_000  # the copy does not see the new knot
    with pytest.raises(EstimationError):
        snap.state_at(200_000_000)  # before the copy


# ---------------------------------------------------------------------------------------------- commands in


@settings(max_examples=50, deadline=None)
@given(
    times=st.lists(st.integers(0, 400), min_size=1, max_size=5, unique=True),
    acc=st.lists(st.floats(-5, 5), min_size=15, max_size=15),
    t1=st.integers(0, 600),
)
def test_the_command_log_integrates_a_zero_order_hold(times, acc, t1):
    from vtr.navigation.repeat_state import CommandLog

    t = np.sort(np.array(times, np.int64)) * 1_000_000
    a = np.array(acc).reshape(5, 3)[: len(t)]
    log = CommandLog(t, a)
    t0_ns, t1_ns = 50_000_000, t1 * 1_000_000
    dp, dv, now = log.integrate(t0_ns, t1_ns)
    # numerically: a(tau) held piecewise, integrated on a 0.1 ms grid
    grid = np.arange(t0_ns, max(t1_ns, t0_ns), 100_000)
    j = np.searchsorted(t, grid, side="right") - 1
    a_grid = np.where((j >= 0)[:, None], a[np.maximum(j, 0)], 0.0)
    dt = 1e-4
    assert np.allclose(dv, a_grid.sum(axis=0) * dt, atol=1e-9)
    assert np.allclose(dp, (a_grid * ((t1_ns - grid - 50_000) / 1e9)[:, None]).sum(axis=0) * dt, atol=1e-6)
    k = np.searchsorted(t, t1_ns, side="right") - 1
    assert np.allclose(now, a[k] if k >= 0 else 0.0)


@settings(max_examples=50, deadline=None)
@given(
    times=st.lists(st.integers(0, 400), min_size=1, max_size=5, unique=True),
    acc=st.lists(st.floats(-5, 5), min_size=15, max_size=15),
    t0=st.integers(-50, 600),
    t1=st.integers(-50, 600),
)
def test_the_commanded_motion_is_what_integrate_differences(times, acc, t0, t1):
    from vtr.navigation.repeat_state import CommandLog

    t = np.sort(np.array(times, np.int64)) * 1_000_000
    log = CommandLog(t, np.array(acc).reshape(5, 3)[: len(t)])
    t0_ns, t1_ns = sorted((t0 * 1_000_000, t1 * 1_000_000))
    p0, v0, _ = log.motion(t0_ns)
    p1, v1, a1 = log.motion(t1_ns)
    dp, dv, a = log.integrate(t0_ns, t1_ns)
    assert np.allclose(p1 - p0 - v0 * (t1_ns - t0_ns) / 1e9, dp, atol=1e-9)
    assert np.allclose(v1 - v0, dv, atol=1e-9) and np.allclose(a1, a)
    assert np.allclose(log.motion(int(t[0]) - 1), 0.0)  # at rest before the first command
    # and motion itself (integrate is its difference): the held accelerations integrated twice on a 0.1 ms grid
    grid = np.arange(0, max(t1_ns, 0), 100_000)
    j = np.searchsorted(t, grid, side="right") - 1
    a_grid = np.where((j >= 0)[:, None], log.acceleration_g[np.maximum(j, 0)], 0.0)
    assert np.allclose(p1, (a_grid * ((t1_ns - grid - 50_000) / 1e9)[:, None]).sum(axis=0) * 1e-4, atol=1e-6)
    assert np.allclose(v1, a_grid.sum(axis=0) * 1e-4, atol=1e-9)


def test_commands_move_the_extrapolation(taught, kitti_clip):
    """After the newest keyframe the state follows the commanded acceleration (eq. 8.15), not constant velocity."""
    with open_source(kitti_clip) as src:
        frames = [src[i] for i in range(1, 16, 2)]
    with OnlineRepeat(taught) as live:
        for f in frames:
            live.feed(f)
        t_knot = live.view.trajectory.last_time_ns
        assert t_knot is not None
        t = t_knot + 300_000_000
        plain = live.state(t, with_covariance=False)
        a_g = np.array([1.0, -0.5, 0.2])
        live.command(t_knot, a_g)
        moved = live.state(t, with_covariance=False)
        C_o_g = plain.T_g_o[:3, :3].T
        assert np.allclose(moved.position - plain.position, C_o_g @ a_g * 0.5 * 0.3**2, atol=1e-9)
        assert np.allclose(moved.velocity - plain.velocity, C_o_g @ a_g * 0.3, atol=1e-9)
        assert np.allclose(moved.acceleration, C_o_g @ a_g)
        # the window extrapolates as the state does: the commands' positions after the knot, the knots' before
        w = live.window(t, 20, 0.02)
        after = w.t_ns > t_knot
        assert after.sum() == 15 and not after.all()
        for tj, p, status in zip(w.t_ns, w.position, w.status, strict=True):
            s_j = live.state(int(tj), with_covariance=False)
            assert np.allclose(p, s_j.position, atol=1e-9) and str(status) == str(s_j.status)
        assert np.allclose(w.position[-1] - plain.position, C_o_g @ a_g * 0.5 * 0.3**2, atol=1e-9)
        with pytest.raises(EstimationError, match="not after"):
            live.command(t_knot, a_g)
        with pytest.raises(EstimationError, match="finite"):
            live.command(t_knot + 1, [np.nan, 0, 0])


# ---------------------------------------------------------------------------------------------- calibration

NEES_3DOF_MEDIAN = 2.366  # median of chi-square with 3 degrees of freedom
NEES_3DOF_99 = 11.345  # its 99 % quantile


def _position_nees(taught, kitti_clip, ticks: int = 1, last: int = 40) -> np.ndarray:
    """NEES of the online state's position (in o, relative to the trunk) at each odd frame's time before ``last``
    (None: the whole clip) and, with ``ticks`` > 1, at the control ticks after it (``CONTROL_PERIOD_S`` apart: what a
    controller reads until the next camera frame at 10 Hz) against KITTI's ground truth (every frame, constant-twist
    between them) relative to the true trunk."""
    from vtr.geometry import exp_se3, inv_T, log_se3

    with open_source(kitti_clip) as src:
        gt = src.ground_truth()
        frames = [src[i] for i in range(1, len(src) if last is None else last, 2)]
    assert gt is not None
    with Map.open(taught) as m:
        teach_t = dict(zip(m.taught_path().ids.tolist(), m.taught_path().t_ns.tolist(), strict=True))

    def truth_at(t: int) -> np.ndarray:
        j = int(np.clip(np.searchsorted(gt.t_ns, t, side="right") - 1, 0, len(gt.t_ns) - 2))
        a = (t - gt.t_ns[j]) / (gt.t_ns[j + 1] - gt.t_ns[j])
        return gt.T_world_cam[j] @ exp_se3(a * log_se3(inv_T(gt.T_world_cam[j]) @ gt.T_world_cam[j + 1]))

    out = []
    with OnlineRepeat(taught) as live:
        for f in frames:
            live.feed(f)
            if not live.localized:
                continue
            v = live.view
            for j in range(ticks):
                t = int(f.t_ns) + int(round(j * CONTROL_PERIOD_S * 1e9))
                s = live.state(t)
                k = int(v.trunk_index_at(np.array([t]))[0])
                T_trunk = gt.T_world_cam[int(np.argmin(np.abs(gt.t_ns - teach_t[int(v.route.path.ids[k])])))]
                T_rel = inv_T(T_trunk) @ truth_at(t)
                T_sv = v.route.T_sensor_vehicle
                p_true = (v.route.trunk(k)[0] @ inv_T(T_sv) @ T_rel @ T_sv)[:3, 3]
                e = s.position - p_true
                out.append(float(e @ np.linalg.solve(s.position_covariance, e)))
    return np.array(out)


def test_the_map_s_placement_is_added_to_every_state_and_shared_by_a_window(taught, kitti_clip):
    """The map's placement part of the latest localization (shared in part by consecutive leaves, which the smoother
    averages as independent) is added to the state's covariance, and to every block of a window (one error of the
    frame o)."""
    with open_source(kitti_clip) as src:
        frames = [src[i] for i in range(1, 16, 2)]
    with OnlineRepeat(taught) as live:
        for f in frames:
            live.feed(f)
        assert live.localized
        v = live.view
        t = int(frames[-1].t_ns)
        s = v.controller_state_at(t, with_covariance=True)
        F = v.frame_output_covariance(t, s.T_o_a)
        assert np.all(np.linalg.eigvalsh(F[:3, :3]) > 0)
        rest = s.position_covariance - F[:3, :3]
        assert np.all(np.linalg.eigvalsh(0.5 * (rest + rest.T)) > -1e-12)  # the smoother's own marginal
        w = v.window(t, 3, 0.02)
        smoother_part = w.covariance - np.kron(np.ones((3, 3)), F)
        assert np.all(np.linalg.eigvalsh(0.5 * (smoother_part + smoother_part.T)) > -1e-9)


def test_position_covariance_covers_the_error(taught, kitti_clip):
    nees = _position_nees(taught, kitti_clip)
    assert len(nees) >= 15 and np.mean(nees <= NEES_3DOF_99) >= 0.9, nees


def test_position_covariance_is_calibrated(kitti_clip, tmp_path):
    """The issue's bound on the state a controller reads, on the whole kitti06 clip (taught on its even frames,
    repeated on its odd ones, as tools/nees_stages.py): at each frame's time and at the control ticks until the next
    camera frame, position NEES median within 30 % of 3 and >= 90 % inside the 99 % bound."""
    whole = tmp_path / "route.vtrmap"
    teach_command(kitti_clip, whole, "0::2", Config())
    nees = _position_nees(whole, kitti_clip, ticks=int(round(CAMERA_PERIOD_S / CONTROL_PERIOD_S)), last=None)
    median, inside = float(np.median(nees)), float(np.mean(nees <= NEES_3DOF_99))
    print(f"kitti06 ticks: NEES median {median:.4f}, {inside:.1%} inside, {len(nees)} states")
    assert 0.7 * 3 <= median <= 1.3 * 3 and inside >= 0.9, (median, inside, len(nees))
