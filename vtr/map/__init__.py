"""Durable pose-graph map of teach and repeat runs (one SQLite file).

Typical use (teach, then a repeat localized against it)::

    with Map.create("route.vtrmap", camera) as m:
        run = m.begin_run("teach", source="datasets/kitti06_clip")
        for kf in keyframes:                      # vtr.types.Keyframe
            m.add_keyframe(run, kf)               # vertex + temporal edge, one transaction
    with Map.open("route.vtrmap", "a") as m:
        m.check_camera(camera)
        rep = m.begin_run("repeat")
        leaf = m.add_vertex(rep, t_ns, T_world_leaf, frame)
        m.add_edge(leaf.id, trunk_id, T_leaf_trunk, covariance, "spatial", inliers)

Leaving a ``with`` block normally finishes the open run; an exception (Ctrl-C and SIGTERM too)
records it aborted with the reason (``RunInfo.state``: running, finished, aborted, interrupted).
See :mod:`vtr.map.store` for durability, lifecycle and immutability rules, :mod:`vtr.map.lock` for
the single-writer lock, :mod:`vtr.map.schema` for the file layout.
"""

from .records import EdgeRecord, RunInfo, VertexRecord, split_vertex_id, vertex_id
from .store import MAP_FORMAT_VERSION, VERTEX_CACHE_SIZE, Map

__all__ = [
    "MAP_FORMAT_VERSION",
    "VERTEX_CACHE_SIZE",
    "EdgeRecord",
    "Map",
    "RunInfo",
    "VertexRecord",
    "split_vertex_id",
    "vertex_id",
]
