"""What stored map data must be, and the one way damage is reported: finite rigid poses (orthonormal rotation,
last row 0 0 0 1), times strictly increasing within each run, vertices only of runs the runs table holds, and
temporal edges that agree with the poses they join (a moved vertex, checksums or not). See docs/map.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import MapError
from ..geometry import inv_T
from .database import Connection
from .records import RUN_SHIFT, blob_matrix, split_vertex_id

if TYPE_CHECKING:
    from .path import TaughtPath

ROTATION_TOL = 1e-6  # |R'R - I| and |det R - 1| allowed (float64 poses composed many times)
EDGE_TOL_M = 1e-6  # a temporal edge agrees with its poses to this (metres / unit rotation)


def damaged(where: str, vid: object, what: str) -> MapError:
    try:
        run, index = split_vertex_id(int(vid))  # type: ignore[call-overload]
        name = f"vertex {vid} (run {run}, index {index})"
    except (TypeError, ValueError):
        name = f"vertex {vid!r}"
    return MapError(
        f"{where}: {name} is damaged ({what}); the map file was changed after vtr wrote it "
        "(`vtr map check` lists what else is)"
    )


def check_poses(where: str, ids: np.ndarray, T: np.ndarray) -> None:
    """``MapError`` unless every pose is finite, a rotation (orthonormal, det +1) and has last row 0 0 0 1."""
    if len(T) == 0:
        return
    bad = ~np.isfinite(T).all(axis=(1, 2))
    if bad.any():
        raise damaged(where, int(ids[np.argmax(bad)]), "its pose is not finite")
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    last = np.abs(T[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    bad = (err > ROTATION_TOL) | (np.abs(det - 1.0) > ROTATION_TOL) | (last > 0)
    if bad.any():
        k = int(np.argmax(bad))
        raise damaged(
            where, int(ids[k]), f"its pose is not a rigid transform (|R'R - I| = {err[k]:.3g}, det R = {det[k]:.6g})"
        )


def check_taught_path(where: str, path: TaughtPath) -> None:
    """What a taught path must be: finite rigid poses, times strictly increasing within each run."""
    check_poses(where, path.ids, path.T_world_vertex)
    run = path.ids >> RUN_SHIFT
    same = run[1:] == run[:-1]
    back = same & (np.diff(path.t_ns) <= 0)
    if back.any():
        k = int(np.argmax(back)) + 1
        raise damaged(
            where,
            int(path.ids[k]),
            f"its time {int(path.t_ns[k])} ns is not after the previous vertex's {int(path.t_ns[k - 1])} ns",
        )


def check_path_edges(conn: Connection, where: str, path: TaughtPath) -> None:
    """``MapError`` when a temporal edge between taught vertices disagrees with their poses (``add_vertex``
    computes one from the other: a difference is a moved vertex or a damaged edge, checksums or not)."""
    if len(path) < 2:
        return
    lo, hi = int(path.ids.min()), int(path.ids.max())
    rows = conn.execute(
        "SELECT from_id, to_id, T_from_to FROM edges WHERE kind = 'temporal' AND from_id BETWEEN ? "
        "AND ? AND to_id BETWEEN ? AND ?",
        (lo, hi, lo, hi),
    ).fetchall()
    index = {int(v): i for i, v in enumerate(path.ids)}
    T = path.T_world_vertex
    for a, b, blob in rows:
        i, j = index.get(int(a)), index.get(int(b))
        if i is None or j is None:
            continue
        E = blob_matrix(blob, (4, 4))
        d = np.abs(inv_T(T[i]) @ T[j] - E)
        if not np.isfinite(E).all() or d.max() > EDGE_TOL_M * max(1.0, float(np.abs(E[:3, 3]).max())):
            raise damaged(
                where,
                int(b),
                f"its pose disagrees with the temporal edge from {a} by "
                f"{float(d[:3, 3].max()):.3g} m (a moved vertex or a damaged edge)",
            )


def check_vertex_runs(conn: Connection, where: str) -> None:
    """``MapError`` when a vertex belongs to a run the runs table does not hold, or its id and run disagree."""
    r = conn.execute(
        "SELECT v.id, v.run FROM vertices v LEFT JOIN runs r ON r.id = v.run "
        "WHERE r.id IS NULL OR v.id <> ((v.run << 32) | v.idx) LIMIT 1"
    ).fetchone()
    if r is not None:
        raise damaged(
            where, r[0], f"it belongs to run {r[1]!r}, which the runs table does not hold or its id does not encode"
        )
