"""The taught-path field: trunk selection is the localizer's rule; gradients across trunk changes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perception_model.model import PerceptionModel
from vtr.config import Config, LocalizationConfig
from vtr.control.field import CameraMount, TaughtPathField
from vtr.geometry import log_se3, log_se3_batch
from vtr.map.path import TaughtPath
from vtr.navigation.chain import LocalizationChain

MODEL = PerceptionModel.thesis()


def _field(vertices, lever=(0.2, 0.1, -0.1), config=None):
    return TaughtPathField(
        MODEL, vertices, T_g_map=np.eye(4), mount=CameraMount(math.pi / 2, np.array(lever)), config=config
    )


def test_log_se3_batch_matches_log_se3():
    from vtr.geometry import exp_se3

    rng = np.random.default_rng(0)
    T = np.array([exp_se3(rng.normal(0, s, 6)) for s in (1e-7, 1e-3, 0.3, 1.0, 2.5) for _ in range(4)])
    assert np.allclose(log_se3_batch(T), [log_se3(t) for t in T], atol=1e-10)


def test_trunk_selection_is_the_localization_chains(l_vertices):
    field = _field(l_vertices)
    rng = np.random.default_rng(1)
    cfg = LocalizationConfig()
    taught = TaughtPath(field.vertex_ids, field.T_g_camera, np.zeros(len(field), dtype=np.int64))
    for _ in range(20):
        prev = int(rng.integers(0, len(field)))
        i = min(len(field) - 1, prev + int(rng.integers(0, 4)))
        pos = field.vehicle_position_g[i] + rng.normal(0, 1.5, 3)
        yaw = field.vehicle_yaw_g[i] + rng.normal(0, 0.3)
        chain = LocalizationChain(taught, cfg, Config().smoothing, start_index=prev)
        # twig at the branch: the prior is the relative pose
        chain.succeeded(-1, field.T_g_camera[prev], prev, np.eye(4), np.eye(6) * 1e-6)
        T_g_leaf = field.camera_poses(pos[None], np.array([yaw]), field.pitch_down[prev])[0]
        expected = chain.prior(T_g_leaf).trunk
        assert field.select_trunks(pos[None], np.array([yaw]), prev)[0] == expected


def test_gradients_by_finite_differences_across_trunk_changes(l_vertices):
    field = _field(l_vertices)
    # a horizon sweeping along the corner: its steps fall on several trunks
    k = np.arange(15)
    pos = np.column_stack([6.0 + 0.9 * k, 0.4 + 0.05 * k**1.5, 12.0 + 0.1 * np.sin(k)])
    yaw = 0.05 * k
    ev = field.evaluate(pos, yaw, previous=5)
    assert len(np.unique(ev.trunk)) >= 5
    h = 1e-6
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        fd = (
            field.evaluate(pos + d, yaw, trunk=ev.trunk, gradient=False).g
            - field.evaluate(pos - d, yaw, trunk=ev.trunk, gradient=False).g
        ) / (2 * h)
        assert np.allclose(ev.dg_dpos[:, j], fd, rtol=1e-5, atol=1e-5)
    fd_yaw = (
        field.evaluate(pos, yaw + h, trunk=ev.trunk, gradient=False).g
        - field.evaluate(pos, yaw - h, trunk=ev.trunk, gradient=False).g
    ) / (2 * h)
    assert np.allclose(ev.dg_dyaw, fd_yaw, rtol=1e-5, atol=1e-5)  # axis yaw and lever arm together
    assert np.any(np.abs(ev.dg_dyaw) > 1.0)


def test_landmarks_are_cached_in_each_trunks_o(l_vertices):
    field = _field(l_vertices, lever=(0.0, 0.0, 0.0))
    for i in (0, 14, 20):
        t = field.evaluator.trunks[i]
        assert t.yaw_g == pytest.approx(field.vehicle_yaw_g[i])
        # taught camera looks along o's +y (mount yaw 90 deg), pitched down: landmarks lie at +y, below
        lm = t.landmarks_o
        assert np.median(lm[:, 1]) > 5.0 and np.all(lm[:, 2] < 0) and abs(np.median(lm[:, 0])) < 5.0


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 10_000),
    n=st.integers(1, 15),
    backward=st.booleans(),
    window=st.sampled_from([None, (1, 2), (0, 1), (3, 0)]),
    stride=st.integers(1, 3),
)
def test_a_horizon_follows_the_trunk_rule_step_by_step(l_vertices, seed, n, backward, window, stride):
    """select_trunks over a horizon: each step's trunk is the localizer's rule (vtr.navigation.trunk) in the window of
    the previous step's trunk, in the direction of travel (computed here one step at a time, the window's candidates
    whole: the field's batched search gives the same answers). Small windows and strides of up to 3 vertices a step
    make the chain outrun the field's first block of candidates (the block is widened)."""
    from vtr.navigation.trunk import BACKWARD, FORWARD, select_trunk, trunk_window

    config = None if window is None else LocalizationConfig(trunk_window_back=window[0], trunk_window_forward=window[1])
    field = _field(l_vertices, config=config)
    rng = np.random.default_rng(seed)
    cfg = field.config
    direction = BACKWARD if backward else FORWARD
    start = int(rng.integers(0, len(field)))
    idx = np.clip(start + direction * stride * np.arange(n) + rng.integers(-1, 2, n), 0, len(field) - 1)
    pos = field.vehicle_position_g[idx] + rng.normal(0, 1.0, (n, 3))
    yaw = field.vehicle_yaw_g[idx] + rng.normal(0, 0.2, n)
    got = field.select_trunks(pos, yaw, start, direction=direction)
    prev, want = start, []
    for k in range(n):
        lo, hi = trunk_window(prev, len(field), cfg.trunk_window_back, cfg.trunk_window_forward, direction)
        T_g_leaf = field.camera_poses(pos[k : k + 1], yaw[k : k + 1], field.pitch_down[start])[0]
        prev = select_trunk(np.linalg.inv(T_g_leaf) @ field.T_g_camera[lo:hi], lo, cfg.rotation_weight)
        want.append(prev)
    assert got.tolist() == want


