"""Teach and repeat on real imagery: KITTI clip (teach even frames, repeat odd / stride 3) and the
EuRoC revisit pairs; failure recovery; bad input through the CLI."""

from __future__ import annotations

import csv
import hashlib
import sqlite3
import subprocess
import sys

import numpy as np
import pytest

from vtr.app.evaluation import localization_errors
from vtr.app.pipeline import repeat_command, teach_command
from vtr.config import Config
from vtr.geometry import inv_T
from vtr.io import open_source
from vtr.io.base import FrameSource
from vtr.map import Map
from vtr.navigation.repeat import Repeat
from vtr.navigation.teach import Teach
from vtr.types import StereoImages

SUCCESS_RATE = 0.95
MAX_MEDIAN_ERROR_M = 0.05
MAX_MEDIAN_ERROR_DEG = 0.5
KITTI06_MAX_MEDIAN_ERROR_M = 0.020  # teach even / repeat odd on kitti06_clip (was 14.4 mm)
# teach even / repeat odd on kitti00_ramp_clip: 76 mm before the far-structure estimator; about 10-25 mm of
# any estimate can be the clip's own 1-2 % scale against its ground truth over ~1 m (tools/scale_check.py)
RAMP_MAX_MEDIAN_ERROR_M = 0.040


@pytest.fixture(scope="module")
def kitti_map(kitti_clip, tmp_path_factory):
    path = tmp_path_factory.mktemp("teach") / "route.vtrmap"
    summary = teach_command(kitti_clip, path, "0::2", Config())
    assert summary.vertices == 26 and summary.failures == 0
    return path


def _copy(path, tmp_path):
    dst = tmp_path / "route.vtrmap"
    dst.write_bytes(path.read_bytes())
    return dst


def test_kitti06_teach_even_repeat_odd_within_20mm(kitti_clip, kitti_map, tmp_path):
    summary = repeat_command(kitti_clip, _copy(kitti_map, tmp_path), tmp_path / "r", "1::2", Config())
    # the first keyframe is a place candidate, confirmed (and localized) by the second: every later one localized
    assert summary.localized == summary.vertices - 1
    rows = list(csv.DictReader(open(tmp_path / "r" / "localization.csv")))
    assert rows[0]["status"] == "unconfirmed" and all(r["status"] == "localized" for r in rows[1:])
    assert summary.errors is not None and summary.errors.median_translation_m <= KITTI06_MAX_MEDIAN_ERROR_M


def test_far_structure_ramp_teach_even_repeat_odd(kitti_ramp_clip, tmp_path):
    """Every keyframe localized, T_leaf_trunk within 40 mm (median) of the ground truth."""
    path = tmp_path / "ramp.vtrmap"
    teach_command(kitti_ramp_clip, path, "0::2", Config())
    summary = repeat_command(kitti_ramp_clip, path, tmp_path / "r", "1::2", Config())
    assert summary.vertices == 13 and summary.localized == summary.vertices - 1  # the first: a place candidate
    assert summary.errors is not None and summary.errors.median_translation_m <= RAMP_MAX_MEDIAN_ERROR_M


@pytest.mark.parametrize("frames", ["1::2", "1::3"])
def test_kitti_repeat_localizes_against_ground_truth(kitti_clip, kitti_map, tmp_path, frames):
    out = tmp_path / "repeat"
    summary = repeat_command(kitti_clip, _copy(kitti_map, tmp_path), out, frames, Config())
    assert summary.localized >= SUCCESS_RATE * (summary.vertices - 1)  # after the first (a place candidate)
    assert summary.errors is not None
    assert summary.errors.median_translation_m <= MAX_MEDIAN_ERROR_M
    assert summary.errors.median_rotation_deg <= MAX_MEDIAN_ERROR_DEG
    header = (out / "landmarks.csv").read_text().splitlines()[0].split(",")
    assert header[:8] == ["t_ns", "leaf_id", "trunk_id", "landmark_id", "inlier", "parallax_deg", "view_deg", "range_m"]
    # every second frame fits; every third leaves c2 unidentifiable on this short clip: refused, not printed
    _check_landmarks_file_and_fit(out, tmp_path, must_fit=frames == "1::2")
    loc_rows = (out / "localization.csv").read_text().splitlines()
    assert len(loc_rows) == summary.vertices + 1
    assert (out / "report.png").stat().st_size > 10_000
    assert (out / "trajectory_tum.txt").is_file() and (out / "run.json").is_file()


