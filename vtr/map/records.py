"""Plain records of the pose-graph map, vertex ids and input validation (the vertex codec is :mod:`vtr.map.codec`).

Vertex ids follow VT&R3: ``id = run << 32 | index``, so an id names its run and its position in
that run. Transforms are 4x4 float64 ``T_a_b`` (frame b into frame a); covariances are 6x6 in
GTSAM's tangent order ``[rotation (rad), translation (m)]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ConfigError, MapError, Terminated, interruption
from ..geometry import check_covariance as check_pose_covariance
from ..geometry import check_se3
from .codec import readonly as _readonly

if TYPE_CHECKING:
    from ..types import StereoFrame

RUN_SHIFT = 32  # bits of the index part of a vertex id
INDEX_MASK = (1 << RUN_SHIFT) - 1
MAX_RUN = (1 << 31) - 1  # ids stay positive signed int64 (SQLite INTEGER)

EDGE_KINDS = ("temporal", "spatial")
RUN_KINDS = ("teach", "repeat")
# Lifecycle of a run. Stored: running -> finished | aborted (final). Reported also: interrupted,
# a run still marked running whose writer is gone (killed), so it will never finish.
RUN_RUNNING, RUN_FINISHED, RUN_ABORTED, RUN_INTERRUPTED = "running", "finished", "aborted", "interrupted"
RUN_STATES = (RUN_RUNNING, RUN_FINISHED, RUN_ABORTED, RUN_INTERRUPTED)
REASON_MAX_CHARS = 500  # an abort reason is one line, cut to this length


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
    def of(
        cls, vid: int, t_ns: int, T_world_vertex: np.ndarray, T_vehicle_sensor: np.ndarray, frame: StereoFrame
    ) -> VertexRecord:
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


def abort_reason(exc: BaseException) -> str:
    """The one-line reason an exception gives an aborted run."""
    exc = interruption(exc) or exc
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted by Ctrl-C (SIGINT)"
    if isinstance(exc, Terminated):
        return "terminated by SIGTERM"
    text = str(exc)
    return one_line_reason(f"{type(exc).__name__}: {text}" if text else type(exc).__name__)


GRAVITY_META_KEY = "gravity_up"
#: an up vector shorter than this has no direction
MIN_UP_NORM = 1e-9


def check_gravity_up(value: object, what: str, error: type[Exception] = ConfigError) -> np.ndarray:
    """``value`` as a unit 3-vector (an up direction); ``error`` naming ``what`` unless three finite numbers of
    non-zero length."""
    try:
        up = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise error(f"{what}: expected three numbers, got {value!r}") from None
    if up.shape != (3,) or not np.all(np.isfinite(up)):
        raise error(f"{what}: expected three finite numbers, got {value!r}")
    n = float(np.linalg.norm(up))
    if n < MIN_UP_NORM:
        raise error(f"{what}: the up direction has zero length")
    return up / n


def utc_now() -> str:
    """Now as ISO-8601 UTC seconds (a run's ``created``, the map's)."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def check_run_row(path: Path, r: tuple) -> None:
    """``MapError`` (one line) when a row of the runs table is not what vtr writes (a damaged file)."""
    rid, kind, privileged, source, created, state, reason = r[:7]
    problem = None
    if isinstance(rid, bool) or not isinstance(rid, int) or not 0 <= rid < 1 << 31:
        problem = f"id {rid!r}"
    elif kind not in RUN_KINDS:
        problem = f"kind {kind!r}"
    elif privileged not in (0, 1):
        problem = f"privileged {privileged!r}"
    elif not isinstance(source, str) or not isinstance(created, str) or not isinstance(reason, str):
        problem = "a text field that is not text"
    elif state not in (RUN_RUNNING, RUN_FINISHED, RUN_ABORTED):
        problem = f"state {state!r}"
    if problem is not None:
        raise MapError(
            f"{path}: the runs table is damaged (run {rid!r}: {problem}); the map file was changed after vtr wrote it"
        )


def run_range(run: int) -> tuple[int, int]:
    """Smallest and largest vertex id of a run."""
    lo = int(run) << RUN_SHIFT
    return lo, lo | INDEX_MASK


def check_int(value: object, what: str, minimum: int | None = None) -> int:
    """``value`` as an int (numpy integers too, never a bool), at least ``minimum``; else ``MapError`` naming
    ``what``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise MapError(f"{what}: expected an integer, got {type(value).__name__}")
    value = int(value)
    if minimum is not None and value < minimum:
        raise MapError(f"{what}: {value} < {minimum}")
    return value
