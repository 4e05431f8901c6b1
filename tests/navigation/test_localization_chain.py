"""The chain owns the taught path and places repeat poses in the teach frame (no images involved)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.config import LocalizationConfig
from vtr.errors import MapError
from vtr.geometry import exp_se3, inv_T
from vtr.map import TaughtPath, vertex_id
from vtr.navigation.localization import LocalizationChain

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
    chain = LocalizationChain(path, LocalizationConfig())
    T_world_leaf, T_leaf_trunk = exp_se3(xi_world), exp_se3(xi_lt)
    chain.update(int(IDS[5]), T_world_leaf, trunk, T_leaf_trunk)
    assert chain.branch_id == int(IDS[trunk]) and chain.localized
    expected = path.T_world_vertex[trunk] @ inv_T(T_leaf_trunk)
    np.testing.assert_allclose(chain.T_teach(T_world_leaf), expected, atol=1e-9)
    np.testing.assert_allclose(chain.T_teach_localized(int(IDS[trunk]), T_leaf_trunk), expected, atol=1e-12)
    # a later frame moves with repeat odometry from there
    T_step = exp_se3(np.array([0.0, 0.01, 0.0, 0.0, 0.0, 0.5]))
    np.testing.assert_allclose(chain.T_teach(T_world_leaf @ T_step), expected @ T_step, atol=1e-9)


def test_prior_finds_the_trunk_and_the_path_is_owned():
    path = _path()
    chain = LocalizationChain(path, LocalizationConfig(), start_index=2)
    assert chain.branch_id == -1                       # before the first success
    # the repeat starts at taught vertex 2; a leaf 3 m further along is nearest to vertex 5
    T_w_leaf = inv_T(path.T_world_vertex[2]) @ path.T_world_vertex[5]
    trunk, T_prior = chain.prior(T_w_leaf)
    assert trunk == 5
    np.testing.assert_allclose(T_prior, np.eye(4), atol=1e-9)
    assert chain.path is path and not path.T_world_vertex.flags.writeable
    with pytest.raises(MapError, match="not on the privileged path"):
        chain.T_teach_localized(vertex_id(1, 0), np.eye(4))
