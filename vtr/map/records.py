"""Plain records of the pose-graph map, vertex ids and input validation (the vertex codec is :mod:`vtr.map.codec`).

Vertex ids follow VT&R3: ``id = run << 32 | index``, so an id names its run and its position in
that run. Transforms are 4x4 float64 ``T_a_b`` (frame b into frame a); covariances are 6x6 in
GTSAM's tangent order ``[rotation (rad), translation (m)]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import MapError
from ..geometry import check_covariance as check_pose_covariance
from ..geometry import check_se3
from .codec import readonly as _readonly

if TYPE_CHECKING:
    from ..types import StereoFrame

RUN_SHIFT = 32                       # bits of the index part of a vertex id
INDEX_MASK = (1 << RUN_SHIFT) - 1
MAX_RUN = (1 << 31) - 1              # ids stay positive signed int64 (SQLite INTEGER)

EDGE_KINDS = ("temporal", "spatial")
RUN_KINDS = ("teach", "repeat")
# Lifecycle of a run. Stored: running -> finished | aborted (final). Reported also: interrupted,
# a run still marked running whose writer is gone (killed), so it will never finish.
RUN_RUNNING, RUN_FINISHED, RUN_ABORTED, RUN_INTERRUPTED = "running", "finished", "aborted", "interrupted"
RUN_STATES = (RUN_RUNNING, RUN_FINISHED, RUN_ABORTED, RUN_INTERRUPTED)
REASON_MAX_CHARS = 500               # an abort reason is one line, cut to this length


def vertex_id(run: int, index: int) -> int:
    """Vertex id of keyframe ``index`` of run ``run`` (``run << 32 | index``)."""
    run, index = int(run), int(index)
    if not 0 <= run <= MAX_RUN:
        raise MapError(f"run id {run} outside [0, {MAX_RUN}]")
    if not 0 <= index <= INDEX_MASK:
        raise MapError(f"vertex index {index} outside [0, {INDEX_MASK}]")
    return (run << RUN_SHIFT) | index


def split_vertex_id(vid: int) -> tuple[int, int]:
    """``(run, index)`` of a vertex id."""
    vid = int(vid)
    if vid < 0:
        raise MapError(f"invalid vertex id {vid}")
    return vid >> RUN_SHIFT, vid & INDEX_MASK


@dataclass(frozen=True)
class VertexRecord:
    """One keyframe of the map: its stereo frame and poses.

    ``T_world_vertex`` (4x4) is the pose of the vertex's left rectified camera in its run's world
    frame (the run's first camera frame); ``T_vehicle_sensor`` (4x4) places that camera on the
    vehicle. ``frame`` is the stored :class:`~vtr.types.StereoFrame` (see :mod:`vtr.map.codec`: its
    ``t_ns`` is the vertex time, ``index`` the source frame index, feature responses are not stored).
    Arrays returned by the map are read-only (they may be shared through the vertex cache).
    """

    id: int
    run: int
    index: int
    t_ns: int
    T_world_vertex: np.ndarray
    T_vehicle_sensor: np.ndarray
    frame: StereoFrame

    @classmethod
    def of(cls, vid: int, t_ns: int, T_world_vertex: np.ndarray, T_vehicle_sensor: np.ndarray,
           frame: StereoFrame) -> VertexRecord:
        """The record of vertex ``vid`` (run and index from the id; poses made read-only)."""
        run, index = split_vertex_id(vid)
        return cls(vid, run, index, int(t_ns), _readonly(T_world_vertex), _readonly(T_vehicle_sensor), frame)

    @property
    def landmark_mask(self) -> np.ndarray:
        """(N,) bool: features with a finite 3-D landmark."""
        return np.all(np.isfinite(self.frame.points), axis=1)

    @property
    def n_features(self) -> int:
        return len(self.frame.features)

    @property
    def position_world(self) -> np.ndarray:
        """(3,) camera centre in the run's world frame, metres."""
        return self.T_world_vertex[:3, 3]


@dataclass(frozen=True)
class EdgeRecord:
    """A relative transform between two vertices.

    ``T_from_to`` maps to-vertex camera coordinates into the from-vertex camera frame;
    ``covariance`` (6x6, [rot, trans]) is its uncertainty; ``kind`` is ``"temporal"`` (odometry,
    consecutive vertices of one run) or ``"spatial"`` (localization, across runs); ``inliers`` the
    number of feature inliers behind the estimate.
    """

    from_id: int
    to_id: int
    kind: str
    T_from_to: np.ndarray
    covariance: np.ndarray
    inliers: int


@dataclass(frozen=True)
class RunInfo:
    """One run (session) of the map: a teach (privileged by default) or a repeat.

    ``created`` is an ISO-8601 UTC time. ``state`` is one of ``RUN_STATES``: ``running`` (a live
    session is writing it), ``finished`` (its session ended in order: the run is complete),
    ``aborted`` (its session ended on an error, Ctrl-C or SIGTERM; ``reason`` says which) or
    ``interrupted`` (still marked running but no process is writing the map: its writer was
    killed). Only a finished teach run is a complete route.
    """

    id: int
    kind: str
    privileged: bool
    source: str
    created: str
    n_vertices: int
    state: str = RUN_FINISHED
    reason: str = ""

    @property
    def finished(self) -> bool:
        return self.state == RUN_FINISHED

    def describe(self) -> str:
        """``state`` with its reason, e.g. ``aborted (KeyboardInterrupt: Ctrl-C)``."""
        return f"{self.state} ({self.reason})" if self.reason else self.state


def one_line_reason(text: str) -> str:
    """An abort reason as stored: one line, at most ``REASON_MAX_CHARS`` characters, never empty."""
    line = " ".join(str(text).split()) or "unknown reason"
    return line if len(line) <= REASON_MAX_CHARS else line[: REASON_MAX_CHARS - 3] + "..."


# ---------------------------------------------------------------- validation


def check_transform(T: np.ndarray, what: str) -> np.ndarray:
    """A finite 4x4 rigid transform as float64, or ``MapError`` naming ``what``."""
    return check_se3(T, what, error=MapError)


def check_covariance(C: np.ndarray, what: str) -> np.ndarray:
    """A finite, symmetric, positive semi-definite 6x6 matrix as float64, or ``MapError``."""
    return check_pose_covariance(C, what, error=MapError)


def matrix_blob(T: np.ndarray) -> bytes:
    """Little-endian float64 bytes of a matrix (row-major)."""
    return np.ascontiguousarray(T, dtype="<f8").tobytes()


def blob_matrix(blob: bytes, shape: tuple[int, int]) -> np.ndarray:
    """Inverse of :func:`matrix_blob` (a fresh, read-only float64 array)."""
    return _readonly(np.frombuffer(blob, dtype="<f8").astype(np.float64).reshape(shape))
