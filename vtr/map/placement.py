"""A run's vertices and landmarks in the map frame: the world frame of the first teach run (its first left camera),
other runs placed through their spatial edges to it (what exports and point clouds show). See docs/map.md.
"""

from __future__ import annotations

import numpy as np

from ..geometry import inv_T
from .records import RUN_SHIFT
from .store import Map


def poses_in_map_frame(map_: Map, run: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """``(ids, T_map_vertex (N, 4, 4), aligned)`` of a run in the map frame (first teach run's world).

    A run other than the reference is placed through its spatial edges to the reference run:
    each vertex goes through the localized vertex nearest to it in index order
    (``T_map_v = T_map_t T_t_l T_l_v``, with ``T_l_v`` from the run's own odometry). Without any
    such edge the run stays in its own world frame and ``aligned`` is false.
    """
    ids, T_run_v = map_.poses(run)
    ref = map_.reference_run()
    if ref == run:
        return ids, T_run_v, True
    if ref is None or len(ids) == 0:
        return ids, T_run_v, False
    ref_ids, T_map_t = map_.poses(ref)
    links = []  # (index in run, T_map_run via this edge, inliers)
    for e in map_.edges(run=run, kind="spatial"):
        rf, rt = e.from_id >> RUN_SHIFT, e.to_id >> RUN_SHIFT
        if rf == run and rt == ref:
            l_id, t_id, T_l_t = e.from_id, e.to_id, e.T_from_to
        elif rf == ref and rt == run:
            l_id, t_id, T_l_t = e.to_id, e.from_id, inv_T(e.T_from_to)
        else:
            continue
        i_l = int(np.searchsorted(ids, l_id))
        i_t = int(np.searchsorted(ref_ids, t_id))
        T_map_run = T_map_t[i_t] @ inv_T(T_l_t) @ inv_T(T_run_v[i_l])
        links.append((i_l, T_map_run, e.inliers))
    if not links:
        return ids, T_run_v, False
    links.sort(key=lambda x: (x[0], -x[2]))
    link_idx = np.array([x[0] for x in links])
    keep = np.concatenate([[True], np.diff(link_idx) > 0])
    link_idx = link_idx[keep]
    link_T = np.stack([x[1] for x, k in zip(links, keep, strict=True) if k])
    # for each vertex, the link nearest in index order
    ar = np.arange(len(ids))
    right = np.clip(np.searchsorted(link_idx, ar), 0, len(link_idx) - 1)
    left = np.clip(right - 1, 0, len(link_idx) - 1)
    choice = np.where(np.abs(ar - link_idx[left]) <= np.abs(link_idx[right] - ar), left, right)
    return ids, link_T[choice] @ T_run_v, True


def landmarks_in_map_frame(map_: Map, run: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(points (M, 3) metres, run_of_point (M,) int64)``: every vertex landmark in the map frame.

    The map frame is the world frame of the first teach run; other runs are placed through
    their spatial edges (see :func:`poses_in_map_frame`), or left in their own world frame when
    unlinked. Streams feature data vertex by vertex (no cache pollution).
    """
    run_ids = [r.id for r in map_.runs()] if run is None else [map_.run(run).id]
    pts, owner = [], []
    for r in run_ids:
        ids, T_map_v, _aligned = poses_in_map_frame(map_, r)
        for i, rec in enumerate(map_.iter_vertices(r)):
            p = rec.frame.points[rec.landmark_mask]
            pts.append(p @ T_map_v[i, :3, :3].T + T_map_v[i, :3, 3])
            owner.append(np.full(len(p), r, dtype=np.int64))
    if not pts:
        return np.empty((0, 3)), np.empty(0, dtype=np.int64)
    return np.concatenate(pts), np.concatenate(owner)


__all__ = ["landmarks_in_map_frame", "poses_in_map_frame"]
