"""Export of map landmarks as a coloured point cloud (PLY through open3d, imported lazily).

Frame: the world frame of the first teach run (its first left camera: x right, y down, z forward),
metres. Other runs are placed through their spatial edges to that run (see
:func:`vtr.map.placement.poses_in_map_frame`); a run without such an edge stays in its own world frame,
which the summary reports as ``aligned=False``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception_model.frames import LEVEL_CAMERA_UP, T_g_map_from_up
from perception_model.outputs import replace_file

from ..errors import MapError
from .placement import landmarks_in_map_frame, poses_in_map_frame
from .store import Map

PLY_SUFFIX = ".ply"
# One colour per run (RGB in [0, 1]), cycled: matplotlib's tab10 palette.
RUN_COLOURS = np.array(
    [
        [0.122, 0.467, 0.706],
        [1.000, 0.498, 0.055],
        [0.173, 0.627, 0.173],
        [0.839, 0.153, 0.157],
        [0.580, 0.404, 0.741],
        [0.549, 0.337, 0.294],
        [0.890, 0.467, 0.761],
        [0.498, 0.498, 0.498],
        [0.737, 0.741, 0.133],
        [0.090, 0.745, 0.812],
    ]
)


@dataclass(frozen=True)
class RunExport:
    """Landmarks exported from one run, its colour and whether it is in the map frame."""

    run: int
    kind: str
    points: int
    aligned: bool
    colour: tuple[float, float, float]


def run_colour(order: int) -> np.ndarray:
    """RGB colour (3,) in [0, 1] of the ``order``-th run."""
    return RUN_COLOURS[order % len(RUN_COLOURS)]


def export_landmarks_ply(
    map_: Map, path: str | Path, runs: list[int] | None = None, *, gravity_aligned: bool = False
) -> list[RunExport]:
    """Write the landmarks of ``runs`` (all by default) to a binary PLY point cloud, coloured by run.

    With ``gravity_aligned`` the points are in the map's gravity frame g (z up, x the first teach camera's forward
    direction made horizontal: ``perception_model.frames.T_g_map_from_up`` of ``Map.gravity_up``, or of a level
    first camera's up when the map stores none) instead of the map frame. The file is written beside and renamed over
    ``path`` (never through a link there: :func:`perception_model.outputs.replace_file`). Returns one
    :class:`RunExport` per run. Raises ``MapError`` when the file name does not end in ``.ply``, the map has no
    landmark, or open3d cannot write the file.
    """
    path = Path(path)
    if path.suffix.lower() != PLY_SUFFIX:
        raise MapError(f"{path}: the point cloud file name must end in {PLY_SUFFIX}")
    infos = {r.id: r for r in map_.runs()}
    run_ids = list(infos) if runs is None else [int(r) for r in runs]
    for r in run_ids:
        if r not in infos:
            raise MapError(f"{map_.path}: no run {r}")
    pts, cols, summary = [], [], []
    for order, r in enumerate(run_ids):
        p, _owner = landmarks_in_map_frame(map_, r)
        aligned = poses_in_map_frame(map_, r)[2]
        colour = run_colour(order)
        pts.append(p)
        cols.append(np.broadcast_to(colour, p.shape))
        rgb = (float(colour[0]), float(colour[1]), float(colour[2]))
        summary.append(RunExport(r, infos[r].kind, len(p), aligned, rgb))
    points = np.concatenate(pts) if pts else np.empty((0, 3))
    if len(points) == 0:
        raise MapError(f"{map_.path}: the map has no landmarks to export")
    if gravity_aligned:
        up = map_.gravity_up
        points = points @ T_g_map_from_up(LEVEL_CAMERA_UP if up is None else up)[:3, :3].T

    import open3d as o3d  # open3d (~1 s) only for a point-cloud export

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    cloud.colors = o3d.utility.Vector3dVector(np.ascontiguousarray(np.concatenate(cols), dtype=np.float64))

    def write(tmp: Path) -> None:
        if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=False, print_progress=False):  # type: ignore[arg-type]
            raise MapError(f"{path}: open3d could not write the point cloud")

    path.parent.mkdir(parents=True, exist_ok=True)
    replace_file(path, write)  # whole, and never through a link at ``path``
    return summary