def _check_landmarks_file_and_fit(out, tmp_path, must_fit: bool = True):
    """landmarks.csv of a real repeat, read back by perception_model's reader, is fitted by the CLI (or, without
    ``must_fit``, refused in one line when the data cannot identify the model: no model written)."""
    import csv
    import json

    from click.testing import CliRunner

    from perception_model.cli import main as pm_main
    from perception_model.landmarks_file import read_landmarks

    obs = read_landmarks(out / "landmarks.csv")
    with open(out / "localization.csv", newline="") as fh:
        ok = [r for r in csv.DictReader(fh) if r["success"] == "1"]
    assert {(int(r["t_ns"]), int(r["leaf_id"]), int(r["trunk_id"])) for r in ok} == set(
        zip(obs.t_ns.tolist(), obs.leaf_id.tolist(), obs.trunk_id.tolist(), strict=True)
    )
    assert obs.matched is not None and not (obs.inlier & ~obs.matched).any()
    for r in ok:  # the inliers of a localization that lie in the leaf's view
        assert 0 < obs.inlier[obs.t_ns == int(r["t_ns"])].sum() <= int(r["inliers"])
    assert (obs.alpha >= 0).all() and (obs.theta < np.pi / 2).all() and (obs.range_m > 0).all()
    model = tmp_path / "model.json"
    res = CliRunner().invoke(
        pm_main, ["fit", str(out / "landmarks.csv"), "--out", str(model), "--holdout", "0", "--min-bin-count", "3"]
    )
    if not must_fit and res.exit_code == 1:
        assert "cannot identify" in res.output and "Traceback" not in res.output and not model.exists(), res.output
        return
    assert res.exit_code == 0, res.output
    fitted = json.loads(model.read_text())
    assert 0 < fitted["c1"] <= 1 and fitted["data"]["n_observations"] == len(obs)
    assert fitted["data"]["n_localizations"] == len(ok)


def test_map_reopens_in_new_process_and_teach_run_is_untouched(kitti_clip, kitti_map, tmp_path):
    path = _copy(kitti_map, tmp_path)

    def teach_rows():
        with sqlite3.connect(path) as con:
            rows = con.execute("SELECT * FROM vertices WHERE run = 0 ORDER BY id").fetchall()
            rows += con.execute(
                "SELECT * FROM edges WHERE kind = 'temporal' AND from_id < 4294967296 ORDER BY from_id"
            ).fetchall()
        return hashlib.sha256(repr(rows).encode()).hexdigest()

    before = teach_rows()
    repeat_command(kitti_clip, path, tmp_path / "r", "1:20:2", Config())
    assert teach_rows() == before
    info = subprocess.run([sys.executable, "-m", "vtr", "map", "info", str(path)], capture_output=True, text=True)
    assert info.returncode == 0, info.stderr
    assert "teach" in info.stdout and "repeat" in info.stdout


@pytest.fixture(scope="module")
def euroc_localized(euroc_pairs):
    """Each revisit pair (taught, revisit) localized without a prior: frames, estimate, stated truth."""
    from vtr.navigation.localization import Localizer, TaughtSubmap
    from vtr.vo.stereo import StereoProcessor

    cfg = Config()
    out = {}
    with open_source(euroc_pairs) as src:
        gt = src.ground_truth()
        sp = StereoProcessor(src.camera, cfg.features, cfg.stereo)
        loc = Localizer(src.camera, cfg.localization, cfg.estimation, cfg.stereo.pixel_sigma)
        for taught, revisit in ((0, 1), (2, 3)):
            f_taught, f_revisit = sp.process(src[taught]), sp.process(src[revisit])
            est = loc.localize(f_revisit, TaughtSubmap.of_frame(f_taught, src.camera), None, trusted_prior=False)
            T, inlier = est.T_leaf_trunk, est.inlier
            e = (
                None
                if T is None
                else localization_errors(T[None], gt.t_ns[[revisit]], gt.t_ns[[taught]], gt.t_ns, gt.T_world_cam)
            )
            stated = inv_T(gt.T_world_cam[revisit]) @ gt.T_world_cam[taught]
            out[(taught, revisit)] = (f_taught, f_revisit, T, int(inlier.sum()), e, stated, src.camera)
    return out


