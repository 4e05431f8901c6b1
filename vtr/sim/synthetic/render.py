"""Rendering images from ray-cast hits: mipmapped texturing, sky, blur and noise (:func:`render`), stereo
pairs (:func:`render_stereo`, :class:`StereoRender`) and depth back-projection (:func:`backproject`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np

from ...camera import StereoCamera
from ...errors import ConfigError
from .cameras import T_left_right
from .constants import _STREAM_NOISE, MIP_BIAS, SKY_GREY_HORIZON, SKY_GREY_ZENITH
from .raycast import _cast, _Frame
from .scene import Scene
from .texture import TextureAtlas


def _texture(fr: _Frame, atlas: TextureAtlas) -> np.ndarray:
    """Trilinear (mipmapped) atlas sample per pixel: float32 grey levels, shape (H, W)."""
    size = np.float32(atlas.size)
    n_levels = atlas.n_levels
    level = np.log2(np.maximum(fr.footprint, np.float32(1e-6)))
    if MIP_BIAS:
        level += np.float32(MIP_BIAS)
    np.clip(level, 0, n_levels - 1, out=level)
    lo = np.minimum(level.astype(np.int32), n_levels - 2)
    frac = level - lo
    # reduce modulo the atlas period (floor form: np.mod is several times slower)
    inv_size = np.float32(1.0 / atlas.size)
    u0 = fr.tex_u - np.floor(fr.tex_u * inv_size) * size
    v0 = fr.tex_v - np.floor(fr.tex_v * inv_size) * size
    scale_tab = np.ldexp(np.float32(1.0), -np.arange(n_levels, dtype=np.int32)).astype(np.float32)
    shape = (fr.H, fr.W)
    samples = []
    for lv in (lo, lo + 1):
        sc = scale_tab[lv]
        mx = (atlas.origin_x[lv] + u0 * sc).reshape(shape)
        my = (atlas.origin_y[lv] + v0 * sc).reshape(shape)
        samples.append(cv2.remap(atlas.packed, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
    s_lo = samples[0].astype(np.float32)
    return s_lo + frac.reshape(shape) * (samples[1].astype(np.float32) - s_lo)


def _sky(fr: _Frame, pix: np.ndarray) -> np.ndarray:
    """Sky grey at flat pixels ``pix``: a smooth gradient in ray elevation (featureless)."""
    elevation = np.clip(fr.d[2][pix] * fr.inv_norm[pix], 0.0, 1.0)  # sin(elevation): world z is up
    return np.float32(SKY_GREY_HORIZON) + np.float32(SKY_GREY_ZENITH - SKY_GREY_HORIZON) * elevation


def render(
    scene: Scene,
    camera: StereoCamera,
    T_world_view: np.ndarray,
    *,
    noise_sigma: float = 0.0,
    noise_seed: int = 0,
    supersample: int = 1,
    return_depth: bool = False,
    blur_sigma_px: float = 0.0,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Render one greyscale uint8 image (H, W) of ``scene`` seen by a pinhole camera with the
    intrinsics of ``camera`` (its left rectified camera) placed at ``T_world_view`` (view -> world, ENU).

    ``noise_sigma`` adds Gaussian noise (grey levels) drawn from ``noise_seed``; ``supersample`` k > 1
    casts k x k rays per pixel and area-averages (anti-aliased silhouettes, k^2 slower);
    ``blur_sigma_px`` > 0 convolves with a Gaussian point-spread function (the lens and sensor of a real
    camera) before the noise is added. With ``return_depth`` also returns the view-frame depth z (m,
    float32, ``inf`` for sky) at pixel centres.
    """
    k = int(supersample)
    if k < 1:
        raise ConfigError(f"supersample must be >= 1, got {supersample}")
    fr = _cast(scene, camera, T_world_view, k)
    img: np.ndarray = _texture(fr, scene.texture).reshape(-1) * fr.gain + fr.bias
    sky = np.flatnonzero(~np.isfinite(fr.depth))
    img[sky] = _sky(fr, sky)
    img = img.reshape(fr.H, fr.W)
    if k > 1:
        img = np.asarray(cv2.resize(img, camera.size, interpolation=cv2.INTER_AREA))
    if blur_sigma_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), blur_sigma_px, borderType=cv2.BORDER_REFLECT))
    if noise_sigma > 0:
        rng = np.random.default_rng([int(scene.seed), _STREAM_NOISE, int(noise_seed)])
        img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(noise_sigma)
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if not return_depth:
        return out
    depth = fr.depth if k == 1 else _cast(scene, camera, T_world_view, 1).depth
    return out, depth.reshape(camera.height, camera.width)


@dataclass(frozen=True)
class StereoRender:
    """A rendered rectified pair (uint8, H x W) and, when requested, each camera's depth z (m, inf = sky)."""

    left: np.ndarray
    right: np.ndarray
    depth_left: np.ndarray | None = None
    depth_right: np.ndarray | None = None


def render_stereo(
    scene: Scene,
    camera: StereoCamera,
    T_world_cam: np.ndarray,
    *,
    noise_sigma: float = 0.0,
    noise_seed: int = 0,
    supersample: int = 1,
    return_depth: bool = False,
    blur_sigma_px: float = 0.0,
    right_cx_offset_px: float = 0.0,
) -> StereoRender:
    """Render the left and right rectified images of ``camera`` with its left camera at ``T_world_cam``
    (left rectified camera -> world ENU). Each image is ray-cast from its own camera centre.
    Noise (if any) is independent in the two images, drawn from ``noise_seed``; ``blur_sigma_px`` as
    in :func:`render`. ``right_cx_offset_px`` renders the right image with its principal point that far
    right of the calibration's: a rectification error that makes every measured disparity smaller by
    that much than the calibration implies (real pairs show it, see docs/far_structure.md)."""
    T_world_right = np.asarray(T_world_cam, float) @ T_left_right(camera)
    right_camera = dataclasses.replace(camera, cx=camera.cx + right_cx_offset_px)
    out: list[tuple[np.ndarray, np.ndarray | None]] = []
    for j, (T, cam) in enumerate(((T_world_cam, camera), (T_world_right, right_camera))):
        res = render(
            scene,
            cam,
            T,
            noise_sigma=noise_sigma,
            noise_seed=2 * int(noise_seed) + j,
            supersample=supersample,
            return_depth=return_depth,
            blur_sigma_px=blur_sigma_px,
        )
        out.append(cast(tuple[np.ndarray, np.ndarray], res) if return_depth else (cast(np.ndarray, res), None))
    return StereoRender(out[0][0], out[1][0], out[0][1], out[1][1])


def backproject(
    camera: StereoCamera, T_world_cam: np.ndarray, depth: np.ndarray, u: np.ndarray, v: np.ndarray
) -> np.ndarray:
    """World points (N, 3) (ENU, m) seen at integer left pixels (u, v) given a rendered depth map (m);
    NaN rows for sky pixels (infinite depth)."""
    u = np.asarray(u, int)
    v = np.asarray(v, int)
    z = depth[v, u].astype(float)
    z[~np.isfinite(z)] = np.nan
    p_cam = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], axis=1)
    T = np.asarray(T_world_cam, float)
    return p_cam @ T[:3, :3].T + T[:3, 3]
