"""Threads inside one run: the same results bit for bit with 1 and 2 threads; background decoding."""

from __future__ import annotations

import os
import sys
import threading

import numpy as np
import pytest

from vtr.app.pipeline import run_odometry
from vtr.config import Config
from vtr.errors import ConfigError
from vtr.io import open_source
from vtr.parallel import available_cores, prefetch, resolve_threads
from vtr.vo.stereo import StereoProcessor


def _config(threads: int) -> Config:
    cfg = Config().replace("features", threads=threads)
    return cfg


def test_odometry_identical_with_one_and_two_threads(kitti_clip):
    runs = {}
    for threads in (1, 2):
        with open_source(kitti_clip) as src:
            records, poses, _ = run_odometry(src, list(range(0, 24)), _config(threads))
        runs[threads] = (records, poses)
    (rec1, poses1), (rec2, poses2) = runs[1], runs[2]
    assert len(poses1) == 24
    assert np.array_equal(poses1, poses2)
    assert rec1 == rec2


def test_stereo_frame_identical_with_threads(kitti_clip):
    with open_source(kitti_clip) as src:
        images = src[7]
        one = StereoProcessor(src.camera, _config(1).features, Config().stereo).process(images)
        two = StereoProcessor(src.camera, _config(2).features, Config().stereo)
        assert two._pool is not None
        for _ in range(2):  # the pool is reused frame after frame
            frame = two.process(images)
            assert np.array_equal(frame.features.uv, one.features.uv)
            assert np.array_equal(frame.features.descriptors, one.features.descriptors)
            assert np.array_equal(frame.points, one.points, equal_nan=True)


def test_resolve_threads():
    assert resolve_threads(0) == available_cores() >= 1
    assert resolve_threads(3) == 3
    with pytest.raises(ConfigError, match="features.threads"):
        resolve_threads(-1)


def test_prefetch_keeps_order_and_runs_in_the_background():
    producers = set()

    def items():
        for i in range(50):
            producers.add(threading.current_thread().name)
            yield i

    assert list(prefetch(items(), 3)) == list(range(50))
    assert producers == {"vtr-prefetch"}
    assert list(prefetch(iter(range(5)), 0)) == list(range(5))


def test_prefetch_raises_the_producers_error_at_its_item():
    def items():
        yield 1
        yield 2
        raise ValueError("frame 3 is corrupt")

    got = []
    with pytest.raises(ValueError, match="frame 3"):
        for x in prefetch(items(), 2):
            got.append(x)
    assert got == [1, 2]


def test_prefetch_stops_the_producer_when_the_consumer_stops():
    produced = []

    def items():
        for i in range(10_000):
            produced.append(i)
            yield i

    gen = prefetch(items(), 2)
    assert next(gen) == 0
    gen.close()
    assert not any(t.name == "vtr-prefetch" for t in threading.enumerate())
    assert len(produced) < 10


def test_teach_and_repeat_identical_with_one_and_two_threads(kitti_clip, tmp_path):
    """Frames stereo-processed ahead on a background thread while the previous one is tracked and localized."""
    from vtr.app.pipeline import repeat_command, teach_command

    outputs = {}
    for threads in (1, 2):
        folder = tmp_path / f"t{threads}"
        teach_command(kitti_clip, folder / "route.vtrmap", "0:24:2", _config(threads))
        repeat_command(kitti_clip, folder / "route.vtrmap", folder / "repeat", "1:24:2", _config(threads))
        outputs[threads] = [
            (folder / "repeat" / name).read_bytes()
            for name in ("localization.csv", "landmarks.csv", "trajectory_tum.txt")
        ]
    assert outputs[1] == outputs[2]


def _threads_named(prefix: str) -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(prefix)]


def test_frames_on_the_pool_equal_one_thread_in_order(kitti_clip):
    """Two workers process whole frames at once; the stream comes out in order, bit for bit the one-thread run."""
    with open_source(kitti_clip) as src:
        idx = list(range(0, 12))
        one = list(StereoProcessor(src.camera, _config(1).features, Config().stereo).frames(src.iter_frames(idx)))
        workers: set[str] = set()
        two = StereoProcessor(src.camera, _config(2).features, Config().stereo)
        original = two._process_on_worker

        def spy(images):
            workers.add(threading.current_thread().name)
            return original(images)

        two._process_on_worker = spy  # type: ignore[method-assign]
        got = list(two.frames(src.iter_frames(idx)))
    assert [f.index for f in got] == idx
    assert len(workers) == 2 and all(name.startswith("vtr-stereo") for name in workers)
    for a, b in zip(one, got, strict=True):
        assert np.array_equal(a.features.uv, b.features.uv)
        assert np.array_equal(a.features.descriptors, b.features.descriptors)
        assert np.array_equal(a.u_right, b.u_right, equal_nan=True)
        assert np.array_equal(a.points, b.points, equal_nan=True)
    assert not _threads_named("vtr-stereo") and not _threads_named("vtr-prefetch")


def test_frames_on_the_pool_raise_a_bad_frame_at_its_place(kitti_clip):
    """A frame that fails on a worker is raised when the consumer reaches it, after every frame before it."""
    from vtr.errors import DataError
    from vtr.types import StereoImages

    with open_source(kitti_clip) as src:

        def images():
            for i in range(8):
                im = src[i]
                yield StereoImages(im.t_ns, im.index, im.left[:, :-4], im.right) if i == 5 else im

        processor = StereoProcessor(src.camera, _config(2).features, Config().stereo)
        got = []
        with pytest.raises(DataError, match="frame 5"):
            for frame in processor.frames(images()):
                got.append(frame.index)
    assert got == [0, 1, 2, 3, 4]
    assert not _threads_named("vtr-stereo") and not _threads_named("vtr-prefetch")


def test_frames_on_the_pool_stop_when_the_consumer_stops(kitti_clip):
    with open_source(kitti_clip) as src:
        processor = StereoProcessor(src.camera, _config(2).features, Config().stereo)
        read = []

        def images():
            for i in range(len(src)):
                read.append(i)
                yield src[i]

        stream = processor.frames(images())
        assert next(stream).index == 0
        stream.close()  # type: ignore[attr-defined]
    assert not _threads_named("vtr-stereo") and not _threads_named("vtr-prefetch")
    assert len(read) < 10  # bounded look-ahead: the clip has 51 frames


@pytest.mark.skipif(not hasattr(os, "setpriority") or sys.platform != "linux", reason="per-thread niceness is Linux's")
def test_background_threads_run_at_the_configured_niceness():
    """Relative to the thread's own niceness, capped at 19 (never an attempt to raise a priority)."""
    from vtr.parallel import background_thread

    seen = {}

    def worker(start, niceness):
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + start)
        base = os.getpriority(os.PRIO_PROCESS, tid)
        background_thread(niceness)
        seen[start, niceness] = base, os.getpriority(os.PRIO_PROCESS, tid)

    for start, niceness in ((0, 0), (0, 7), (15, 7)):
        t = threading.Thread(target=worker, args=(start, niceness))
        t.start()
        t.join()
    caller = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    assert seen[0, 0] == (caller, caller)
    assert seen[0, 7] == (caller, min(caller + 7, 19))
    base, after = seen[15, 7]
    assert after == min(base + 7, 19) and after >= base
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == caller  # the caller is untouched
