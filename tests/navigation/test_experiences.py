"""Multi-experience localization on the drifting-appearance case (vtr.app.drifting): a synthetic aerial route
taught once and flown while its textures drift further from the taught ones, every flight appended to one map.
Real odometry, GTSAM and OpenCV; maps reopened from disk; exact ground truth from the generator."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from vtr.app.drifting import drifting_flights, fly, render_flight, repeat_route, route
from vtr.config import Config
from vtr.io import open_source
from vtr.map import Map
from vtr.map.check import check_map
from vtr.map.experiences import WORDS_KEY, experience_links, experiences, prune, retention, use_counts
from vtr.navigation.experiences import ExperienceSubmaps, Recommender
from vtr.navigation.localization import TaughtSubmap
from vtr.navigation.repeat import Repeat

LENGTH_M = 16.0
CHANGES = (0.35, 0.5, 0.65, 0.8)
BACKWARD_CHANGES = (0.35, 0.5, 0.65)
#: what a flight must reach from the first that fails against the teach alone (issue 34)
MIN_RATE_AFTER, MAX_FIRST_CORRECT = 0.95, 3


def _fails_alone(flight) -> bool:
    i = flight.integrity
    return (
        i.wrong > 0 or i.first_correct is None or i.first_correct > MAX_FIRST_CORRECT or i.rate_after < MIN_RATE_AFTER
    )


@pytest.fixture(scope="module")
def forward(tmp_path_factory):
    root = tmp_path_factory.mktemp("drift")
    multi, alone = drifting_flights(root, CHANGES, LENGTH_M)
    return root, multi, alone


def _check_drifting(multi, alone):
    failing = [k for k, a in enumerate(alone) if _fails_alone(a)]
    assert failing, [str(a.integrity) for a in alone]  # the case is a real failure for the teach alone
    for k, (m, a) in enumerate(zip(multi, alone, strict=True)):
        i = m.integrity
        assert i.wrong == 0, (m.change, str(i))
        if k >= failing[0]:
            assert a.integrity.correct == 0 or _fails_alone(a)
            assert i.first_correct is not None and i.first_correct <= MAX_FIRST_CORRECT, (m.change, str(i))
            assert i.rate_after >= MIN_RATE_AFTER, (m.change, str(i))
            assert m.with_experience >= i.correct - 1, (m.change, m.with_experience)  # through experiences
    return failing[0]


def test_drifting_appearance_localizes_through_experiences(forward):
    _, multi, alone = forward
    first_failing = _check_drifting(multi, alone)
    assert CHANGES[first_failing] >= 0.5
    assert multi[0].experiences_used == ()  # the first flight has only the teach


def test_drifting_appearance_flown_backward(tmp_path_factory, forward):
    root = tmp_path_factory.mktemp("drift_back")
    shutil.copyfile(forward[0] / "teach.vtrmap", root / "teach.vtrmap")  # the same teach
    shutil.copytree(forward[0] / "teach", root / "teach")
    multi, alone = drifting_flights(root, BACKWARD_CHANGES, LENGTH_M, backward=True)
    _check_drifting(multi, alone)
    assert all(loc.direction == -1 for m in multi for loc in m.localizations if loc.success)


def test_experiences_per_keyframe_are_bounded(forward):
    root, multi, _ = forward
    bound = Config().experiences.max_per_keyframe
    assert max(len(loc.experiences) for m in multi for loc in m.localizations) <= bound
    # the last flight could have used every earlier one, and used at most the bound at each keyframe
    assert len(multi[-1].experiences_used) >= 1


def test_only_accepted_localizations_link_an_experience(forward):
    """Every spatial edge of a repeat is a success: a localization the gates refused (unconfirmed, inconsistent,
    too few inliers...) never places an experience vertex on the taught path."""
    root, multi, _ = forward
    with Map.open(root / "experiences.vtrmap") as m:
        for flight in multi:
            links = experience_links(m, [flight.run])
            ok = {loc.leaf_id for loc in flight.localizations if loc.success}
            refused = {loc.leaf_id for loc in flight.localizations if not loc.success}
            assert set(links.vertex_id.tolist()) == ok
            assert not refused & set(links.vertex_id.tolist())
        use = use_counts(m)
    # the map counts the keyframes each experience gave inliers to, as the repeats reported them
    reported: dict[int, int] = {}
    for flight in multi:
        for loc in flight.localizations:
            for e in loc.experiences:
                reported[e] = reported.get(e, 0) + 1
    assert {e: n for e, (n, _) in use.items()} == reported


def test_another_place_never_localizes_against_ten_experiences(tmp_path_factory, forward):
    root, multi, _ = forward
    work = tmp_path_factory.mktemp("elsewhere")
    grown = work / "grown.vtrmap"
    shutil.copyfile(root / "teach.vtrmap", grown)
    taught = render_flight(root / "teach", 0, route(LENGTH_M), 0.0)
    for k in range(10):  # the drifting flights again and again, in order
        change = CHANGES[k % len(CHANGES)]
        folder = root / f"fwd_{change:.2f}"
        truth = render_flight(folder, 0, repeat_route(LENGTH_M, False), change)
        fly(grown, folder, truth, taught, change, False, Config())
    with Map.open(grown) as m:
        assert sum(e.trusted for e in experiences(m, Config().experiences.min_localized_share)) == 10
    other = render_flight(work / "other", 7, route(LENGTH_M - 4.0), 0.0)  # another scene
    flight = fly(grown, work / "other", other, taught, 0.0, False, Config())
    assert flight.integrity.successes == 0, [loc.status.value for loc in flight.localizations]
    # and that flight, localized nowhere, is no experience
    with Map.open(grown) as m:
        info = {e.run: e for e in experiences(m, Config().experiences.min_localized_share)}
    assert not info[flight.run].trusted and "localized 0 of" in info[flight.run].why_not


def test_aborted_and_untrusted_repeats_are_not_experiences(tmp_path_factory, forward):
    root, multi, _ = forward
    work = tmp_path_factory.mktemp("aborted")
    path = work / "m.vtrmap"
    shutil.copyfile(root / "experiences.vtrmap", path)
    folder = root / f"fwd_{CHANGES[-1]:.2f}"
    with pytest.raises(KeyboardInterrupt), open_source(folder) as src, Map.open(path, "a") as m:
        rp = Repeat(m, Config(), str(folder))
        for k, images in enumerate(src):
            rp.process(images)
            if k == 10:
                raise KeyboardInterrupt  # Ctrl-C mid-flight: the run is aborted
    strict = dataclasses.replace(Config().experiences, min_localized_share=1.0)
    with Map.open(path, "a") as m:
        infos = {e.run: e for e in experiences(m, Config().experiences.min_localized_share)}
        aborted = max(infos)
        assert infos[aborted].state == "aborted" and not infos[aborted].trusted
        cfg = Config()
        sub = ExperienceSubmaps(
            m, m.taught_path(), cfg.experiences, cfg.localization.neighbour_vertices, m.camera, Repeat(m, cfg).place, ()
        )
        assert aborted not in sub.trusted and set(sub.trusted) == {f.run for f in multi}
        # a share no flight reaches (each misses its first keyframe): none is trusted
        assert not any(e.trusted for e in experiences(m, strict.min_localized_share))


def test_prune_keeps_newest_and_most_used_and_the_map_stays_whole(tmp_path_factory, forward):
    root, multi, _ = forward
    path = tmp_path_factory.mktemp("prune") / "m.vtrmap"
    shutil.copyfile(root / "experiences.vtrmap", path)
    before = path.stat().st_size
    with Map.open(path) as m:
        taught = m.taught_path().ids.copy()
        used = use_counts(m)
    most_used = max(used, key=lambda e: (used[e][0], e))
    with Map.open(path, "a") as m:
        plan = retention(m, keep_last=1, keep_most_used=1, min_localized_share=0.5)
        assert set(plan.keep) == {multi[-1].run, most_used} and plan.remove
        expected = sum(r.n_vertices for r in m.runs() if r.id in plan.remove)
        words = {r: f"{WORDS_KEY}/{r}/digest" for r in [*plan.remove, *plan.keep]}
        for key in words.values():  # an experience's stored words (derived data)
            m.put_derived(key, b"words")
        assert prune(m, plan.remove) == expected
        # a pruned run's words go with it: the next run may take its id, and must not read them as its own
        assert all(m.derived(words[r]) is None for r in plan.remove)
        assert all(m.derived(words[r]) == b"words" for r in plan.keep)
    assert path.stat().st_size < before
    with Map.open(path) as m:
        check_map(m)
        np.testing.assert_array_equal(m.taught_path().ids, taught)
        assert {r.id for r in m.runs() if not r.privileged} == set(plan.keep)
        assert set(experience_links(m, [f.run for f in multi]).run.tolist()) <= set(plan.keep)
        assert set(use_counts(m)) <= set(plan.keep)


def test_recommender_prefers_recent_matches_then_place_similarity():
    cfg = dataclasses.replace(Config().experiences, max_per_keyframe=3, history_keyframes=2)
    r = Recommender(cfg)
    available = np.array([1, 2, 3, 4, 5])
    similarity = lambda runs: np.array([{1: 0.1, 2: 0.9, 3: 0.5, 4: 0.2, 5: 0.8}[int(e)] for e in runs])  # noqa: E731
    assert r.choose(available, similarity) == [2, 5, 3]  # no history: place similarity
    r.observe({4: 50, 1: 80})
    assert r.choose(available, similarity) == [1, 4, 2]  # recent inliers first, one place explores
    r.observe({})
    r.observe({})  # forgotten after history_keyframes
    assert r.choose(available, similarity) == [2, 5, 3]
    assert Recommender(dataclasses.replace(cfg, max_per_keyframe=0)).choose(available, similarity) == []


def _vtr(*args):
    from click.testing import CliRunner

    from vtr.cli import main

    return CliRunner().invoke(main, [str(a) for a in args])


def test_read_only_map_repeat_uses_experiences_and_adds_none(tmp_path_factory, forward):
    """`vtr repeat --read-only-map` localizes through the stored experiences (localization.csv names them, the
    summary counts them) and leaves the map as it was; `vtr map info` lists the experiences and their use."""
    from vtr.app.runfiles.localization_csv import read_localization_csv

    root, multi, _ = forward
    work = tmp_path_factory.mktemp("readonly")
    path = work / "m.vtrmap"
    shutil.copyfile(root / "experiences.vtrmap", path)
    before = path.read_bytes()
    r = _vtr("repeat", root / f"fwd_{CHANGES[-1]:.2f}", "--map", path, "--out", work / "out", "--read-only-map")
    assert r.exit_code == 0, r.output
    assert path.read_bytes() == before
    locs = read_localization_csv(work / "out" / "localization.csv")
    ok = [loc for loc in locs if loc.success]
    assert len(ok) >= MIN_RATE_AFTER * (len(locs) - MAX_FIRST_CORRECT)
    assert all(loc.experiences and set(loc.experiences) <= {f.run for f in multi} for loc in ok)
    assert f"experiences: {len(multi)} in the map, {len(ok)} localization(s) used one" in r.output
    info = _vtr("map", "info", path)
    assert info.exit_code == 0, info.output
    lines = info.output.splitlines()
    rows = lines[lines.index(next(x for x in lines if x.startswith("experiences"))) + 2 :]
    with Map.open(path) as m:
        use = use_counts(m)
    for f in multi:
        row = next(x.split() for x in rows if x.split()[0] == str(f.run))
        assert row[4] == "yes" and int(row[5]) == use.get(f.run, (0, 0))[0]


def test_prune_command_dry_run_changes_nothing(tmp_path_factory, forward):
    root, multi, _ = forward
    path = tmp_path_factory.mktemp("prune_cli") / "m.vtrmap"
    shutil.copyfile(root / "experiences.vtrmap", path)
    before = path.read_bytes()
    r = _vtr("map", "prune", path, "--keep-last", 1, "--keep-most-used", 0, "--dry-run")
    assert r.exit_code == 0, r.output
    assert path.read_bytes() == before and f"would remove {len(multi) - 1} run(s)" in r.output
    r = _vtr("map", "prune", path, "--keep-last", 1, "--keep-most-used", 0)
    assert r.exit_code == 0, r.output
    assert f"removed {len(multi) - 1} run(s)" in r.output and path.stat().st_size < len(before)
    r = _vtr("map", "prune", path, "--keep-last", -1)
    assert r.exit_code != 0 and "--keep-last" in r.output


def test_a_damaged_experience_is_dropped_with_a_warning(tmp_path_factory, forward):
    """An experience whose vertex data no longer matches its checksum (a flipped byte on disk) is left out of the
    repeat, which says so once and localizes through the others."""
    import sqlite3

    root, multi, _ = forward
    path = tmp_path_factory.mktemp("damaged") / "m.vtrmap"
    shutil.copyfile(root / "experiences.vtrmap", path)
    bad = multi[-1].run
    with sqlite3.connect(path) as c:
        c.execute("DROP TRIGGER vertex_data_append_only_update")
        rows = c.execute("SELECT id, data FROM vertex_data WHERE id >> 32 = ?", (bad,)).fetchall()
        for vid, data in rows:
            flipped = bytearray(data)
            flipped[-1] ^= 0x10
            c.execute("UPDATE vertex_data SET data = ? WHERE id = ?", (bytes(flipped), vid))
    warnings: list[str] = []
    folder = root / f"fwd_{CHANGES[-1]:.2f}"
    with open_source(folder) as src, Map.open(path, "a") as m:
        rp = Repeat(m, Config(), str(folder), warn=warnings.append)
        locs = [s.localization for s in (rp.process(im) for im in src) if s.localization is not None]
    assert len(warnings) == 1 and f"experience run(s) [{bad}] not used" in warnings[0], warnings
    assert not any(bad in loc.experiences for loc in locs)
    ok = [loc for loc in locs if loc.success]
    assert len(ok) >= MIN_RATE_AFTER * (len(locs) - MAX_FIRST_CORRECT) and all(loc.experiences for loc in ok)


def _landmarkless_submap(vertex_ids: np.ndarray, T_x_trunk: np.ndarray, slot: np.ndarray) -> TaughtSubmap:
    """A submap of ``vertex_ids`` placed by ``T_x_trunk`` whose landmarks (one per ``slot``) carry no data: what the
    placement covariances read is which vertex each inlier came from and where that vertex sits."""
    n = len(slot)
    return TaughtSubmap(
        vertex_ids,
        T_x_trunk,
        0,
        np.zeros((n, 3)),
        np.zeros((n, 32), np.uint8),
        slot,
        np.zeros((n, 3)),
        np.arange(n),
        np.ones(n),
        np.zeros(n, bool),
    )


def test_experience_covariance_adds_each_contributing_edge_moved_to_the_leaf():
    from vtr.geometry import exp_se3
    from vtr.navigation.experiences import experience_covariance
    from vtr.navigation.localization import LocalizationEstimate
    from vtr.state.trajectory import adjoint

    taught, exp_a, exp_b = 5, (3 << 32) | 7, (4 << 32) | 2
    T_x_trunk = np.stack(
        [
            np.eye(4),
            exp_se3(np.array([0.01, 0.02, 0.0, 0.3, -0.1, 0.2])),
            exp_se3(np.array([0.0, -0.02, 0.01, -0.2, 0.1, 0.1])),
        ]
    )
    slot = np.array([0, 0, 1, 1, 2])
    n = len(slot)
    sub = _landmarkless_submap(np.array([taught, exp_a, exp_b]), T_x_trunk, slot)
    np.testing.assert_array_equal(sub.experience, [0, 0, 3, 3, 4])
    P = {exp_a: np.diag([1e-6] * 3 + [1e-4] * 3), exp_b: np.diag([4e-6] * 3 + [9e-4] * 3)}
    T = exp_se3(np.array([0.02, 0.0, -0.01, 0.5, 0.0, 1.0]))
    matched = np.arange(n)
    est = LocalizationEstimate(T, np.eye(6) * 1e-6, n, matched, np.array([True, True, True, False, False]))
    A = adjoint(T @ np.linalg.inv(T_x_trunk[1]))
    np.testing.assert_allclose(experience_covariance(sub, est, P.get), A @ P[exp_a] @ A.T, atol=1e-15)  # b: no inlier
    only_taught = LocalizationEstimate(T, np.eye(6), n, matched, np.array([True, True, False, False, False]))
    assert not experience_covariance(sub, only_taught, P.get).any()


def test_taught_covariance_is_the_trunk_s_edge_moved_to_the_leaf():
    """The taught map's own placement: the trunk's temporal edge moved to the leaf, whichever taught vertices gave
    the inliers (the window placed their landmarks consistently; the trunk's stored pose is off from them by its
    edge's error); nothing when only experience vertices gave inliers."""
    from vtr.geometry import exp_se3
    from vtr.navigation.experiences import taught_covariance
    from vtr.navigation.localization import LocalizationEstimate
    from vtr.state.trajectory import adjoint

    trunk, before, experience = (1 << 32) | 5, (1 << 32) | 4, (3 << 32) | 7
    T_x_trunk = np.stack(
        [
            np.eye(4),
            exp_se3(np.array([0.0, 0.01, 0.0, 0.0, 0.0, 2.0])),
            exp_se3(np.array([0.01, 0.0, 0.0, 0.3, 0.0, 0.1])),
        ]
    )
    slot = np.array([0, 0, 1, 2, 2])
    n = len(slot)
    sub = _landmarkless_submap(np.array([trunk, before, experience]), T_x_trunk, slot)
    P = {trunk: np.diag([1e-6] * 3 + [4e-5, 2e-5, 1e-4]), before: np.diag([2e-6] * 3 + [1e-5, 1e-5, 9e-5])}
    T = exp_se3(np.array([0.0, 0.02, 0.0, 0.5, 0.0, 1.0]))
    matched = np.arange(n)
    expected = adjoint(T) @ P[trunk] @ adjoint(T).T
    taught_inliers = (
        [True, True, True, True, False],
        [True, False, False, False, False],
        [False, False, True, True, True],  # a neighbour's and an experience's
    )
    for inlier in taught_inliers:
        est = LocalizationEstimate(T, np.eye(6) * 1e-6, n, matched, np.array(inlier))
        got = taught_covariance(sub, est, P.get)
        np.testing.assert_allclose(got, expected, atol=1e-15)
        assert np.all(np.linalg.eigvalsh(got) > 0)
    nothing = LocalizationEstimate(T, np.eye(6), n, matched, np.array([False, False, False, True, True]))
    assert not taught_covariance(sub, nothing, P.get).any()


def test_experience_place_words_are_stored_and_give_the_place_vectors(forward):
    """A repeat stores the place-recognition words of the experiences it scored (derived data), and the vectors
    made from them are those of the vertices' own descriptors."""
    from vtr.navigation.experiences import WORDS_KEY, _decode_words
    from vtr.navigation.place import route_place_index

    root, multi, _ = forward
    cfg = Config()
    with Map.open(root / "experiences.vtrmap") as m:
        place = route_place_index(m, cfg.place, cfg.run.seed)
        sub = ExperienceSubmaps(
            m, m.taught_path(), cfg.experiences, cfg.localization.neighbour_vertices, m.camera, place
        )
        digest = sub._vocabulary_digest()
        stored = [r for r in sub.trusted if m.derived(f"{WORDS_KEY}/{r}/{digest}") is not None]
        assert set(stored) == {f.run for f in multi[:-1]}  # scored by the flights after them
        vid = int(sub.links.vertex_id[sub.links.run == multi[0].run][3])
        d = m.vertex(vid).frame.features.descriptors
        np.testing.assert_allclose(sub.vector(vid), place.vector(d), atol=1e-12)
        # place recognition with experiences: every taught vertex scores at least its own score, and better where
        # the experience vertex was localized
        places = sub.places()
        s, own = places.scores(d), place.scores(d)
        assert np.all(s >= own - 1e-12) and s.max() > own.max()
        assert places.query(d, 3).indices[0] == int(np.argmax(s)) and len(places) == len(place)
    assert _decode_words(b"not an archive") is None and _decode_words(None) is None
