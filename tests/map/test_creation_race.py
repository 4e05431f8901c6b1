"""Two processes creating one map at the same instant: exactly one wins, its map survives and
opens, the other gets the one-line "already exists" error and removes nothing but its own
temporary file. Real processes released together by a barrier, repeated over many trials."""

from __future__ import annotations

import multiprocessing as mp
import os

import numpy as np
import pytest
from test_map import CAMERA, make_frame, pose

from vtr.errors import MapError
from vtr.map import Map

TRIALS = 20
VERTICES = 3  # the winner writes these after creating, while the loser fails and cleans up
JOIN_TIMEOUT_S = 60


def _create(path: str, barrier, results) -> None:
    barrier.wait()
    try:
        with Map.create(path, CAMERA) as m:
            run = m.begin_run("teach", source=f"pid {os.getpid()}")
            rng = np.random.default_rng(0)
            for i in range(VERTICES):
                frame = make_frame(rng, 30, index=i)
                m.add_vertex(run, frame.t_ns, pose(float(i)), frame)
        results.put(("won", os.getpid()))
    except MapError as err:
        results.put(("lost", str(err)))
    except BaseException as err:  # noqa: BLE001 - reported to the test
        results.put(("crashed", f"{type(err).__name__}: {err}"))


@pytest.mark.parametrize("writers", [2, 3])
def test_racing_creators_one_wins_map_survives(tmp_path, writers):
    ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
    outcomes = []
    for trial in range(TRIALS if writers == 2 else TRIALS // 2):
        path = tmp_path / f"race{trial}.vtrmap"
        barrier, results = ctx.Barrier(writers), ctx.Queue()
        procs = [ctx.Process(target=_create, args=(str(path), barrier, results)) for _ in range(writers)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(JOIN_TIMEOUT_S)
            assert p.exitcode == 0
        got = sorted(results.get(timeout=5) for _ in procs)
        outcomes.append(got)
        won = [g for g in got if g[0] == "won"]
        lost = [g for g in got if g[0] == "lost"]
        assert len(won) == 1 and len(lost) == writers - 1, got
        for _, message in lost:
            assert message.startswith(f"{path} already exists: refusing to overwrite a map")
            assert "\n" not in message
        with Map.open(path) as m:  # the winner's map survived, complete
            [info] = m.runs()
            assert (info.state, info.n_vertices, info.source) == ("finished", VERTICES, f"pid {won[0][1]}")
        # nothing left beside it: no -wal/-shm, no temporary files of the losers
        assert sorted(
            p.name
            for p in tmp_path.iterdir()
            if p.name.startswith(f"race{trial}.") or p.name.startswith(f".race{trial}.")
        ) == [path.name]
    assert len(outcomes) == (TRIALS if writers == 2 else TRIALS // 2)


def test_file_system_without_hard_links_still_creates_exclusively(tmp_path, monkeypatch):
    """Where os.link is not supported (FAT, some network shares) the map is created with O_EXCL and
    the schema copied in: still exclusive, still one self-contained file."""

    def no_links(src, dst):
        raise PermissionError(1, "Operation not permitted", str(src))

    monkeypatch.setattr(os, "link", no_links)
    path = tmp_path / "route.vtrmap"
    with Map.create(path, CAMERA) as m:
        run = m.begin_run("teach")
        frame = make_frame(np.random.default_rng(0), 10)
        m.add_vertex(run, 0, pose(0.0), frame)
        with pytest.raises(MapError, match="another process is writing this map"):
            Map.open(path, "a")
    with pytest.raises(MapError, match="already exists"):
        Map.create(path, CAMERA)
    assert [p.name for p in tmp_path.iterdir()] == ["route.vtrmap"]
    with Map.open(path) as m:
        assert [(r.state, r.n_vertices) for r in m.runs()] == [("finished", 1)]
