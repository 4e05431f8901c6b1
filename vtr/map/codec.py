"""The vertex codec: a :class:`~vtr.types.StereoFrame` to the bytes a map vertex stores, and back.

A vertex blob is the magic ``VTRV`` plus the codec version byte, the feature count N (uint32 LE),
the ``RAW_ARRAYS`` as raw little-endian bytes, then zlib of the other arrays' raw little-endian
bytes, each in ``VERTEX_ARRAYS`` order (fixed dtypes and trailing shapes, so no per-array header is
needed and decoding is a few slices). What is stored of a frame: feature pixels ``uv``, ``octave``,
ORB ``descriptors``, right-image column ``u_right`` and triangulated ``points``; the vertex row
holds its time and source frame index. Feature responses (detector scores, used only while
selecting features) are not stored: a decoded frame has zeros there.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from ..errors import MapError
from ..types import Features, StereoFrame

DESCRIPTOR_BYTES = 32
# Arrays of a vertex, in blob order, with their stored dtype and trailing shape.
VERTEX_ARRAYS: tuple[tuple[str, np.dtype, tuple[int, ...]], ...] = (
    ("uv", np.dtype("<f8"), (2,)),
    ("octave", np.dtype("<i4"), ()),
    ("descriptors", np.dtype("u1"), (DESCRIPTOR_BYTES,)),
    ("u_right", np.dtype("<f8"), ()),
    ("points", np.dtype("<f8"), (3,)),
)
BLOB_MAGIC = b"VTRV\x02"  # vertex blob: magic + codec version
COUNT_BYTES = 4  # uint32 feature count after the magic
RAW_ARRAYS = ("descriptors",)  # stored as is: binary descriptors are random bits, zlib gains nothing
ROW_BYTES = {name: dtype.itemsize * int(np.prod(tail, dtype=np.int64)) for name, dtype, tail in VERTEX_ARRAYS}


@dataclass(frozen=True)
class EncodedFrame:
    """A frame ready for the map: its ``blob``, the ``frame`` as stored (stored dtypes, read-only) and counts."""

    blob: bytes
    frame: StereoFrame
    n_features: int
    n_landmarks: int


def readonly(a: np.ndarray) -> np.ndarray:
    """``a`` marked read-only (arrays the map hands out may be shared through its vertex cache)."""
    a.flags.writeable = False
    return a


def _frame(t_ns: int, index: int, arrays: dict[str, np.ndarray]) -> StereoFrame:
    a = {name: readonly(v) for name, v in arrays.items()}
    response = readonly(np.zeros(len(a["uv"])))
    return StereoFrame(
        int(t_ns), int(index), Features(a["uv"], a["octave"], response, a["descriptors"]), a["u_right"], a["points"]
    )


def _stored_arrays(frame: StereoFrame) -> dict[str, np.ndarray]:
    """The stored arrays of a frame, validated and converted to their stored dtypes (``MapError`` on
    inconsistent lengths or shapes, or on a lossy dtype conversion)."""
    try:
        src = {
            "uv": frame.features.uv,
            "octave": frame.features.octave,
            "descriptors": frame.features.descriptors,
            "u_right": frame.u_right,
            "points": frame.points,
        }
    except AttributeError as err:
        raise MapError(f"frame: not a StereoFrame ({err})") from err
    out: dict[str, np.ndarray] = {}
    n = None
    for name, dtype, tail in VERTEX_ARRAYS:
        a = np.asarray(src[name])
        if a.ndim != 1 + len(tail) or a.shape[1:] != tail:
            raise MapError(
                f"frame {name}: expected shape (N, {', '.join(map(str, tail))}) got {a.shape}"
                if tail
                else f"frame {name}: expected shape (N,), got {a.shape}"
            )
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


MAX_LANDMARK_M = 1e6  # no stereo pair triangulates a point this far (1000 km): damaged data


def check_landmarks_in_front(points: np.ndarray, where: str) -> None:
    """``MapError`` unless every landmark (finite row) lies in front of its camera (z > 0) and nearer than
    ``MAX_LANDMARK_M``, and no row holds an infinity (a feature without a landmark is all NaN): stereo
    triangulation only yields such points, so another one means damaged or foreign data."""
    inf = np.isinf(points).any(axis=1)
    if inf.any():
        k = int(np.argmax(inf))
        raise MapError(f"{where}: landmark {k} of {len(points)} is infinite ({points[k].tolist()})")
    far = np.abs(np.nan_to_num(points)).max(axis=1) > MAX_LANDMARK_M if len(points) else np.zeros(0, bool)
    if far.any():
        k = int(np.argmax(far))
        raise MapError(
            f"{where}: landmark {k} of {len(points)} is {np.abs(points[k]).max():.3g} m away "
            f"(more than {MAX_LANDMARK_M:g} m)"
        )
    z = points[:, 2]
    behind = np.isfinite(points).all(axis=1) & ~(z > 0)
    if behind.any():
        k = int(np.argmax(behind))
        raise MapError(f"{where}: landmark {k} of {len(points)} is behind its camera (z = {z[k]:.6g} m)")


def pack_arrays(arrays: dict[str, np.ndarray], level: int) -> bytes:
    """The blob of arrays already in their stored dtypes and shapes (no checks: :func:`encode_frame`
    validates a frame first; tests use this alone to write damaged data)."""
    n = len(arrays["uv"])

    def raw(name: str, dtype: np.dtype) -> bytes:
        return np.ascontiguousarray(arrays[name], dtype=dtype).tobytes()

    stored = b"".join(raw(name, dtype) for name, dtype, _t in VERTEX_ARRAYS if name in RAW_ARRAYS)
    packed = b"".join(raw(name, dtype) for name, dtype, _t in VERTEX_ARRAYS if name not in RAW_ARRAYS)
    return BLOB_MAGIC + np.uint32(n).astype("<u4").tobytes() + stored + zlib.compress(packed, level)


def encode_frame(frame: StereoFrame, t_ns: int, level: int) -> EncodedFrame:
    """Validate and encode ``frame`` (zlib ``level``); the stored frame carries the vertex time ``t_ns``."""
    arrays = _stored_arrays(frame)
    n = len(arrays["uv"])
    blob = pack_arrays(arrays, level)
    n_landmarks = int(np.count_nonzero(np.all(np.isfinite(arrays["points"]), axis=1)))
    return EncodedFrame(blob, _frame(t_ns, getattr(frame, "index", -1), arrays), n, n_landmarks)


def decode_frame(blob: bytes, t_ns: int, index: int, where: str) -> StereoFrame:
    """Inverse of :func:`encode_frame` (read-only arrays); ``MapError`` naming ``where`` on a damaged blob."""
    if not blob.startswith(BLOB_MAGIC):
        raise MapError(f"{where}: vertex data has an unknown encoding")
    head = len(BLOB_MAGIC) + COUNT_BYTES
    if len(blob) < head:
        raise MapError(f"{where}: vertex data is damaged (truncated)")
    n = int(np.frombuffer(blob, dtype="<u4", count=1, offset=len(BLOB_MAGIC))[0])
    raw_size = n * sum(ROW_BYTES[name] for name in RAW_ARRAYS)
    try:
        packed = zlib.decompress(blob[head + raw_size :])
    except zlib.error as err:
        raise MapError(f"{where}: vertex data is damaged ({err})") from err
    if len(blob) < head + raw_size or len(packed) != n * sum(ROW_BYTES.values()) - raw_size:
        raise MapError(f"{where}: vertex data is damaged ({len(blob)} bytes for {n} features)")
    out, offsets = {}, {"raw": head, "packed": 0}
    for name, dtype, tail in VERTEX_ARRAYS:
        source, key = (blob, "raw") if name in RAW_ARRAYS else (packed, "packed")
        size = n * ROW_BYTES[name]
        out[name] = (
            np.frombuffer(source, dtype=dtype, count=size // dtype.itemsize, offset=offsets[key])
            .reshape((n, *tail))
            .astype(dtype.newbyteorder("="), copy=False)
        )
        offsets[key] += size
    check_landmarks_in_front(out["points"], where)
    return _frame(t_ns, index, out)
