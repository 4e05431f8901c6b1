"""A world whose appearance drifts flight after flight: synthetic aerial sequences of one scene whose textures are
blended toward another texture by a growing amount (docs/map.md, "Experiences").

:func:`write_drifted_sequence` renders each stereo pair twice, once with the scene's own textures and once with
the same geometry textured from ``other_seed`` (:func:`other_texture`), and writes ``(1 - change) * own + change *
other`` per pixel: geometry, camera and ground truth stay exact while the ground (and every surface) looks less
and less like the taught one, as seasons, vegetation or lighting do to a real route.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..camera import StereoCamera
from ..errors import ConfigError
from ..geometry import inv_T
from ..io.kitti import write_kitti_poses
from ..io.kitti_writer import KittiWriter
from .synthetic import Scene, render_stereo

#: the texture seed of the changed world is the scene's plus this
OTHER_TEXTURE_SEED_OFFSET = 1000
GREY_MAX = 255


def other_texture(scene: Scene, seed_offset: int = OTHER_TEXTURE_SEED_OFFSET) -> Scene:
    """The same geometry (boxes, trees, ground, backdrop) textured from another seed."""
    return dataclasses.replace(scene, seed=int(scene.seed) + int(seed_offset))


def write_drifted_sequence(
    out_dir: str | Path,
    scene: Scene,
    camera: StereoCamera,
    T_world_cam: np.ndarray,
    t_ns: np.ndarray,
    change: float,
    *,
    other: Scene | None = None,
) -> Path:
    """A KITTI-layout folder (as :func:`vtr.sim.synthetic.write_sequence`: images, calib, times, ``poses.txt`` and
    ``poses_world.txt``) of ``scene`` seen along ``T_world_cam`` (N, 4, 4) at ``t_ns`` (N,), its appearance moved
    ``change`` (0: as the scene, 1: entirely ``other``, default :func:`other_texture`) toward the other texture."""
    change = float(change)
    if not 0.0 <= change <= 1.0:
        raise ConfigError(f"change: expected a blend in [0, 1], got {change}")
    T = np.asarray(T_world_cam, float)
    t_ns = np.asarray(t_ns, np.int64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0 or t_ns.shape != (len(T),):
        raise ConfigError(f"T_world_cam: expected (N, 4, 4) with N > 0 and t_ns (N,), got {T.shape} and {t_ns.shape}")
    other = other_texture(scene) if other is None else other
    out = Path(out_dir)
    writer = KittiWriter(out, camera)
    for i in range(len(T)):
        own = render_stereo(scene, camera, T[i])
        pair = [own.left, own.right]
        if change > 0.0:
            changed = render_stereo(other, camera, T[i])
            pair = [
                np.clip(
                    np.rint((1.0 - change) * a.astype(np.float32) + change * b.astype(np.float32)), 0, GREY_MAX
                ).astype(np.uint8)
                for a, b in ((own.left, changed.left), (own.right, changed.right))
            ]
        writer.add(int(t_ns[i]), pair[0], pair[1])
    writer.close(inv_T(T[0]) @ T)
    write_kitti_poses(out / "poses_world.txt", T)
    return out


__all__ = ["OTHER_TEXTURE_SEED_OFFSET", "other_texture", "write_drifted_sequence"]