def _route_distances_every_segment(pts, p):
    """The distance to the taught polyline measured against every segment (the field's rule before its k-d trees)."""
    if len(pts) == 1:
        return np.linalg.norm(p - pts[0], axis=1), np.zeros(len(p))
    a, seg = pts[:-1], np.diff(pts, axis=0)
    length = np.linalg.norm(seg, axis=1)
    d = np.divide(seg, length[:, None], out=np.zeros_like(seg), where=length[:, None] > 0.0)
    rel = p[:, None, :] - a[None]
    s = np.einsum("nsk,sk->ns", rel, d)
    closest = a[None] + np.clip(s, 0.0, length[None])[..., None] * d[None]
    dist = np.linalg.norm(p[:, None, :] - closest, axis=2)
    nearest = np.argmin(dist, axis=1)
    rows = np.arange(len(p))
    s_n = s[rows, nearest]
    past = np.zeros(len(p))
    first, last = nearest == 0, nearest == len(seg) - 1
    past[first] = np.maximum(past[first], -s_n[first])
    past[last] = np.maximum(past[last], s_n[last] - length[-1])
    return dist[rows, nearest], past


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 60), back=st.booleans(), spread=st.sampled_from([0.1, 3.0, 50.0]))
def test_route_distances_are_those_over_every_segment(seed, n, back, spread):
    """Random walks (an out-and-back one flies over itself, repeated vertices give zero-length segments) and points
    near and far: the pruned search gives the distances and past-end figures of measuring every segment."""
    from vtr.control.field import _TaughtPolyline

    rng = np.random.default_rng(seed)
    steps = rng.normal(0, 1.0, (n, 3)) * (rng.random((n, 1)) > 0.1)
    pts = np.cumsum(steps, axis=0)
    if back:
        pts = np.vstack([pts, pts[::-1][1:] + rng.normal(0, 0.01, (n - 1, 3))])
    p = pts[rng.integers(0, len(pts), 20)] + rng.normal(0, spread, (20, 3))
    got = _TaughtPolyline(pts).distances(p)
    want = _route_distances_every_segment(pts, p)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
