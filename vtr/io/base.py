"""One frame-source interface for every logged format.

A ``FrameSource`` yields ``StereoImages`` (timestamped, rectified, greyscale) and carries the
``StereoCamera`` that describes them. Sources are sequences (random access by index, ``len``)
and context managers; images are read lazily so a long log is never held in memory.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import StereoCamera
from ..errors import DataError
from ..types import StereoImages


@dataclass(frozen=True)
class SourceOptions:
    """How to open a SOURCE: ``format`` forces a reader (default: detect); the topic names and
    ``allow_unpaired`` apply to ROS bags only (an error for any other format when set)."""

    format: str | None = None
    left_topic: str | None = None
    right_topic: str | None = None
    left_info_topic: str | None = None
    right_info_topic: str | None = None
    allow_unpaired: bool = False

    def bag_kwargs(self) -> dict[str, str | bool | None]:
        """Keyword arguments of ``RosbagSource`` that differ from its defaults."""
        return {
            k: v
            for k, v in (
                ("left_topic", self.left_topic),
                ("right_topic", self.right_topic),
                ("left_info_topic", self.left_info_topic),
                ("right_info_topic", self.right_info_topic),
                ("allow_unpaired", self.allow_unpaired),
            )
            if v
        }


#: a reference pose further than this from a frame's time does not give that frame's gravity (ns)
GRAVITY_TRUTH_MATCH_NS = 50_000_000


@dataclass(frozen=True)
class GroundTruth:
    """Reference poses of the left rectified camera: ``T_world_cam`` (N, 4, 4) at ``t_ns`` (N,)."""

    t_ns: np.ndarray
    T_world_cam: np.ndarray


class FrameSource(ABC, Sequence):
    """Random-access sequence of rectified stereo pairs with their calibration."""

    path: Path
    camera: StereoCamera
    format_name: str = "?"
    gravity_aligned_truth: bool = False  # the ground truth's world has z up (gravity_up reads it)

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def timestamps(self) -> np.ndarray:
        """int64 ns time of every frame, in order."""

    @abstractmethod
    def _load(self, index: int) -> StereoImages: ...

    def __getitem__(self, index: int) -> StereoImages:  # type: ignore[override]
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} outside {self.path} ({n} frames)")
        return self._load(index % n)

    def __iter__(self) -> Iterator[StereoImages]:
        for i in range(len(self)):
            yield self._load(i)

    def iter_frames(self, indices: Iterable[int] | None = None) -> Iterator[StereoImages]:
        """Frames at ``indices`` (all by default) in order; streaming sources override this to read
        them in one sequential pass."""
        for i in range(len(self)) if indices is None else indices:
            yield self[i]

    def ground_truth(self) -> GroundTruth | None:
        """Reference trajectory of the left rectified camera, when the format carries one."""
        return None

    def gravity_up(self, index: int) -> np.ndarray | None:
        """Up (opposite to gravity) in the left rectified camera of frame ``index`` (unit 3-vector), when the
        source knows it: formats whose ground-truth world is gravity-aligned, z up (``gravity_aligned_truth``,
        e.g. EuRoC) give it from the reference pose nearest the frame (within ``GRAVITY_TRUTH_MATCH_NS``);
        None otherwise (a KITTI folder knows no mount)."""
        gt = self.ground_truth() if self.gravity_aligned_truth else None
        if gt is None or len(gt.t_ns) == 0:
            return None
        t = int(self.timestamps()[index])
        j = int(np.argmin(np.abs(np.asarray(gt.t_ns, np.int64) - t)))
        if abs(int(gt.t_ns[j]) - t) > GRAVITY_TRUTH_MATCH_NS:
            return None
        return np.asarray(gt.T_world_cam[j], float)[:3, :3].T @ np.array([0.0, 0.0, 1.0])

    def close(self) -> None:
        """Release files or handles held by the source."""

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def check_image(self, img: np.ndarray | None, where: str | Path) -> np.ndarray:
        """Validate a decoded image against the calibration; raise ``DataError`` naming ``where``."""
        if img is None:
            raise DataError(f"{where}: cannot decode image (missing or corrupt file)")
        h, w = img.shape[:2]
        if (w, h) != self.camera.size:
            raise DataError(
                f"{where}: image is {w}x{h} but the calibration says {self.camera.width}x{self.camera.height}"
            )
        return img


def parse_frame_range(spec: str | None, n: int, source: str = "source") -> list[int]:
    """Indices selected by ``START:STOP:STEP`` (Python slice semantics) over ``n`` frames.

    Raises ``DataError`` when the selection is malformed or falls outside the source (the message names it as
    ``frames '<spec>'``: the command line's ``--frames`` and a batch manifest's ``frames`` alike).
    """
    if not spec:
        return list(range(n))
    parts = spec.split(":")
    if len(parts) > 3:
        raise DataError(f"frames {spec!r}: expected START:STOP:STEP")
    try:
        vals = [int(p) if p.strip() else None for p in parts] + [None] * (3 - len(parts))
    except ValueError as err:
        raise DataError(f"frames {spec!r}: not integers") from err
    start, stop, step = vals
    if step is not None and step <= 0:
        raise DataError(f"frames {spec!r}: STEP must be positive")
    if start is not None and not 0 <= start < n:
        raise DataError(f"frames {spec!r}: START {start} outside {source} with {n} frames")
    if stop is not None and not 0 <= stop <= n:
        raise DataError(f"frames {spec!r}: STOP {stop} outside {source} with {n} frames")
    idx = list(range(n))[slice(start, stop, step)]
    if not idx:
        raise DataError(f"frames {spec!r}: selects no frame of {source} ({n} frames)")
    return idx
