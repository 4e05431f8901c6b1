"""Place recognition over the taught vertices: real ORB descriptors of the KITTI clip, the index stored and read
back, damage refused, and each repeat frame's best candidates near where it was taken."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtr.config import Config
from vtr.errors import MapError
from vtr.io import open_source
from vtr.navigation.place import PlaceIndex, k_majority
from vtr.vo.stereo import StereoProcessor


@pytest.fixture(scope="module")
def descriptors(kitti_clip):
    cfg = Config()
    with open_source(kitti_clip) as src:
        sp = StereoProcessor(src.camera, cfg.features, cfg.stereo)
        return [sp.process(im).features.descriptors for im in src.iter_frames(list(range(0, 51)))]


@pytest.fixture(scope="module")
def index(descriptors):
    taught = descriptors[0::2]
    return PlaceIndex.build(lambda: iter(taught), len(taught), Config().place)


def test_repeat_frames_find_where_they_were_taken(index, descriptors):
    """Odd frame 2k+1 lies between taught vertices k and k+1: the best candidate is one of them or a neighbour."""
    for f in range(1, 51, 2):
        best = int(index.query(descriptors[f], 3).indices[0])
        assert abs(best - (f // 2 + 0.5)) <= 1.5, (f, best)


def test_stored_index_reads_back_and_damage_is_refused(index, descriptors):
    data = index.to_bytes()
    again = PlaceIndex.from_bytes(data)
    np.testing.assert_array_equal(again.scores(descriptors[7]), index.scores(descriptors[7]))
    with pytest.raises(MapError, match="not a place index"):
        PlaceIndex.from_bytes(b"XXXX" + data[4:])
    with pytest.raises(MapError, match="damaged place index"):
        PlaceIndex.from_bytes(data[: len(data) // 2])


@settings(max_examples=20, deadline=None)
@given(st.integers(2, 40), st.integers(0, 2**31 - 1))
def test_k_majority_centres_are_binary_descriptors_of_the_right_count(k, seed):
    rng = np.random.default_rng(seed)
    X = rng.integers(0, 256, size=(200, 32), dtype=np.uint8)
    centres = k_majority(X, k, 3, np.random.default_rng(seed))
    assert centres.shape == (k, 32) and centres.dtype == np.uint8


def test_a_place_from_another_scene_scores_lower_than_the_route(index, descriptors):
    """Random descriptors (no place of the route) score below every real frame's best match."""
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, size=(2000, 32), dtype=np.uint8)
    worst_real = min(float(index.query(descriptors[f], 1).scores[0]) for f in range(1, 51, 2))
    assert float(index.query(noise, 1).scores[0]) < worst_real


def test_the_route_index_is_stored_at_teach_and_rebuilt_when_missing_or_damaged(kitti_clip, tmp_path):
    """`vtr teach` stores the index; a map without one (taught before it existed) or with a damaged one gets one
    rebuilt from its vertices, the same as the stored one."""
    import sqlite3

    from vtr.app.pipeline import teach_command
    from vtr.map import Map
    from vtr.navigation.place import place_key, route_place_index

    path = tmp_path / "route.vtrmap"
    teach_command(kitti_clip, path, "0:20:2", Config())
    with Map.open(path) as m:
        key = place_key(m.reference_run())
        stored = m.derived(key)
        assert stored is not None
        reference = PlaceIndex.from_bytes(stored)
    con = sqlite3.connect(path)
    con.execute("UPDATE derived SET data = ? WHERE key = ?", (b"VTRP\x01garbage", key))
    con.commit()
    con.close()
    with Map.open(path, "a") as m, pytest.warns(RuntimeWarning, match="it is damaged; rebuilt"):
        rebuilt = route_place_index(m, Config().place)
        np.testing.assert_array_equal(rebuilt.word, reference.word)
        assert PlaceIndex.from_bytes(m.derived(key)).indptr.tolist() == reference.indptr.tolist()  # stored again


def test_an_index_copied_from_another_map_of_the_same_length_is_rebuilt_with_a_warning(kitti_clip, tmp_path):
    """The index carries a digest of the vertices it indexes: another map's index of the same length (taught from
    other frames) is not accepted; it is rebuilt from this map's vertices, stored, and the rebuild is reported."""
    from vtr.app.pipeline import teach_command
    from vtr.map import Map
    from vtr.navigation.place import place_key, route_place_index

    ours, other = tmp_path / "ours.vtrmap", tmp_path / "other.vtrmap"
    teach_command(kitti_clip, ours, "0:20:2", Config())
    teach_command(kitti_clip, other, "1:21:2", Config())
    with Map.open(ours) as m:
        key = place_key(m.reference_run())
        reference = PlaceIndex.from_bytes(m.derived(key))
        n = len(m.taught_path())
    with Map.open(other) as m:
        foreign = m.derived(place_key(m.reference_run()))
        assert len(PlaceIndex.from_bytes(foreign)) == n  # same length: a length check cannot tell
    with Map.open(ours, "a") as m:
        m.put_derived(key, foreign)
    told: list[str] = []
    with Map.open(ours, "a") as m:
        assert route_place_index(m, Config().place, warn=told.append).digest == reference.digest
        assert len(told) == 1 and "does not match the taught vertices" in told[0] and "rebuilt" in told[0]
        np.testing.assert_array_equal(PlaceIndex.from_bytes(m.derived(key)).word, reference.word)  # stored again
    told.clear()
    with Map.open(ours) as m:
        route_place_index(m, Config().place, warn=told.append)
    assert told == []  # the stored one matches now


