"""Teach an aerial route in a synthetic scene and repeat it with lateral offsets: localization
succeeds and recovers the true offset (exact ground truth from the generator)."""

from __future__ import annotations

import numpy as np
import pytest

from vtr.config import Config
from vtr.geometry import inv_T
from vtr.io import open_source
from vtr.map import Map, split_vertex_id
from vtr.navigation.repeat import Repeat
from vtr.navigation.teach import Teach
from vtr.sim import synthetic as syn

LENGTH_M = 16.0
RAMP_M = 5.0
OFFSET_TOLERANCE = 0.05  # estimated lateral offset within 5 % of the true one
ZERO_OFFSET_TOLERANCE_M = 0.05


@pytest.fixture(scope="module")
def taught(tmp_path_factory):
    root = tmp_path_factory.mktemp("aerial")
    cam, scene = syn.zed_camera(), syn.aerial_scene(0)
    T = syn.aerial_route(LENGTH_M, 1.0)
    teach_dir = syn.write_sequence(root / "teach", scene, cam, T, syn.route_times(T, 4.0))
    with open_source(teach_dir) as src, Map.create(root / "route.vtrmap", src.camera) as m:
        teach = Teach(m, src.camera, Config(), str(teach_dir))
        for images in src:
            teach.process(images)
        teach.finish()
    return root, scene, cam, T


@pytest.mark.parametrize("lateral", [0.0, 2.0, 4.0])
def test_repeat_recovers_lateral_offset(taught, lateral):
    root, scene, cam, T_teach = taught
    T_rep = syn.drifting_aerial_route(LENGTH_M - 1.0, 1.0, lateral, 0.0, RAMP_M, start_offset_m=0.5)
    rep_dir = syn.write_sequence(root / f"rep{lateral:g}", scene, cam, T_rep, syn.route_times(T_rep, 4.0), noise_seed=1)
    path = root / f"map{lateral:g}.vtrmap"
    path.write_bytes((root / "route.vtrmap").read_bytes())
    with open_source(rep_dir) as src, Map.open(path, "a") as m:
        teach_t = {int(i): m.vertex(int(i)).t_ns for i in m.taught_path().ids}
        rp = Repeat(m, Config(), str(rep_dir))
        locs = [s.localization for s in (rp.process(im) for im in src) if s.localization is not None]
    teach_t_ns = syn.route_times(T_teach, 4.0)
    settled = [loc for loc in locs if split_vertex_id(loc.leaf_id)[1] >= RAMP_M]
    assert all(loc.success for loc in settled)
    est = []
    for loc in settled:
        k = int(np.searchsorted(teach_t_ns, teach_t[loc.trunk_id]))
        p_world = (T_teach[k] @ inv_T(loc.T_leaf_trunk))[:3, 3]
        est.append(p_world[1] - T_teach[0, 1, 3])  # route heads along +x: left is +y
    est = np.array(est)
    tol = max(OFFSET_TOLERANCE * lateral, ZERO_OFFSET_TOLERANCE_M)
    assert np.all(np.abs(est - lateral) <= tol), est


class _Truth:
    """Ground truth of a synthetic sequence in the scene's world (``GroundTruth``'s two fields)."""

    def __init__(self, T_world_cam: np.ndarray, t_ns: np.ndarray):
        self.T_world_cam, self.t_ns = T_world_cam, t_ns


def _repeat_integrity(taught, name: str, scene, T_rep: np.ndarray):
    from vtr.app.evaluation import integrity_of

    root, _, cam, T_teach = taught
    t_rep = syn.route_times(T_rep, 4.0)
    rep_dir = syn.write_sequence(root / name, scene, cam, T_rep, t_rep, noise_seed=2)
    path = root / f"{name}.vtrmap"
    path.write_bytes((root / "route.vtrmap").read_bytes())
    with open_source(rep_dir) as src, Map.open(path, "a") as m:
        rp = Repeat(m, Config(), str(rep_dir))
        locs = [s.localization for s in rp.steps(rp.odometry.stereo.frames(iter(src))) if s.localization is not None]
        trunk_t = np.array([m.vertex(loc.trunk_id).t_ns for loc in locs], np.int64)
    return locs, integrity_of(locs, trunk_t, _Truth(T_rep, t_rep), _Truth(T_teach, syn.route_times(T_teach, 4.0)))


def test_synthetic_repeat_started_part_way(taught):
    """Started 7.5 m along the route, 1 m to the left: found by place recognition, no wrong success."""
    _, scene, _, _ = taught
    locs, integrity = _repeat_integrity(
        taught, "partway", scene, syn.aerial_route(LENGTH_M - 0.5, 1.0, start_offset_m=7.5, lateral_offset_m=1.0)
    )
    assert integrity.wrong == 0 and integrity.first_correct is not None and integrity.first_correct < 3, integrity
    assert integrity.rate_after >= 0.9, integrity


def test_synthetic_route_flown_backward(taught):
    """The return flight: the taught route from its end to its start, the camera facing as taught."""
    _, scene, _, _ = taught
    T_back = syn.aerial_route(14.0, 1.0, start_offset_m=0.5, lateral_offset_m=0.5)[::-1].copy()
    locs, integrity = _repeat_integrity(taught, "backward", scene, T_back)
    assert integrity.wrong == 0 and integrity.first_correct is not None and integrity.first_correct < 3, integrity
    assert integrity.rate_after >= 0.9, integrity
    assert all(loc.direction == -1 for loc in locs if loc.success)


def test_synthetic_scene_of_another_place_never_succeeds(taught):
    """A route through another scene: place recognition proposes vertices, none verifies twice: no success."""
    locs, integrity = _repeat_integrity(taught, "elsewhere", syn.aerial_scene(7), syn.aerial_route(12.0, 1.0))
    assert integrity.successes == 0, [loc.status for loc in locs]
    assert all(loc.status.value != "localized" for loc in locs)
