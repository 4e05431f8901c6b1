"""Writing a rendered stereo sequence as a KITTI-layout folder with exact ground truth
(:func:`write_sequence`)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ...camera import StereoCamera
from ...errors import ConfigError
from ...geometry import inv_T
from ...io.kitti import write_kitti_poses
from ...io.kitti_writer import KittiWriter
from .render import render_stereo
from .scene import Scene


def write_sequence(
    out_dir: str | Path,
    scene: Scene,
    camera: StereoCamera,
    T_world_cam: np.ndarray,
    t_ns: np.ndarray,
    *,
    noise_sigma: float = 0.0,
    noise_seed: int = 0,
    supersample: int = 1,
    write_depth: bool = False,
    progress: Callable[[int, int], None] | None = None,
    blur_sigma_px: float = 0.0,
    right_cx_offset_px: float = 0.0,
) -> Path:
    """Render and write a KITTI-layout stereo folder: ``image_0/`` (left), ``image_1/`` (right),
    ``calib.txt``, ``times.txt``, ``times_ns.txt``, ``poses.txt`` (T_cam0_cam, KITTI convention:
    world = first left camera), plus ``poses_world.txt`` (T_world_cam in the scene's ENU world, KITTI
    3x4 format), ``synthetic.json`` (scene and camera summary) and, with ``write_depth``,
    ``depth_0/NNNNNN.npy`` (left depth z, m, float32, inf = sky).

    ``T_world_cam`` (N, 4, 4) are left rectified camera -> world (ENU) poses; ``t_ns`` (N,) int64 ns.
    Frame i uses image noise seed ``noise_seed * 1_000_003 + i``. ``progress(i, N)`` is called per frame.
    ``blur_sigma_px`` and ``right_cx_offset_px`` as in :func:`render_stereo`; ``calib.txt`` states the
    nominal camera either way (an offset is an error the calibration does not know of).
    """
    out = Path(out_dir)
    T = np.asarray(T_world_cam, float)
    t_ns = np.asarray(t_ns, np.int64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0:
        raise ConfigError(f"T_world_cam must be (N, 4, 4) with N > 0, got {T.shape}")
    if t_ns.shape != (len(T),):
        raise ConfigError(f"t_ns must be ({len(T)},), got {t_ns.shape}")
    if np.any(np.diff(t_ns) <= 0):
        raise ConfigError("t_ns must be strictly increasing")
    writer = KittiWriter(out, camera)
    if write_depth:
        (out / "depth_0").mkdir(parents=True, exist_ok=True)
    for i in range(len(T)):
        res = render_stereo(
            scene,
            camera,
            T[i],
            noise_sigma=noise_sigma,
            noise_seed=noise_seed * 1_000_003 + i,
            supersample=supersample,
            return_depth=write_depth,
            blur_sigma_px=blur_sigma_px,
            right_cx_offset_px=right_cx_offset_px,
        )
        writer.add(int(t_ns[i]), res.left, res.right)
        if write_depth and res.depth_left is not None:
            np.save(out / "depth_0" / f"{i:06d}.npy", res.depth_left)
        if progress is not None:
            progress(i, len(T))
    writer.close(inv_T(T[0]) @ T)
    write_kitti_poses(out / "poses_world.txt", T)
    meta = {
        "generator": "vtr.sim.synthetic",
        "frames": "poses.txt: T_cam0_cam (left rectified camera, KITTI convention); "
        "poses_world.txt: T_world_cam (world ENU, z up, ground at z=0)",
        "T_world_cam0": T[0].tolist(),
        "seed": scene.seed,
        "texture_size": scene.texture_size,
        "n_boxes": len(scene.boxes),
        "n_trees": len(scene.trees),
        "backdrop_radius_m": None if scene.backdrop is None else scene.backdrop.radius,
        "ground_contrast": scene.ground.contrast,
        "camera": camera.to_dict(),
        "noise_sigma": noise_sigma,
        "noise_seed": noise_seed,
        "supersample": supersample,
        "blur_sigma_px": blur_sigma_px,
        "right_cx_offset_px": right_cx_offset_px,
    }
    (out / "synthetic.json").write_text(json.dumps(meta, indent=2) + "\n")
    return out
