"""The full check of a map (``vtr map check MAP``): SQLite's own integrity check, the runs table, every vertex's
checksums and blob, the taught path, and every temporal edge against the poses it joins (catches a moved vertex in
a map without checksums too). See docs/map.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import MapError
from ..geometry import inv_T
from .checksums import checksummed
from .damage import EDGE_TOL_M, check_poses, check_taught_path, check_vertex_runs, damaged
from .records import RUN_SHIFT
from .store import Map


@dataclass(frozen=True)
class CheckReport:
    """What :func:`check_map` looked at."""

    runs: int
    vertices: int
    edges: int
    checksums: bool  # the map has checksums (created by a vtr with them)


def check_map(m: Map) -> CheckReport:
    """The full check of an open map ``m``; ``MapError`` on the first damage found."""
    where = str(m.path)
    with m.file.connection() as conn:
        result = conn.execute("PRAGMA integrity_check").fetchall()
        if [tuple(r) for r in result] != [("ok",)]:
            raise MapError(f"{where}: the SQLite file is damaged ({str(result[0][0]).splitlines()[0]})")
        sums = checksummed(conn, where)
    runs = m.runs()  # checks the runs table
    with m.file.connection() as conn:
        check_vertex_runs(conn, where)
    n_vertices = 0
    for run in runs:
        ids, T = m.poses(run.id)  # checksums of the rows, when the map has them
        check_poses(where, ids, T)
        _, t = m.timestamps(run.id)
        back = np.diff(t) <= 0
        if back.any():
            raise damaged(where, int(ids[int(np.argmax(back)) + 1]), "its time is not after the previous vertex's")
        for vid in ids:
            m.vertex(int(vid), cached=False)  # checksum of the blob, then the codec's checks
        n_vertices += len(ids)
    if any(r.privileged for r in runs):
        check_taught_path(where, m.taught_path())
    edges = m.edges()
    pose: dict[int, np.ndarray] = {}
    for run in runs:
        ids, T = m.poses(run.id)
        pose.update(zip(ids.tolist(), T, strict=True))
    for e in edges:
        if not (np.isfinite(e.T_from_to).all() and np.isfinite(e.covariance).all()):
            raise MapError(f"{where}: {e.kind} edge {e.from_id}->{e.to_id} is damaged (not finite)")
        if e.kind == "temporal":
            if e.from_id >> RUN_SHIFT != e.to_id >> RUN_SHIFT or e.from_id not in pose or e.to_id not in pose:
                raise MapError(f"{where}: temporal edge {e.from_id}->{e.to_id} does not join two vertices of a run")
            d = inv_T(pose[e.from_id]) @ pose[e.to_id] - e.T_from_to
            if np.abs(d).max() > EDGE_TOL_M * max(1.0, float(np.abs(e.T_from_to[:3, 3]).max())):
                raise damaged(
                    where,
                    e.to_id,
                    f"its pose disagrees with the temporal edge from {e.from_id} by "
                    f"{float(np.abs(d[:3, 3]).max()):.3g} m (a moved vertex)",
                )
    return CheckReport(len(runs), n_vertices, len(edges), sums)
