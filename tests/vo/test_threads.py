"""Threads inside one run: the same results bit for bit with 1 and 2 threads; background decoding."""

from __future__ import annotations

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
    cfg = Config()
    cfg.features.threads = threads
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
        for _ in range(2):          # the pool is reused frame after frame
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
        outputs[threads] = [(folder / "repeat" / name).read_bytes()
                            for name in ("localization.csv", "landmarks.csv", "trajectory_tum.txt")]
    assert outputs[1] == outputs[2]
