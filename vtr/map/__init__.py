"""Durable pose-graph map of teach and repeat runs (one SQLite file).

Typical use (teach, then a repeat localized against it)::

    with Map.create("route.vtrmap", camera) as m:
        run = m.begin_run("teach", source="datasets/kitti06_clip")
        for kf in keyframes:                      # vtr.types.Keyframe
            m.add_keyframe(run, kf)               # vertex + temporal edge, one transaction
    with Map.open("route.vtrmap", "a") as m:
        m.check_camera(camera)
        rep = m.begin_run("repeat")
        leaf = m.add_keyframe(rep, keyframe)     # the leaf
        m.add_edge(leaf.id, trunk_id, T_leaf_trunk, covariance, "spatial", inliers)
        # (vtr's repeat writes a leaf with its spatial edge and localization record in one transaction instead:
        #  m.add_leaf(rep, keyframe, Leaf(record, SpatialEdge(...))), vtr.map.localizations)
        taught = m.taught_path()                  # TaughtPath: ids, T_world_vertex, t_ns
        frame = m.vertex(trunk_id).frame          # the trunk's StereoFrame

Leaving a ``with`` block normally finishes the open run; an exception (Ctrl-C and SIGTERM too)
records it aborted with the reason (``RunInfo.state``: running, finished, aborted, interrupted).
See docs/map.md: the file, its modules (store, writing, reading, database, lock, localizations, writer, schema,
codec) and their rules.
"""

from .database import copy_map_file
from .path import TaughtPath
from .records import EdgeRecord, RunInfo, VertexRecord, split_vertex_id, vertex_id
from .store import MAP_FORMAT_VERSION, VERTEX_CACHE_SIZE, Map, check_gravity_up

__all__ = [
    "MAP_FORMAT_VERSION",
    "VERTEX_CACHE_SIZE",
    "EdgeRecord",
    "Map",
    "RunInfo",
    "TaughtPath",
    "VertexRecord",
    "check_gravity_up",
    "copy_map_file",
    "split_vertex_id",
    "vertex_id",
]
