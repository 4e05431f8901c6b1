"""Horizon evaluation against per-trunk PerceptionConstraint; axis gradient; empty trunks flagged."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception_model import frames
from perception_model.constraint import PerceptionConstraint
from perception_model.horizon import (
    EMPTY_TRUNK,
    NO_LANDMARK_IN_VIEW,
    OFF_ROUTE,
    OK,
    HorizonEvaluator,
    TrunkLandmarks,
)
from perception_model.model import PerceptionModel

MODEL = PerceptionModel.thesis()


def _trunks(rng, t=6, m=300):
    out = []
    for i in range(t):
        lm = rng.uniform([8.0, -10.0, -14.0], [25.0, 10.0, -9.0], (m - 20 * i, 3))
        out.append(
            TrunkLandmarks(
                i,
                np.array([1.5 * i, 0.3 * i, 12.0]),
                0.2 * i - 0.5,
                np.array([0.1, 0.0, 0.05]),
                lm,
                math.radians(45.0 + i),
            )
        )
    return out


def test_each_step_equals_its_own_trunks_perception_constraint():
    rng = np.random.default_rng(1)
    trunks = _trunks(rng)
    ev = HorizonEvaluator(MODEL, trunks)
    n = 12
    tr = rng.integers(0, len(trunks), n)
    pos = ev.camera_centres_g()[tr] + rng.normal(0, 1.5, (n, 3))
    yaw = ev.yaw_g[tr] + rng.normal(0, 0.3, n)
    out = ev.evaluate(pos, tr, yaw)
    assert np.all(out.flag == OK)
    for k in range(n):
        t = trunks[tr[k]]
        X, psi_o = frames.to_trunk_frame(pos[k], yaw[k], t.position_g, t.yaw_g)
        con = PerceptionConstraint(MODEL, t.landmarks_o, pitch_down=t.pitch_down)
        ref = con.evaluate((X - t.camera_o)[None], [psi_o])
        R = frames.rot_z(t.yaw_g)
        assert out.mu[k] == pytest.approx(ref.mu[0], abs=1e-9)
        assert out.g[k] == pytest.approx(ref.g[0], abs=1e-9)
        assert out.g_conservative[k] == pytest.approx(ref.g_conservative[0], abs=1e-9)
        assert np.allclose(out.dg_dpos[k], R @ ref.dg_dpos[0], atol=1e-9)
        assert np.allclose(out.dgc_dpos[k], R @ ref.dgc_dpos[0], atol=1e-9)
        assert out.dg_dyaw[k] == pytest.approx(ref.dg_dyaw[0], abs=1e-9)


def test_axis_gradient_by_finite_differences():
    rng = np.random.default_rng(2)
    ev = HorizonEvaluator(MODEL, _trunks(rng))
    tr = np.array([0, 2, 5])
    pos = ev.camera_centres_g()[tr] + rng.normal(0, 1.0, (3, 3))
    z0 = frames.optical_axis(ev.yaw_g[tr] + 0.1, math.radians(50.0))
    out = ev.evaluate(pos, tr, axes_g=z0)
    h = 1e-6
    for k in range(3):
        for j in range(3):
            zp, zm = z0.copy(), z0.copy()
            zp[k, j] += h
            zm[k, j] -= h
            fd = (
                ev.evaluate(pos, tr, axes_g=zp, gradient=False).g[k]
                - ev.evaluate(pos, tr, axes_g=zm, gradient=False).g[k]
            ) / (2 * h)
            # the evaluator normalizes the axis: compare the tangential part
            an = out.dg_daxis[k] - (out.dg_daxis[k] @ z0[k]) * z0[k]
            assert fd == pytest.approx(an[j], abs=1e-5 * max(1.0, abs(an[j])))


def test_empty_and_out_of_view_trunks_are_flagged_not_errors():
    rng = np.random.default_rng(3)
    trunks = _trunks(rng, t=2)
    trunks.append(TrunkLandmarks(99, np.zeros(3), 0.0, np.zeros(3), np.zeros((0, 3))))
    ev = HorizonEvaluator(MODEL, trunks, l_min=30.0)
    pos = ev.camera_centres_g()[[0, 1, 2]]
    # step 1 looks straight up-back, away from every landmark
    axes = np.array([frames.optical_axis(ev.yaw_g[0], math.radians(50.0)), [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    out = ev.evaluate(pos, [0, 1, 2], axes_g=axes)
    assert out.flag.tolist() == [OK, NO_LANDMARK_IN_VIEW, EMPTY_TRUNK]
    assert out.mu[1] == out.mu[2] == 0.0 and out.g[2] == pytest.approx(-30.0)
    assert np.all(out.dg_dpos[1:] == 0.0) and np.all(np.isfinite(out.dg_daxis))


def test_mu_gradients_and_distances():
    """``dmu_dyaw`` / ``dmu_daxis`` (the field's guard uses them) by finite differences; ``distance_m`` is the
    camera's distance from its trunk's taught camera; OFF_ROUTE is a flag of its own."""
    rng = np.random.default_rng(4)
    ev = HorizonEvaluator(MODEL, _trunks(rng))
    tr = np.array([1, 3, 4])
    taught = ev.camera_centres_g()[tr]
    pos = taught + rng.normal(0, 1.0, (3, 3))
    yaw = ev.yaw_g[tr] + 0.15
    out = ev.evaluate(pos, tr, yaw)
    assert np.allclose(out.distance_m, np.linalg.norm(pos - taught, axis=1))
    h = 1e-6
    fd = (ev.evaluate(pos, tr, yaw + h, gradient=False).mu - ev.evaluate(pos, tr, yaw - h, gradient=False).mu) / (2 * h)
    assert np.allclose(out.dmu_dyaw, fd, rtol=1e-5, atol=1e-6)
    z0 = frames.optical_axis(yaw, math.radians(50.0))
    ax = ev.evaluate(pos, tr, axes_g=z0)
    for j in range(3):
        zp, zm = z0.copy(), z0.copy()
        zp[:, j] += h
        zm[:, j] -= h
        fd = (
            ev.evaluate(pos, tr, axes_g=zp, gradient=False).mu - ev.evaluate(pos, tr, axes_g=zm, gradient=False).mu
        ) / (2 * h)
        tangential = ax.dmu_daxis - np.einsum("nk,nk->n", ax.dmu_daxis, z0)[:, None] * z0
        assert np.allclose(fd, tangential[:, j], rtol=1e-5, atol=1e-6)
    assert len({OK, NO_LANDMARK_IN_VIEW, EMPTY_TRUNK, OFF_ROUTE}) == 4
