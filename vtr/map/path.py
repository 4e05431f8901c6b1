"""The taught path: the privileged vertices a repeat follows, as one record.

``TaughtPath`` is what the map hands the localization chain, the controller log and reports:
vertex ids, their camera poses ``T_world_vertex`` and times, in path order (run, then index).
Each pose is in its run's world frame (the run's first camera frame); see ``docs/frames.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from ..errors import MapError
from ..geometry import inv_T
from .records import split_vertex_id

if TYPE_CHECKING:
    from scipy.spatial import cKDTree


def _frozen(a: np.ndarray, dtype: type) -> np.ndarray:
    out: np.ndarray = np.array(a, dtype=dtype, copy=True)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class TaughtPath:
    """Privileged vertices in path order: ``ids`` (N,) int64, ``T_world_vertex`` (N, 4, 4), ``t_ns`` (N,) int64.

    Arrays are read-only copies. Path *indices* (0..N-1) address vertices along the path; ``ids`` are
    map vertex ids (``run << 32 | index``).
    """

    ids: np.ndarray
    T_world_vertex: np.ndarray
    t_ns: np.ndarray
    _index: dict[int, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        ids, T, t = np.asarray(self.ids), np.asarray(self.T_world_vertex), np.asarray(self.t_ns)
        if ids.ndim != 1 or T.shape != (len(ids), 4, 4) or t.shape != ids.shape:
            raise MapError(
                f"taught path: ids {ids.shape}, T_world_vertex {T.shape} and t_ns {t.shape} "
                "do not describe the same N vertices"
            )
        object.__setattr__(self, "ids", _frozen(ids, np.int64))
        object.__setattr__(self, "T_world_vertex", _frozen(T, np.float64))
        object.__setattr__(self, "t_ns", _frozen(t, np.int64))
        object.__setattr__(self, "_index", {int(v): i for i, v in enumerate(self.ids)})

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame, metres."""
        return self.T_world_vertex[:, :3, 3]

    def index(self, vertex_id: int) -> int:
        """Path index of a vertex id (``MapError`` if the vertex is not on the path)."""
        i = self._index.get(int(vertex_id))
        if i is None:
            run, idx = split_vertex_id(vertex_id)
            raise MapError(f"vertex {vertex_id} (run {run}, index {idx}) is not on the privileged path")
        return i

    def window(self, index: int, back: int, forward: int) -> tuple[int, int]:
        """``(lo, hi)``: path indices from ``back`` before ``index`` to ``forward`` after it, ``hi`` exclusive,
        clipped at the ends of the path."""
        return max(0, int(index) - int(back)), min(len(self), int(index) + int(forward) + 1)

    def segment(self, lo: int, hi: int) -> TaughtPath:
        """The sub-path of indices ``lo`` to ``hi`` (exclusive)."""
        return TaughtPath(self.ids[lo:hi], self.T_world_vertex[lo:hi], self.t_ns[lo:hi])

    @cached_property
    def _tree(self) -> cKDTree:
        from scipy.spatial import cKDTree  # scipy.spatial costs ~0.2 s to import: only nearest-vertex queries need it

        return cKDTree(self.positions)

    def nearest(self, position_world: np.ndarray, k: int = 1) -> np.ndarray:
        """(min(k, N),) int64 path indices of the vertices nearest to ``position_world`` (3,), nearest first."""
        p = np.asarray(position_world, dtype=float).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise MapError(f"nearest: position must be 3 finite numbers, got {position_world!r}")
        _d, idx = self._tree.query(p, k=min(int(k), len(self)))
        return np.atleast_1d(idx).astype(np.int64)

    def arc_length_m(self, T_sensor_body: np.ndarray | None = None) -> np.ndarray:
        """(N,) distance along the path from its first vertex, metres, between camera centres (or between the
        origins of the body that ``T_sensor_body`` places relative to the camera)."""
        T = self.T_world_vertex if T_sensor_body is None else self.T_world_vertex @ T_sensor_body
        step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(step)])

    def T_world_localized(self, vertex_id: int, T_leaf_vertex: np.ndarray) -> np.ndarray:
        """World pose of a leaf camera localized against path vertex ``vertex_id`` (map id):
        ``T_world_vertex @ inv(T_leaf_vertex)``."""

        return self.T_world_vertex[self.index(vertex_id)] @ inv_T(T_leaf_vertex)
