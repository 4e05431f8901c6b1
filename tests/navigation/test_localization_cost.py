"""What keeps a repeat's localization cheap, as behaviour (speed itself is tools/bench_repeat.py's): a tracked leaf is
matched guided by the chain's prior (never the broad search) and finds as many inliers as the broad search would;
place recognition is queried while tracking only for the periodic check; the localizer's stages are timed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vtr.app.pipeline import teach_command
from vtr.config import Config
from vtr.io import open_source
from vtr.map import Map
from vtr.navigation import chain_localizer as chain_module
from vtr.navigation import localization as loc_module
from vtr.navigation.repeat import Repeat

FRAMES = list(range(1, 24, 2))


@pytest.fixture(scope="module")
def taught(kitti_clip, tmp_path_factory):
    path = tmp_path_factory.mktemp("cost") / "route.vtrmap"
    teach_command(kitti_clip, path, "0:24:2", Config())
    return path


def _repeat(kitti_clip, taught, tmp_path, config: Config, monkeypatch, record) -> list:
    """The odd frames repeated against the even ones (1 thread), with ``record`` patched in by the caller."""
    copy = tmp_path / "repeat.vtrmap"
    copy.write_bytes(taught.read_bytes())
    with open_source(kitti_clip) as src, Map.open(copy, "a") as m:
        rp = Repeat(m, config, "test")
        record(rp)
        steps = [rp.process_frame(f) for f in rp.odometry.stereo.frames(src.iter_frames(FRAMES))]
    return [s.localization for s in steps if s.localization is not None]


def _tracking_flag(monkeypatch) -> dict[str, bool]:
    """``{"on": ...}``: true while the chain tracks a leaf (``ChainLocalizer._track`` runs), patched in here."""
    flag = {"on": False}
    real_track = chain_module.ChainLocalizer._track

    def track(self, *a, **k):
        flag["on"] = True
        try:
            return real_track(self, *a, **k)
        finally:
            flag["on"] = False

    monkeypatch.setattr(chain_module.ChainLocalizer, "_track", track)
    return flag


def test_a_tracked_leaf_is_matched_guided_and_keeps_the_broad_search_inliers(kitti_clip, taught, tmp_path, monkeypatch):
    """Every leaf localized while tracking is matched by projecting the submap with the chain's prior (the broad
    all-against-all search never runs for it); on the kitti clip that finds at least as many inliers in all as the
    broad search on the same leaves, and never 3 % fewer on one."""
    config = Config().replace("features", threads=1)
    tracked: list[tuple] = []
    broad_calls = {"tracking": 0}
    in_track = _tracking_flag(monkeypatch)
    real_localize = loc_module.Localizer.localize
    real_match_all = loc_module.match_all

    def localize(self, leaf, submap, T_prior, seed=0, trusted_prior=True, consecutive_failures=0):
        if in_track["on"]:
            tracked.append((self, leaf, submap, T_prior, seed))
        return real_localize(self, leaf, submap, T_prior, seed, trusted_prior, consecutive_failures)

    def match_all(*a, **k):
        broad_calls["tracking"] += in_track["on"]
        return real_match_all(*a, **k)

    monkeypatch.setattr(loc_module.Localizer, "localize", localize)
    monkeypatch.setattr(loc_module, "match_all", match_all)
    locs = _repeat(kitti_clip, taught, tmp_path, config, monkeypatch, lambda rp: None)
    assert sum(loc.success for loc in locs) >= len(locs) - 1 and len(tracked) >= len(locs) - 2
    assert broad_calls["tracking"] == 0
    monkeypatch.setattr(loc_module.Localizer, "localize", real_localize)
    guided, broad = [], []
    for localizer, leaf, submap, T_prior, seed in tracked:
        assert T_prior is not None
        guided.append(localizer.localize(leaf, submap, T_prior, seed).inliers)
        broad.append(localizer.localize(leaf, submap, None, seed).inliers)
    guided_a, broad_a = np.array(guided), np.array(broad)
    assert guided_a.sum() >= broad_a.sum(), (guided, broad)
    assert np.all(guided_a >= 0.97 * broad_a), (guided, broad)


@pytest.mark.parametrize("check_every", [1000, 4])
def test_place_recognition_is_not_queried_while_tracking_but_for_the_periodic_check(
    kitti_clip, taught, tmp_path, monkeypatch, check_every
):
    """Place recognition is asked only while searching (the start, a loss) and, while tracking, once every
    ``localization.place_check_every`` leaves: a tracked leaf costs no place query of its own."""
    config = Config().replace("features", threads=1)
    config = config.replace("localization", place_check_every=check_every)
    calls = {"tracking": 0, "searching": 0}
    in_track = _tracking_flag(monkeypatch)

    def record(rp):
        real_scores = rp.place.scores

        def scores(descriptors, also=None):
            calls["tracking" if in_track["on"] else "searching"] += 1
            return real_scores(descriptors, also=also)

        object.__setattr__(rp.place, "scores", scores)  # this repeat's index only

    locs = _repeat(kitti_clip, taught, tmp_path, config, monkeypatch, record)
    localized = sum(loc.success for loc in locs)
    assert localized >= len(locs) - 1
    assert calls["searching"] >= 1  # the first leaf is found by place recognition
    if check_every > len(locs):
        assert calls["tracking"] == 0  # no periodic check due: no query while tracking
    else:  # the periodic check (counted from the last check)
        assert 1 <= calls["tracking"] <= -(-localized // (check_every - 1))


def test_the_localizer_times_its_stages(kitti_clip, taught, tmp_path, monkeypatch):
    """match / ransac / refine and the repeat's submap reads and landmark records are timed (bench_repeat's split),
    and the map writes (vertex, edges and localization record: one transaction) beside the odometry's stages."""
    config = Config().replace("features", threads=1)
    kept = {}
    locs = _repeat(kitti_clip, taught, tmp_path, config, monkeypatch, lambda rp: kept.setdefault("rp", rp))
    seconds = dict(kept["rp"].localizer.timer.seconds)
    assert locs and {"match", "ransac", "refine", "submap", "landmark_record"} <= set(seconds)
    assert all(v > 0 for v in seconds.values())
    assert kept["rp"].timer.seconds["map_write"] > 0
    assert dataclasses.is_dataclass(locs[0])