@pytest.mark.parametrize("pair", [(0, 1), (2, 3)])
def test_euroc_revisit_pairs_localize(euroc_localized, pair):
    """Frames 0->1 (0.43 m, 37 deg apart) and 2->3 (0.32 m, 16 deg): ORB bridges both views."""
    _, _, T, inliers, _, _, _ = euroc_localized[pair]
    assert T is not None and inliers >= Config().localization.min_inliers_unlocalized


def test_euroc_pair_2_3_within_5cm_1deg(euroc_localized):
    e = euroc_localized[(2, 3)][4]
    assert e.translation_m[0] <= 0.05 and e.rotation_deg[0] <= 1.0


# Pair 0->1 has no pose bound: its stated pose does not fit the images (datasets/euroc_revisit_pairs/SOURCE.md);
# it is judged by the image-consistency check below instead.


@pytest.mark.parametrize("pair", [(0, 1), (2, 3)])
def test_euroc_pairs_estimate_fits_the_images_better_than_stated_truth(euroc_localized, pair):
    """Taught landmarks projected into the revisit with a pose must land on matching features: ours
    puts hundreds within 3 px; the stated ground truth (a VIO project's body poses) only a few."""
    from vtr.vo.matching import match_to_landmarks

    taught, revisit, T, _, _, stated, camera = euroc_localized[pair]
    max_distance = Config().localization.max_descriptor_distance
    fits = [len(match_to_landmarks(taught, revisit, pose, camera, 3.0, max_distance, 1.0)[0]) for pose in (T, stated)]
    assert fits[0] >= 300
    assert fits[1] * 5 < fits[0]


class _ForeignSegment(FrameSource):
    """A repeat source whose frames ``lo..hi`` come from another place (a synthetic scene)."""

    format_name = "test"

    def __init__(self, base: FrameSource, indices: list[int], foreign: dict[int, tuple[np.ndarray, np.ndarray]]):
        self.base, self.indices, self.foreign = base, indices, foreign
        self.path, self.camera = base.path, base.camera

    def __len__(self):
        return len(self.indices)

    def timestamps(self):
        return self.base.timestamps()[self.indices]

    def _load(self, i):
        img = self.base[self.indices[i]]
        if i in self.foreign:
            return StereoImages(img.t_ns, img.index, *self.foreign[i])
        return img


def test_localization_failure_is_reported_and_recovers(kitti_clip, kitti_map, tmp_path):
    from vtr.sim import synthetic as syn

    scene = syn.aerial_scene(5)
    cam = syn.kitti_like_camera()
    poses = syn.aerial_route(10.0, 2.0)
    foreign = {}
    for k, i in enumerate(range(8, 12)):
        r = syn.render_stereo(scene, cam, poses[k])
        foreign[i] = (r.left, r.right)
    with open_source(kitti_clip) as base, Map.open(_copy(kitti_map, tmp_path), "a") as m:
        src = _ForeignSegment(base, list(range(1, 51, 2)), foreign)
        rp = Repeat(m, Config(), "test")
        locs = [s.localization for s in (rp.process(src[i]) for i in range(len(src))) if s.localization]
    ok = np.array([loc.success for loc in locs])
    idx = {loc.t_ns: k for k, loc in enumerate(locs)}
    foreign_t = {int(base_t) for base_t in src.timestamps()[list(foreign)]}
    in_foreign = np.array([loc.t_ns in foreign_t for loc in locs])
    assert ok[~in_foreign][1:4].all()  # localized before (the first confirms at the second)
    assert not ok[in_foreign].any()  # failures while elsewhere, reported
    assert max(loc.consecutive_failures for loc in locs) >= len(foreign) - 1
    after = np.flatnonzero(~in_foreign & (np.arange(len(locs)) > max(idx[t] for t in foreign_t if t in idx)))
    assert ok[after[2:]].all()  # recovered once the route is back in view
    assert ok[after[:3]].any()