def test_map_check_names_a_foreign_place_index_and_repair_rebuilds_it(kitti_clip, tmp_path):
    """`vtr map check` used to say ok with another map's place index (same length) stored: now it exits 1 naming
    the index and `--repair`; `--repair` rebuilds it from the vertices, and the map then checks ok."""
    from click.testing import CliRunner

    from vtr.app.pipeline import teach_command
    from vtr.cli import main
    from vtr.map import Map
    from vtr.navigation.place import place_key

    ours, other = tmp_path / "ours.vtrmap", tmp_path / "other.vtrmap"
    teach_command(kitti_clip, ours, "0:12:2", Config())
    teach_command(kitti_clip, other, "1:13:2", Config())
    runner = CliRunner()
    ok = runner.invoke(main, ["map", "check", str(ours)])
    assert ok.exit_code == 0 and "place index matches the taught vertices" in ok.output
    with Map.open(ours) as m:
        key = place_key(m.reference_run())
        reference = m.derived(key)
    with Map.open(other) as m:
        foreign = m.derived(place_key(m.reference_run()))
    with Map.open(ours, "a") as m:
        m.put_derived(key, foreign)
    bad = runner.invoke(main, ["map", "check", str(ours)])
    assert bad.exit_code == 1
    assert "does not match the taught vertices" in bad.stderr and "--repair" in bad.stderr
    assert bad.stderr.count("\n") == 1
    fixed = runner.invoke(main, ["map", "check", str(ours), "--repair"])
    assert fixed.exit_code == 0 and "rebuilt" in fixed.output, fixed.output
    with Map.open(ours) as m:
        assert m.derived(key) == reference  # the same index the teach stored
    assert "place index matches" in runner.invoke(main, ["map", "check", str(ours)]).output


def _route_views(pool: np.ndarray, n: int, seed: int = 0):
    """A synthetic route of ``n`` vertices over real descriptors: landmark k is a pool descriptor with 24 bits
    flipped; position x sees the 1000 landmarks born over its last 10 vertices, each with 12 more bits flipped
    (tools/bench_place.py builds its routes the same way)."""
    rng = np.random.default_rng(seed)
    base = pool[rng.integers(0, len(pool), 100 * (n + 10))]
    bits = np.zeros((len(base), 256), np.uint8)
    bits[np.arange(len(base))[:, None], rng.integers(0, 256, (len(base), 24))] = 1
    world = base ^ np.packbits(bits, axis=1)

    def view(x: float, salt: int) -> np.ndarray:
        r = np.random.default_rng([seed, salt, int(1000 * x)])
        first = max(int(round((x - 9) * 100)), 0)
        d = world[first : first + 1000].copy()
        noise = np.zeros((len(d), 256), np.uint8)
        noise[np.arange(len(d))[:, None], r.integers(0, 256, (len(d), 12))] = 1
        return d ^ np.packbits(noise, axis=1)

    return view


@pytest.fixture(scope="module")
def long_route(descriptors):
    """A 600-vertex route indexed with a shortlist of 100: every query takes the two-pass path."""
    import dataclasses

    view = _route_views(np.unique(np.concatenate(descriptors), axis=0), 600)
    config = dataclasses.replace(Config().place, shortlist=100)
    index = PlaceIndex.build(lambda: (view(i, 0) for i in range(600)), 600, config)
    return index, view


def test_a_long_route_is_queried_in_two_passes_and_finds_the_place(long_route):
    """Beyond ``place.shortlist`` vertices only the shortlist is scored, exactly; the best candidates are still
    where the query was taken and the same as scoring every vertex finds."""
    import dataclasses

    index, view = long_route
    exact = dataclasses.replace(index, shortlist=len(index))
    for x in np.arange(12.5, 596, 37.0):  # (the first 10 vertices all see the same landmarks)
        d = view(x, 1)
        s, all_s = index.scores(d), exact.scores(d)
        rows = np.flatnonzero(s)
        assert 0 < len(rows) <= index.shortlist
        np.testing.assert_allclose(s[rows], all_s[rows], rtol=1e-9, atol=1e-12)  # the shortlist scored exactly
        best = index.query(d, 3).indices
        assert abs(int(best[0]) - x) <= 1.5, (x, best)
        assert best[0] == exact.query(d, 3).indices[0]
        far = slice(int(x + 200) % 600, int(x + 200) % 600 + 20)  # a window elsewhere: scored on request
        np.testing.assert_allclose(index.scores(d, also=far)[far], all_s[far], rtol=1e-9, atol=1e-12)


def test_a_short_route_is_scored_whole_and_the_inverted_file_is_stored(index, descriptors):
    """Up to ``place.shortlist`` vertices every vertex is scored (the sparse product); the inverted file of the
    first pass reads back with the index, and an index stored without it (an older vtr) derives the same one."""
    assert len(index) <= index.shortlist
    q = index.vector(descriptors[7])
    np.testing.assert_array_equal(index.scores(descriptors[7]), np.asarray(index._csr @ q).ravel())
    again = PlaceIndex.from_bytes(index.to_bytes())
    assert again.coarse is not None
    for name in ("indptr", "vertex", "weight"):
        np.testing.assert_array_equal(getattr(again.coarse, name), getattr(index.coarse, name))
    import dataclasses

    older = dataclasses.replace(index, coarse=None)
    np.testing.assert_array_equal(older._coarse().vertex, index.coarse.vertex)
