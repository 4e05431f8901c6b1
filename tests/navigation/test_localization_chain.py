"""The chain owns the taught path and places repeat poses in the teach frame (no images involved)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.config import Config
from vtr.errors import MapError
from vtr.geometry import exp_se3, inv_T
from vtr.map import TaughtPath, vertex_id
from vtr.navigation.chain import LocalizationChain, innovation_chi2
from vtr.navigation.trunk import BACKWARD, FORWARD, trunk_window

N = 12
IDS = np.array([vertex_id(0, i) for i in range(N)])


def _path() -> TaughtPath:
    T = np.stack([exp_se3(np.array([0.0, 0.02 * i, 0.0, 0.1 * i, 0.0, float(i)])) for i in range(N)])
    return TaughtPath(IDS, T, np.arange(N) * 10**8)


twists = st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6).map(np.array)


@settings(max_examples=30, deadline=None)
@given(twists, twists, st.integers(0, N - 1))
def test_teach_frame_pose_after_a_success(xi_world, xi_lt, trunk):
    """Right after a successful localization the chain's teach-frame pose of the leaf is its localization."""
    path = _path()
    chain = LocalizationChain(path, Config().localization, Config().smoothing)
    T_world_leaf, T_leaf_trunk = exp_se3(xi_world), exp_se3(xi_lt)
    chain.succeeded(int(IDS[5]), T_world_leaf, trunk, T_leaf_trunk, np.eye(6) * 1e-4)
    assert chain.branch_id == int(IDS[trunk]) and chain.localized
    expected = path.T_world_vertex[trunk] @ inv_T(T_leaf_trunk)
    np.testing.assert_allclose(chain.T_teach(T_world_leaf), expected, atol=1e-9)
    np.testing.assert_allclose(chain.T_teach_localized(int(IDS[trunk]), T_leaf_trunk), expected, atol=1e-12)
    # a later frame moves with repeat odometry from there
    T_step = exp_se3(np.array([0.0, 0.01, 0.0, 0.0, 0.0, 0.5]))
    np.testing.assert_allclose(chain.T_teach(T_world_leaf @ T_step), expected @ T_step, atol=1e-9)


def test_prior_finds_the_trunk_and_the_path_is_owned():
    path = _path()
    chain = LocalizationChain(path, Config().localization, Config().smoothing, start_index=2)
    assert chain.branch_id == -1  # before the first success
    chain.succeeded(int(IDS[2]), np.eye(4), 2, np.eye(4), np.eye(6) * 1e-6)
    # localized at taught vertex 2; a leaf 3 m further along is nearest to vertex 5
    T_w_leaf = inv_T(path.T_world_vertex[2]) @ path.T_world_vertex[5]
    prior = chain.prior(T_w_leaf)
    assert prior.trunk == 5
    np.testing.assert_allclose(prior.T_leaf_trunk, np.eye(4), atol=1e-9)
    # the prior's covariance grows with the distance travelled since the last localization
    near = chain.prior(inv_T(path.T_world_vertex[2]) @ path.T_world_vertex[3]).covariance
    assert np.all(np.diag(prior.covariance) >= np.diag(near)) and prior.covariance[5, 5] > near[5, 5]
    assert chain.path is path and not path.T_world_vertex.flags.writeable
    with pytest.raises(MapError, match="not on the privileged path"):
        chain.T_teach_localized(vertex_id(1, 0), np.eye(4))


def test_a_start_hint_must_be_on_the_path():
    with pytest.raises(MapError, match="start vertex 12 is not on the taught path"):
        LocalizationChain(_path(), Config().localization, Config().smoothing, start_index=N)


@given(st.integers(0, N - 1), st.integers(0, 5), st.integers(0, 9))
def test_the_trunk_window_mirrors_when_the_route_is_travelled_backward(trunk, back, forward):
    lo, hi = trunk_window(trunk, N, back, forward, FORWARD)
    blo, bhi = trunk_window(trunk, N, back, forward, BACKWARD)
    assert lo == max(0, trunk - back) and hi == min(N, trunk + forward + 1)
    assert blo == max(0, trunk - forward) and bhi == min(N, trunk + back + 1)


def test_off_the_route_beyond_either_end():
    path = _path()
    chain = LocalizationChain(path, Config().localization, Config().smoothing)
    last, first = N - 1, 0
    # 4 m beyond the last vertex along the path (camera z is the path direction here)
    ahead = np.eye(4)
    ahead[2, 3] = -4.0  # T_leaf_trunk: the trunk 4 m behind the leaf
    assert chain.beyond_end_m(last, ahead) == pytest.approx(4.0, abs=0.1)
    behind = np.eye(4)
    behind[2, 3] = 4.0
    assert chain.beyond_end_m(first, behind) == pytest.approx(4.0, abs=0.1)
    assert chain.beyond_end_m(N // 2, ahead) < 0  # inside the route


@settings(max_examples=30, deadline=None)
@given(twists, st.floats(1e-4, 1.0))
def test_innovation_is_mahalanobis_and_scale_invariant(xi, sigma):
    """The gate's statistic is xi' (P1 + P2)^-1 xi: scaling both covariances by s^2 divides it by s^2."""
    T = exp_se3(xi * 0.1)
    P = np.eye(6) * sigma**2
    chi = innovation_chi2(T, P, np.eye(4), P)
    assert chi == pytest.approx(innovation_chi2(T, 4 * P, np.eye(4), 4 * P) * 4, rel=1e-9)
    assert innovation_chi2(np.eye(4), P, np.eye(4), P) == pytest.approx(0.0, abs=1e-12)