def _vtr(*args):
    return subprocess.run([sys.executable, "-m", "vtr", *map(str, args)], capture_output=True, text=True)


def _one_line_error(r, *needles):
    assert r.returncode == 1 and "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("vtr: error:")
    for n in needles:
        assert n in line, line


def test_repeat_bad_input(kitti_clip, euroc_micro, kitti_map, tmp_path):
    path = _copy(kitti_map, tmp_path)
    size = path.stat().st_size
    _one_line_error(
        _vtr("repeat", kitti_clip, "--map", tmp_path / "missing.vtrmap", "--out", tmp_path / "o"), "missing.vtrmap"
    )
    _one_line_error(_vtr("repeat", euroc_micro, "--map", path, "--out", tmp_path / "o"), "camera")
    _one_line_error(
        _vtr("repeat", kitti_clip, "--map", path, "--out", tmp_path / "o", "--frames", "60:70"), "frames '60:70'"
    )
    with Map.open(path) as m:
        assert [r.kind for r in m.runs()] == ["teach"]
    assert path.stat().st_size == size


def test_teach_refuses_existing_map_and_empty_run(kitti_clip, kitti_map, tmp_path):
    path = _copy(kitti_map, tmp_path)
    _one_line_error(_vtr("teach", kitti_clip, "--map", path, "--frames", "0:3"), "exists")
    with open_source(kitti_clip) as src, Map.create(tmp_path / "empty.vtrmap", src.camera) as m:
        teach = Teach(m, src.camera, Config())
        with pytest.raises(Exception, match="no keyframe"):
            teach.finish()


def test_a_repeat_can_leave_the_map_untouched(kitti_clip, kitti_map, tmp_path):
    """`vtr repeat --read-only-map`: the same localizations, and the map's bytes unchanged (no run appended)."""
    path = _copy(kitti_map, tmp_path)
    before = hashlib.sha256(path.read_bytes()).hexdigest()
    r = _vtr("repeat", kitti_clip, "--map", path, "--frames", "1:20:2", "--out", tmp_path / "ro", "--read-only-map")
    assert r.returncode == 0, r.stderr
    assert hashlib.sha256(path.read_bytes()).hexdigest() == before
    with Map.open(path) as m:
        assert [run.kind for run in m.runs()] == ["teach"]
    r = _vtr("repeat", kitti_clip, "--map", path, "--frames", "1:20:2", "--out", tmp_path / "rw")
    assert r.returncode == 0, r.stderr
    with Map.open(path) as m:
        assert [run.kind for run in m.runs()] == ["teach", "repeat"]
    ro = (tmp_path / "ro" / "localization.csv").read_text()
    rw = (tmp_path / "rw" / "localization.csv").read_text()
    assert ro == rw  # the same repeat, whether the map keeps it or not


def test_a_repeat_not_judged_against_ground_truth_says_why(kitti_clip, tmp_path):
    """A reversed copy of the clip has ground truth of its own, but not the teach's source: the summary says the
    repeat was not judged and why (it used to say nothing)."""
    from vtr.cli.summaries import repeat_lines
    from vtr.io.kitti import write_reordered_clip

    path = tmp_path / "route.vtrmap"
    teach_command(kitti_clip, path, "0:12:2", Config())
    rev = write_reordered_clip(kitti_clip, tmp_path / "reversed", list(range(11, -1, -1)))
    summary = repeat_command(rev, path, tmp_path / "r", "1::2", Config(), read_only_map=True)
    assert summary.integrity is None and summary.ground_truth_note is not None
    assert "is not the teach's" in summary.ground_truth_note
    assert any(line.startswith("not judged against ground truth: ") for line in repeat_lines(summary))
    same = repeat_command(kitti_clip, path, tmp_path / "s", "1:12:2", Config(), read_only_map=True)
    assert same.integrity is not None and same.ground_truth_note is None
