"""Plain records of the pose-graph map, vertex ids, input validation and the vertex-array codec.

Vertex ids follow VT&R3: ``id = run << 32 | index``, so an id names its run and its position in
that run. Transforms are 4x4 float64 ``T_a_b`` (frame b into frame a); covariances are 6x6 in
GTSAM's tangent order ``[rotation (rad), translation (m)]``.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from ..errors import MapError
from ..geometry import check_se3

RUN_SHIFT = 32                       # bits of the index part of a vertex id
INDEX_MASK = (1 << RUN_SHIFT) - 1
MAX_RUN = (1 << 31) - 1              # ids stay positive signed int64 (SQLite INTEGER)

EDGE_KINDS = ("temporal", "spatial")
RUN_KINDS = ("teach", "repeat")

COV_SYMMETRY_RTOL = 1e-9             # |C - C^T| allowed, relative to max |C|
COV_PSD_RTOL = 1e-9                  # smallest eigenvalue allowed, relative to the largest (negative)

DESCRIPTOR_BYTES = 32
# Arrays of a vertex, in blob order, with their stored dtype and trailing shape.
VERTEX_ARRAYS: tuple[tuple[str, np.dtype, tuple[int, ...]], ...] = (
    ("uv", np.dtype("<f8"), (2,)),
    ("octave", np.dtype("<i4"), ()),
    ("descriptors", np.dtype("u1"), (DESCRIPTOR_BYTES,)),
    ("u_right", np.dtype("<f8"), ()),
    ("points", np.dtype("<f8"), (3,)),
)
BLOB_MAGIC = b"VTRV\x02"             # vertex blob: magic + codec version (layout in ``encode_arrays``)
COUNT_BYTES = 4                      # uint32 feature count after the magic
RAW_ARRAYS = ("descriptors",)        # stored as is: binary descriptors are random bits, zlib gains nothing
ROW_BYTES = {name: dtype.itemsize * int(np.prod(tail, dtype=np.int64)) for name, dtype, tail in VERTEX_ARRAYS}


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


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


@dataclass(frozen=True)
class VertexRecord:
    """One keyframe of the map.

    ``T_world_vertex`` (4x4) is the pose of the vertex's left rectified camera in its run's world
    frame (the run's first camera frame); ``T_vehicle_sensor`` (4x4) places that camera on the
    vehicle. ``uv`` (N, 2) px, ``octave`` (N,) int32, ``descriptors`` (N, 32) uint8 ORB bits,
    ``u_right`` (N,) px (NaN without a stereo match), ``points`` (N, 3) metres in the vertex camera
    frame (NaN rows without depth); ``frame_index`` the index of the source frame (``StereoFrame.index``).
    Arrays returned by the map are read-only (they may be shared
    through the vertex cache).
    """

    id: int
    run: int
    index: int
    t_ns: int
    T_world_vertex: np.ndarray
    T_vehicle_sensor: np.ndarray
    uv: np.ndarray
    octave: np.ndarray
    descriptors: np.ndarray
    u_right: np.ndarray
    points: np.ndarray
    frame_index: int = -1

    @property
    def landmark_mask(self) -> np.ndarray:
        """(N,) bool: features with a finite 3-D landmark."""
        return np.all(np.isfinite(self.points), axis=1)

    @property
    def n_features(self) -> int:
        return len(self.uv)

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

    ``created`` is an ISO-8601 UTC time; ``finished`` is true once the session that wrote the run
    closed the map (a run cut short by a crash stays unfinished).
    """

    id: int
    kind: str
    privileged: bool
    source: str
    created: str
    n_vertices: int
    finished: bool = False


# ---------------------------------------------------------------- validation


def check_transform(T, what: str) -> np.ndarray:
    """A finite 4x4 rigid transform as float64, or ``MapError`` naming ``what``."""
    return check_se3(T, what, error=MapError)


def check_covariance(C, what: str) -> np.ndarray:
    """A finite, symmetric, positive semi-definite 6x6 matrix as float64, or ``MapError``."""
    try:
        C = np.array(C, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise MapError(f"{what}: not a numeric 6x6 matrix ({err})") from err
    if C.shape != (6, 6):
        raise MapError(f"{what}: expected a 6x6 matrix, got shape {C.shape}")
    if not np.all(np.isfinite(C)):
        raise MapError(f"{what}: contains NaN or infinity")
    scale = float(np.max(np.abs(C))) if C.size else 0.0
    if np.max(np.abs(C - C.T)) > COV_SYMMETRY_RTOL * max(scale, 1e-300):
        raise MapError(f"{what}: not symmetric")
    eig = np.linalg.eigvalsh(C)
    if eig[0] < -COV_PSD_RTOL * max(float(eig[-1]), 0.0):
        raise MapError(f"{what}: not positive semi-definite (smallest eigenvalue {eig[0]:.3g})")
    return C


def frame_arrays(frame) -> dict[str, np.ndarray]:
    """The stored arrays of a ``StereoFrame``, validated and converted to their stored dtypes.

    Raises ``MapError`` on inconsistent lengths or shapes, or on a lossy dtype conversion.
    """
    try:
        src = {
            "uv": frame.features.uv, "octave": frame.features.octave,
            "descriptors": frame.features.descriptors, "u_right": frame.u_right, "points": frame.points,
        }
    except AttributeError as err:
        raise MapError(f"frame: not a StereoFrame ({err})") from err
    out: dict[str, np.ndarray] = {}
    n = None
    for name, dtype, tail in VERTEX_ARRAYS:
        a = np.asarray(src[name])
        if a.ndim != 1 + len(tail) or a.shape[1:] != tail:
            raise MapError(f"frame {name}: expected shape (N, {', '.join(map(str, tail))}) got {a.shape}"
                           if tail else f"frame {name}: expected shape (N,), got {a.shape}")
        n = len(a) if n is None else n
        if len(a) != n:
            raise MapError(f"frame {name}: {len(a)} rows, but uv has {n}")
        if a.dtype.kind not in "fiub":
            raise MapError(f"frame {name}: unsupported dtype {a.dtype}")
        if dtype.kind in "iu" and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise MapError(f"frame {name}: values do not fit the stored dtype {dtype}")
        b = np.array(a, dtype=dtype, order="C", copy=True)
        both_float = dtype.kind == "f" and a.dtype.kind == "f"
        if a.dtype != dtype and not np.array_equal(b, a, equal_nan=both_float):
            raise MapError(f"frame {name}: values do not fit the stored dtype {dtype}")
        out[name] = b
    check_landmarks_in_front(out["points"], "frame points")
    return out


def check_landmarks_in_front(points: np.ndarray, where: str) -> None:
    """``MapError`` unless every landmark (finite row) lies in front of its camera (z > 0): stereo
    triangulation only yields such points, so another one means damaged or foreign data."""
    z = points[:, 2]
    behind = np.isfinite(points).all(axis=1) & ~(z > 0)
    if behind.any():
        k = int(np.argmax(behind))
        raise MapError(f"{where}: landmark {k} of {len(points)} is behind its camera (z = {z[k]:.6g} m)")


def count_landmarks(points: np.ndarray) -> int:
    return int(np.count_nonzero(np.all(np.isfinite(points), axis=1)))


# ---------------------------------------------------------------- codec


def encode_arrays(arrays: dict[str, np.ndarray], level: int) -> bytes:
    """Blob of the vertex arrays: magic, the feature count N (uint32 LE), the ``RAW_ARRAYS`` as raw
    bytes, then zlib (``level``) of the other arrays' raw little-endian bytes, each in
    ``VERTEX_ARRAYS`` order (fixed dtypes and trailing shapes, so no per-array header is needed and
    decoding is a few slices)."""
    n = len(arrays["uv"])

    def raw(name: str, dtype: np.dtype) -> bytes:
        return np.ascontiguousarray(arrays[name], dtype=dtype).tobytes()

    stored = b"".join(raw(name, dtype) for name, dtype, _t in VERTEX_ARRAYS if name in RAW_ARRAYS)
    packed = b"".join(raw(name, dtype) for name, dtype, _t in VERTEX_ARRAYS if name not in RAW_ARRAYS)
    return BLOB_MAGIC + np.uint32(n).astype("<u4").tobytes() + stored + zlib.compress(packed, level)


def decode_arrays(blob: bytes, where: str) -> dict[str, np.ndarray]:
    """Inverse of :func:`encode_arrays` (read-only arrays); ``MapError`` naming ``where`` on a damaged blob."""
    if not blob.startswith(BLOB_MAGIC):
        raise MapError(f"{where}: vertex data has an unknown encoding")
    head = len(BLOB_MAGIC) + COUNT_BYTES
    if len(blob) < head:
        raise MapError(f"{where}: vertex data is damaged (truncated)")
    n = int(np.frombuffer(blob, dtype="<u4", count=1, offset=len(BLOB_MAGIC))[0])
    raw_size = n * sum(ROW_BYTES[name] for name in RAW_ARRAYS)
    try:
        packed = zlib.decompress(blob[head + raw_size:])
    except zlib.error as err:
        raise MapError(f"{where}: vertex data is damaged ({err})") from err
    if len(blob) < head + raw_size or len(packed) != n * sum(ROW_BYTES.values()) - raw_size:
        raise MapError(f"{where}: vertex data is damaged ({len(blob)} bytes for {n} features)")
    out, offsets = {}, {"raw": head, "packed": 0}
    for name, dtype, tail in VERTEX_ARRAYS:
        source, key = (blob, "raw") if name in RAW_ARRAYS else (packed, "packed")
        size = n * ROW_BYTES[name]
        out[name] = np.frombuffer(source, dtype=dtype, count=size // dtype.itemsize, offset=offsets[key]).reshape(
            (n, *tail)).astype(dtype.newbyteorder("="), copy=False)
        offsets[key] += size
    check_landmarks_in_front(out["points"], where)
    return out


def matrix_blob(T: np.ndarray) -> bytes:
    """Little-endian float64 bytes of a matrix (row-major)."""
    return np.ascontiguousarray(T, dtype="<f8").tobytes()


def blob_matrix(blob: bytes, shape: tuple[int, int]) -> np.ndarray:
    """Inverse of :func:`matrix_blob` (a fresh, read-only float64 array)."""
    return _readonly(np.frombuffer(blob, dtype="<f8").astype(np.float64).reshape(shape))


def make_vertex_record(vid: int, t_ns: int, T_world_vertex: np.ndarray, T_vehicle_sensor: np.ndarray,
                       arrays: dict[str, np.ndarray], frame_index: int = -1) -> VertexRecord:
    run, index = split_vertex_id(vid)
    return VertexRecord(
        id=vid, run=run, index=index, t_ns=int(t_ns), frame_index=int(frame_index),
        T_world_vertex=_readonly(T_world_vertex), T_vehicle_sensor=_readonly(T_vehicle_sensor),
        **{name: _readonly(arrays[name]) for name, _d, _t in VERTEX_ARRAYS},
    )
