"""Repeat.steps: localizations on their own thread or the caller's, in order, the map whole on every way out."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from vtr.app.pipeline import teach_command
from vtr.config import Config
from vtr.errors import MapError, interruption
from vtr.io import open_source
from vtr.map import Map
from vtr.navigation.repeat import Repeat

FRAMES = list(range(1, 24, 2))


@pytest.fixture(scope="module")
def taught(kitti_clip, tmp_path_factory):
    path = tmp_path_factory.mktemp("pipeline") / "route.vtrmap"
    teach_command(kitti_clip, path, "0:24:2", Config())
    return path


def _config(threads: int, thread: str = "own") -> Config:
    return Config().replace("features", threads=threads).replace("localization", thread=thread)


def _copy(path, tmp_path, name="route.vtrmap"):
    dst = tmp_path / name
    dst.write_bytes(path.read_bytes())
    return dst


def _key(step):
    loc = step.localization
    return (
        step.vertex_id,
        step.T_teach_frame.tobytes(),
        step.odometry.T_world_frame.tobytes(),
        None if loc is None else (loc.trunk_id, loc.inliers, loc.T_leaf_trunk.tobytes(), loc.covariance.tobytes()),
    )


def _repeat_vertices_whole(m: Map, run: int) -> list[int]:
    """The run's vertex ids, checked consecutive and chained by temporal edges (one per consecutive pair)."""
    ids = [int(i) for i in m.vertex_ids(run)]
    assert ids == list(range(ids[0], ids[0] + len(ids)))
    temporal = [(e.from_id, e.to_id) for e in m.edges(run, "temporal")]
    assert temporal == list(zip(ids[:-1], ids[1:], strict=True))
    return ids


def _threads(prefix: str) -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(prefix)]


def test_steps_on_two_threads_equal_process_frame(kitti_clip, taught, tmp_path):
    """process_frame frame after frame, and steps with the localizations on the caller's thread or on their own
    (1 and 2 feature threads): the same steps bit for bit."""
    keys, latest = {}, {}
    for case in ("process_frame", (1, "caller"), (1, "own"), (2, "own"), (2, "caller")):
        threads, thread = (1, "own") if case == "process_frame" else case
        name = "pf" if case == "process_frame" else f"t{threads}{thread}"
        with open_source(kitti_clip) as src, Map.open(_copy(taught, tmp_path, f"{name}.vtrmap"), "a") as m:
            rp = Repeat(m, _config(threads, thread), "test")
            frames = rp.odometry.stereo.frames(src.iter_frames(FRAMES))
            if case == "process_frame":
                steps = [rp.process_frame(f) for f in frames]  # the one-frame-at-a-time API
            else:
                steps = list(rp.steps(frames))
            keys[name] = [_key(s) for s in steps]
            latest[name] = rp.latest.T_leaf_trunk.tobytes()
            assert all(s.localization_seconds > 0 for s in steps if s.localization is not None)
            m.finish_run()
            _repeat_vertices_whole(m, rp.run)
    assert len(keys["pf"]) == len(FRAMES)
    for name in keys:
        assert keys[name] == keys["pf"], name
        assert latest[name] == latest["pf"], name
    assert not _threads("vtr-localize")


@pytest.mark.parametrize(("threads", "thread"), [(1, "caller"), (1, "own"), (2, "own")])
def test_a_failed_vertex_write_stops_every_later_one(kitti_clip, taught, tmp_path, monkeypatch, threads, thread):
    """The write of the 4th vertex fails (a full disk) on the writer thread: the error comes out at its step, after
    the three steps before it, and no later vertex is written although the odometry (and with 2 threads the
    localization) had run ahead."""
    import time

    real, calls = Map.add_leaf, []

    def add_leaf(self, *args, **kwargs):
        calls.append(threading.current_thread().name)
        if len(calls) == 4:
            time.sleep(0.5)  # the odometry runs ahead meanwhile: the next vertices wait in the queue
            raise MapError("disk full (injected)")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Map, "add_leaf", add_leaf)
    with open_source(kitti_clip) as src, Map.open(_copy(taught, tmp_path), "a") as m:
        rp = Repeat(m, _config(threads, thread), "test")
        got, localized = [], []
        with pytest.raises(MapError, match="disk full"):
            for step in rp.steps(rp.odometry.stereo.frames(src.iter_frames(FRAMES))):
                got.append(step.vertex_id)
                if step.localization is not None and step.localization.success:
                    localized.append(step.vertex_id)
        assert len(got) == 3 and len(calls) == 4  # nothing attempted after the failure
        assert all(name.startswith("vtr-map-write") for name in calls)  # committed off the frame's thread
        assert _repeat_vertices_whole(m, rp.run) == got
        # the first leaf is an unconfirmed place candidate, the next ones are localized
        assert localized == got[1:]
        assert [e.from_id for e in m.edges(rp.run, "spatial")] == localized
        assert [r.leaf_id for r in m.localization_records(rp.run)] == got  # one record per vertex, no more
    assert not _threads("vtr-localize") and not _threads("vtr-map-write")


def test_closing_the_stream_early_leaves_whole_vertices(kitti_clip, taught, tmp_path):
    with open_source(kitti_clip) as src, Map.open(_copy(taught, tmp_path), "a") as m:
        rp = Repeat(m, _config(2), "test")
        stream = rp.steps(rp.odometry.stereo.frames(src.iter_frames(FRAMES)))
        got = [next(stream).vertex_id for _ in range(3)]
        stream.close()  # as an error or Ctrl-C in the consumer does
        assert not _threads("vtr-localize") and not _threads("vtr-map-write")
        ids = _repeat_vertices_whole(m, rp.run)
        assert ids[:3] == got and len(ids) <= 3 + 2 + 1  # at most the look-ahead beyond the last step
        spatial = [e.from_id for e in m.edges(rp.run, "spatial")]
        assert spatial == ids[1:]  # every written vertex localized but the first (unconfirmed)
    assert np.all(np.diff(got) == 1)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("where", ["localization", "consumer"])
def test_ctrl_c_anywhere_leaves_one_report_row_per_vertex(kitti_clip, taught, tmp_path, monkeypatch, threads, where):
    """A real SIGINT arriving while the 5th vertex is localized (just after its map write), or in the
    consumer right after it took a step: the run loop ends with KeyboardInterrupt and every vertex the map
    holds was handed to the consumer exactly once (with one thread the signal used to land between the write
    and the report: one vertex more in the map than rows in localization.csv)."""
    import signal

    from vtr.app.repeat_run import run_repeat

    real, calls = Repeat._localize, []

    def localize(self, *args, **kwargs):
        calls.append(1)
        if where == "localization" and len(calls) == 5:
            signal.raise_signal(signal.SIGINT)  # handled by Python at the next bytecode: inside the step
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Repeat, "_localize", localize)
    rows: list[int] = []

    def on_step(step):
        if step.localization is not None:
            rows.append(step.vertex_id)
            if where == "consumer" and len(rows) == 5:
                signal.raise_signal(signal.SIGINT)

    with open_source(kitti_clip) as src, Map.open(_copy(taught, tmp_path), "a") as m:
        rp = Repeat(m, _config(threads), "test")
        with pytest.raises(BaseException) as err:  # KeyboardInterrupt, or what it interrupted (vtr's CLI: both)
            run_repeat(rp, rp.odometry.stereo.frames(src.iter_frames(FRAMES)), on_step=on_step)
        assert interruption(err.value) is not None, err.value
        ids = _repeat_vertices_whole(m, rp.run)
    assert len(rows) >= 5 and rows == ids  # each written vertex reported once, in order
    assert not _threads("vtr-localize")
