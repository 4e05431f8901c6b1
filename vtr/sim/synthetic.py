"""Synthetic rectified greyscale stereo sequences with exact ground truth.

A :class:`Scene` is a textured ground plane (world frame ENU: x east, y north, z up, ground at
z = 0 m) with raised structures -- axis-aligned :class:`Box` buildings and :class:`Tree` s made of
a cylindrical trunk and a conical crown -- and an optional distant :class:`Backdrop` (a textured
vertical cylinder with a hilly top edge, "mountains") around the scene. Everything is
deterministic from a seed (:func:`make_scene`).

Rendering (:func:`render`, :func:`render_stereo`) ray-casts every pixel of each camera from its
own centre (the right camera sits ``baseline`` m along the left camera's +x axis), so stereo
geometry is exact: the rendered depth ``z`` of a left pixel gives disparity ``fx * baseline / z``.
Appearance is view-consistent: every surface point samples a fixed random texture atlas at its
surface coordinates (metres), with trilinear mipmapping chosen from the pixel footprint on the
surface, ``depth / (f * cos(incidence))``, so far or grazing surfaces are low-pass filtered
instead of aliasing into spurious features. Faces are shaded by a fixed sun direction.

Frames: ``T_world_cam`` maps coordinates of the *left rectified camera* (x right, y down,
z forward, metres) into the world (ENU, metres). Depth maps hold the left-camera z (m) per
pixel, ``inf`` where a pixel sees sky.

Trajectories: :func:`aerial_route` (multirotor at 12 m altitude, camera pitched 50 deg down,
heading along the path, with lateral/vertical offsets for repeat runs) and
:func:`turning_route` (ground vehicle, forward-looking camera 1.5 m above the ground, straight,
turn, straight). :func:`write_sequence` writes a KITTI-layout folder.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import cast

import cv2
import numpy as np

from ..camera import StereoCamera
from ..conventions import NS_PER_S
from ..errors import ConfigError
from ..geometry import distance_to_polyline, inv_T, make_T
from ..io.kitti import write_kitti_poses
from ..io.kitti_writer import KittiWriter

# --------------------------------------------------------------------------------------------
# Named constants
# --------------------------------------------------------------------------------------------

#: Near clipping distance (m, camera z): hits closer than this are ignored.
NEAR_M = 0.05
#: Side of the square texture atlas in texels (power of two); with GROUND_TEXEL_M the ground
#: texture repeats every 4096 * 0.05 = 204.8 m.
DEFAULT_TEXTURE_SIZE = 4096
#: Ground texture resolution at mip level 0 (m per texel).
GROUND_TEXEL_M = 0.05
#: Box / tree texture resolution at mip level 0 (m per texel).
STRUCTURE_TEXEL_M = 0.04
#: Shortest / longest noise wavelength of the atlas (texels) and the amplitude exponent per
#: octave (amplitude ~ wavelength ** exponent; > 0 makes coarse detail stronger).
NOISE_MIN_WAVELENGTH = 2
NOISE_MAX_WAVELENGTH_FRACTION = 16
NOISE_AMPLITUDE_EXPONENT = 0.1
#: Random flat shapes drawn into the atlas per million texels, their size range (texels) and grey
#: level range (in units of the noise standard deviation).
SHAPES_PER_MEGATEXEL = 1200
SHAPE_SIZE_RANGE_TEXELS = (2.0, 160.0)
SHAPE_LEVEL_RANGE = 2.0
SHAPE_EDGE_BLUR_TEXELS = 0.6
#: Percentiles mapped to grey 0 and 255 when the atlas is quantized.
ATLAS_STRETCH_PERCENTILES = (0.5, 99.5)
#: Texels of wrap-around padding around each packed mip level (bilinear reads one past the end).
ATLAS_PAD = 2
#: Added to every mip level (log2 texels); > 0 blurs more, < 0 sharpens (and aliases).
MIP_BIAS = 0.0
#: Smallest |cos(incidence)| used for the footprint (grazing rays pick the coarsest levels).
MIN_COS_INCIDENCE = 1e-3

#: Mid grey of the 8-bit atlas; contrast scales the texture about it.
MID_GREY = 127.5
#: Lambertian shading: intensity factor = AMBIENT + DIFFUSE * max(0, n . sun).
AMBIENT = 0.45
DIFFUSE = 0.55
#: Unit sun direction in the world (ENU), about 55 deg elevation from the south-east.
SUN_DIRECTION_WORLD = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])
#: Sky grey at the horizon and at the zenith (a smooth featureless gradient).
SKY_GREY_HORIZON = 215.0
SKY_GREY_ZENITH = 185.0
#: Samples of a backdrop's height profile around its circle.
BACKDROP_PROFILE_SAMPLES = 720

#: Default aerial configuration (thesis simulation: multirotor, camera pitched 50 deg down).
DEFAULT_ALTITUDE_M = 12.0
DEFAULT_AERIAL_PITCH_RAD = math.radians(50.0)
#: Default ground-vehicle camera height (m).
DEFAULT_GROUND_CAMERA_HEIGHT_M = 1.5

#: Seed streams, so the texture, the structures, the surface texture offsets and the image noise
#: draw independent random numbers from one user seed.
_STREAM_TEXTURE = 1
_STREAM_LAYOUT = 2
_STREAM_SURFACES = 3
_STREAM_NOISE = 4

__all__ = [
    "Backdrop", "Box", "Ground", "Scene", "StereoRender", "TextureAtlas", "Tree", "T_left_right",
    "aerial_route", "aerial_scene", "backproject", "camera_pose", "camera_rotation", "far_structure_scene",
    "kitti_like_camera", "make_scene", "make_texture_atlas", "render", "render_stereo", "route_times",
    "turning_route", "write_sequence", "zed_camera",
]


# --------------------------------------------------------------------------------------------
# Scene description
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Box:
    """Axis-aligned box standing on the ground (world ENU, metres): ``[x_min, x_max] x [y_min, y_max]
    x [0, height]``. ``albedo`` scales brightness, ``contrast`` scales the texture about mid grey."""

    x_min: float
    y_min: float
    x_max: float
    y_max: float
    height: float
    albedo: float = 1.0
    contrast: float = 1.0


@dataclass(frozen=True)
class Tree:
    """A tree at ``(x, y)`` (world ENU, metres): vertical cylinder trunk of ``trunk_radius`` from the
    ground to ``trunk_height``, topped by a cone of base radius ``crown_radius`` and height
    ``crown_height`` (apex at ``trunk_height + crown_height``)."""

    x: float
    y: float
    trunk_radius: float
    trunk_height: float
    crown_radius: float
    crown_height: float
    albedo: float = 1.0
    contrast: float = 1.0


@dataclass(frozen=True)
class Backdrop:
    """Distant textured wall: inside of a vertical cylinder of ``radius`` (m) centred at ``centre_xy``
    (world ENU), from the ground up to a height profile ``heights`` (m) sampled uniformly in
    azimuth ``atan2(y - cy, x - cx)`` over [-pi, pi) and interpolated linearly (periodic)."""

    centre_xy: tuple[float, float]
    radius: float
    heights: tuple[float, ...]
    albedo: float = 1.0
    contrast: float = 1.0


@dataclass(frozen=True)
class Ground:
    """Ground plane z = 0 (world ENU). ``half_extent_m`` bounds it to a square around ``centre_xy``
    (``inf``: unbounded); ``texel_m`` is its texture resolution (m per texel at mip level 0)."""

    half_extent_m: float = math.inf
    centre_xy: tuple[float, float] = (0.0, 0.0)
    texel_m: float = GROUND_TEXEL_M
    albedo: float = 1.0
    contrast: float = 1.0


@dataclass(frozen=True, eq=False)
class TextureAtlas:
    """Tileable random texture of ``size`` x ``size`` texels and its mip pyramid packed in one uint8 image.

    Level ``L`` (``size >> L`` texels square, level 0 the full resolution) starts at
    ``packed[origin_y[L], origin_x[L]]`` (origins include the wrap padding), so texel coordinate ``x``
    (level-0 units, already reduced modulo ``size``) of level ``L`` is at packed column
    ``origin_x[L] + x / 2**L``.
    """

    size: int
    packed: np.ndarray
    origin_x: np.ndarray
    origin_y: np.ndarray

    @property
    def n_levels(self) -> int:
        return len(self.origin_x)

    def level(self, index: int) -> np.ndarray:
        """Mip level ``index`` as a (size >> index)-square uint8 view (for inspection and tests)."""
        n = self.size >> index
        y, x = int(self.origin_y[index]), int(self.origin_x[index])
        return self.packed[y:y + n, x:x + n]


@dataclass(frozen=True, eq=False)
class Scene:
    """A static world (ENU, metres) for rendering. Build one with :func:`make_scene`.

    ``seed`` fixes the texture atlas and the per-surface texture placement; ``texture_size`` is
    the atlas side (texels). The compiled geometry used by the renderer is derived on construction.
    """

    seed: int
    ground: Ground = field(default_factory=Ground)
    boxes: tuple[Box, ...] = ()
    trees: tuple[Tree, ...] = ()
    backdrop: Backdrop | None = None
    texture_size: int = DEFAULT_TEXTURE_SIZE
    structure_texel_m: float = STRUCTURE_TEXEL_M
    _compiled: _CompiledScene = field(init=False, repr=False)

    def __post_init__(self) -> None:
        size = int(self.texture_size)
        if size < 16 or size & (size - 1):
            raise ConfigError(f"texture_size must be a power of two >= 16, got {self.texture_size}")
        object.__setattr__(self, "boxes", tuple(self.boxes))
        object.__setattr__(self, "trees", tuple(self.trees))
        object.__setattr__(self, "_compiled", _compile(self))

    @property
    def texture(self) -> TextureAtlas:
        """The scene's texture atlas (cached per seed and size)."""
        return make_texture_atlas(self.seed, self.texture_size)

    def structure_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height (m) of the top of boxes at world points (x, y) (0 on bare ground; trees ignored)."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        h = np.zeros(np.broadcast(x, y).shape)
        for b in self.boxes:
            inside = (x >= b.x_min) & (x <= b.x_max) & (y >= b.y_min) & (y <= b.y_max)
            h = np.where(inside, np.maximum(h, b.height), h)
        return h


# --------------------------------------------------------------------------------------------
# Texture atlas
# --------------------------------------------------------------------------------------------


def _wrap_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur with periodic (tileable) borders."""
    pad = max(1, int(math.ceil(4 * sigma)))
    p = np.pad(img, pad, mode="wrap")
    return cv2.GaussianBlur(p, (0, 0), sigma)[pad:-pad, pad:-pad]


def _wrap_pyr_down(img: np.ndarray) -> np.ndarray:
    """``cv2.pyrDown`` with periodic borders: output texel i is centred on input texel 2 i."""
    pad = 4
    p = np.pad(img, pad, mode="wrap")
    return cv2.pyrDown(p)[pad // 2:-pad // 2, pad // 2:-pad // 2]


def _noise_octaves(rng: np.random.Generator, size: int) -> np.ndarray:
    """Sum of tileable value-noise octaves (cubic-interpolated random grids), float32."""
    img = np.zeros((size, size), np.float32)
    lam = NOISE_MIN_WAVELENGTH
    while lam <= size // NOISE_MAX_WAVELENGTH_FRACTION:
        n = size // lam
        grid = np.pad(rng.standard_normal((n, n), dtype=np.float32), 2, mode="wrap")
        up = cv2.resize(grid, ((n + 4) * lam, (n + 4) * lam), interpolation=cv2.INTER_CUBIC)
        img += np.float32(lam**NOISE_AMPLITUDE_EXPONENT) * up[2 * lam:2 * lam + size, 2 * lam:2 * lam + size]
        lam *= 2
    img -= img.mean()
    img /= img.std()
    return img


def _draw_shapes(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Random flat shapes (discs, ellipses, rotated rectangles, triangles, thick lines) with periodic
    wrap. Returns (value layer, coverage mask) as float32; shapes are drawn large to small."""
    n = int(SHAPES_PER_MEGATEXEL * size * size / 1e6)
    lo, hi = SHAPE_SIZE_RANGE_TEXELS
    radii = np.sort(np.exp(rng.uniform(np.log(lo), np.log(min(hi, size / 8)), n)))[::-1]
    centres = rng.uniform(0, size, (n, 2))
    levels = rng.uniform(-SHAPE_LEVEL_RANGE, SHAPE_LEVEL_RANGE, n)
    kinds = rng.integers(0, 5, n)
    angles = rng.uniform(0, 2 * np.pi, n)
    aspects = rng.uniform(0.25, 1.0, n)
    vertex_angles = rng.uniform(0, 2 * np.pi, (n, 3))
    empty = -100.0  # sentinel below every shape level: marks texels no shape covers
    layer = np.full((size, size), empty, np.float32)
    for r, (cx, cy), val, kind, ang, asp, vang in zip(
        radii, centres, levels, kinds, angles, aspects, vertex_angles, strict=True
    ):
        shifts_x = [0.0] + ([size] if cx - r < 0 else []) + ([-size] if cx + r >= size else [])
        shifts_y = [0.0] + ([size] if cy - r < 0 else []) + ([-size] if cy + r >= size else [])
        for sx in shifts_x:
            for sy in shifts_y:
                x, y = cx + sx, cy + sy
                _draw_one(layer, int(kind), x, y, float(r), float(ang), float(asp), vang, float(val))
    mask = (layer > empty / 2).astype(np.float32)
    layer[mask == 0] = 0.0
    return layer, mask


def _draw_one(img: np.ndarray, kind: int, x: float, y: float, r: float, ang: float, asp: float,
              vang: np.ndarray, colour: float) -> None:
    c = (round(x), round(y))
    if kind == 0:
        cv2.circle(img, c, max(1, round(r)), colour, -1)
    elif kind == 1:
        cv2.ellipse(img, c, (max(1, round(r)), max(1, round(r * asp))), math.degrees(ang), 0, 360, colour, -1)
    elif kind == 2:
        ca, sa = math.cos(ang), math.sin(ang)
        hx, hy = r, r * asp
        corners = [(x + ca * px - sa * py, y + sa * px + ca * py) for px, py in
                   ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]
        cv2.fillConvexPoly(img, np.round(corners).astype(np.int32), colour)
    elif kind == 3:
        pts = np.stack([x + r * np.cos(vang), y + r * np.sin(vang)], axis=1)
        cv2.fillConvexPoly(img, np.round(pts).astype(np.int32), colour)
    else:
        dx, dy = r * math.cos(ang), r * math.sin(ang)
        p0 = (round(x - dx), round(y - dy))
        p1 = (round(x + dx), round(y + dy))
        cv2.line(img, p0, p1, colour, max(1, round(r * asp * 0.3)))


@functools.lru_cache(maxsize=4)
def make_texture_atlas(seed: int, size: int = DEFAULT_TEXTURE_SIZE) -> TextureAtlas:
    """Tileable, non-periodic-looking random texture (multi-scale value noise plus random sharp-edged
    shapes, contrast-stretched to uint8) and its wrap-around mip pyramid, deterministic from ``seed``.

    Cached: scenes with the same seed and size share one atlas (read-only arrays).
    """
    rng = np.random.default_rng([int(seed), _STREAM_TEXTURE])
    noise = _noise_octaves(rng, size)
    layer, mask = _draw_shapes(rng, size)
    # shapes replace the coarse noise but keep a little of the fine noise inside them
    mask = _wrap_blur(mask, SHAPE_EDGE_BLUR_TEXELS)
    layer = _wrap_blur(layer, SHAPE_EDGE_BLUR_TEXELS)
    img = noise * (1.0 - 0.6 * mask) + layer
    lo, hi = np.percentile(img[:: max(1, size // 512), :: max(1, size // 512)], ATLAS_STRETCH_PERCENTILES)
    img = np.clip((img - lo) * (255.0 / (hi - lo)), 0, 255)
    levels = [np.round(img).astype(np.uint8)]
    while levels[-1].shape[0] > 1:
        levels.append(_wrap_pyr_down(levels[-1]))
    # pack: level 0 on the left, the others stacked in a column on its right
    p = ATLAS_PAD
    width = size + 2 * p + (size // 2 + 2 * p)
    height = max(size + 2 * p, sum(lv.shape[0] + 2 * p for lv in levels[1:]))
    packed = np.zeros((height, width), np.uint8)
    ox, oy = [p], [p]
    packed[: size + 2 * p, : size + 2 * p] = np.pad(levels[0], p, mode="wrap")
    y = 0
    for lv in levels[1:]:
        n = lv.shape[0]
        packed[y:y + n + 2 * p, size + 2 * p:size + 2 * p + n + 2 * p] = np.pad(lv, p, mode="wrap")
        ox.append(size + 3 * p)
        oy.append(y + p)
        y += n + 2 * p
    packed.setflags(write=False)
    return TextureAtlas(size, packed, np.array(ox, np.float32), np.array(oy, np.float32))


# --------------------------------------------------------------------------------------------
# Compiled scene (flat arrays for the renderer)
# --------------------------------------------------------------------------------------------


def _shade(normal: np.ndarray) -> float:
    return AMBIENT + DIFFUSE * max(0.0, float(np.dot(normal, SUN_DIRECTION_WORLD)))


@dataclass(frozen=True, eq=False)
class _CompiledScene:
    """Renderer-side arrays. Surface texture: colour = gain * atlas + bias, where gain/bias fold in
    albedo, contrast and (for planar faces) shading; atlas texel = (s / texel + off_u, t / texel + off_v)."""

    # axis-aligned rectangles (box faces): plane coordinate[axis] == c, normal sign along axis
    rect_axis: np.ndarray  # (F,) int
    rect_axes: np.ndarray  # (3, F) int: the normal axis, then the face's s and t axes
    rect_c: np.ndarray  # (F,)
    rect_sign: np.ndarray  # (F,) +1 / -1
    rect_bounds: np.ndarray  # (F, 4) lo_s, hi_s, lo_t, hi_t on the two other axes (ascending order)
    rect_corners: np.ndarray  # (F, 4, 3) world corners
    rect_tex: np.ndarray  # (F, 5) off_u, off_v, 1/texel, gain, bias
    # vertical cone frusta (tree parts): cx, cy, z0, z1, r0, r1
    frusta: np.ndarray  # (P, 6)
    frustum_corners: np.ndarray  # (P, 8, 3) bounding box corners
    frustum_tex: np.ndarray  # (P, 5) off_u, off_v, 1/texel, albedo, contrast
    ground_tex: tuple[float, float, float, float, float]
    backdrop_tex: tuple[float, float, float, float, float] | None
    backdrop_heights: np.ndarray | None


def _surface_gain_bias(albedo: float, contrast: float, shade: float) -> tuple[float, float]:
    k = albedo * shade
    return k * contrast, k * MID_GREY * (1.0 - contrast)


def _compile(scene: Scene) -> _CompiledScene:
    rng = np.random.default_rng([int(scene.seed), _STREAM_SURFACES])
    size = int(scene.texture_size)
    inv_tex = 1.0 / scene.structure_texel_m
    axes, cs, signs, bounds, corners, tex = [], [], [], [], [], []
    for b in scene.boxes:
        lo = np.array([b.x_min, b.y_min, 0.0])
        hi = np.array([b.x_max, b.y_max, b.height])
        # four walls and the roof (the floor rests on the ground and is never visible)
        for axis, sign in ((0, -1), (0, 1), (1, -1), (1, 1), (2, 1)):
            others = [a for a in range(3) if a != axis]
            c = lo[axis] if sign < 0 else hi[axis]
            normal = np.zeros(3)
            normal[axis] = sign
            gain, bias = _surface_gain_bias(b.albedo, b.contrast, _shade(normal))
            axes.append(axis)
            cs.append(c)
            signs.append(sign)
            bounds.append([lo[others[0]], hi[others[0]], lo[others[1]], hi[others[1]]])
            quad = []
            for s, t in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.zeros(3)
                p[axis] = c
                p[others[0]] = (lo, hi)[s][others[0]]
                p[others[1]] = (lo, hi)[t][others[1]]
                quad.append(p)
            corners.append(quad)
            off = rng.uniform(0, size, 2)
            tex.append([off[0], off[1], inv_tex, gain, bias])
    frusta, fcorners, ftex = [], [], []
    for tr in scene.trees:
        top = tr.trunk_height + tr.crown_height
        parts = ((0.0, tr.trunk_height, tr.trunk_radius, tr.trunk_radius),
                 (tr.trunk_height, top, tr.crown_radius, 0.0))
        for z0, z1, r0, r1 in parts:
            r = max(r0, r1)
            frusta.append([tr.x, tr.y, z0, z1, r0, r1])
            fcorners.append([[tr.x + sx * r, tr.y + sy * r, z]
                             for sx in (-1, 1) for sy in (-1, 1) for z in (z0, z1)])
            off = rng.uniform(0, size, 2)
            ftex.append([off[0], off[1], inv_tex, tr.albedo, tr.contrast])
    g = scene.ground
    g_gain, g_bias = _surface_gain_bias(g.albedo, g.contrast, _shade(np.array([0.0, 0.0, 1.0])))
    off = rng.uniform(0, size, 2)
    ground_tex = (float(off[0]), float(off[1]), 1.0 / g.texel_m, g_gain, g_bias)
    backdrop_tex, heights = None, None
    if scene.backdrop is not None:
        bd = scene.backdrop
        if bd.radius <= 0 or len(bd.heights) < 2:
            raise ConfigError("backdrop needs a positive radius and at least two height samples")
        # the wall faces inward; shade it as if lit diffusely (no single normal)
        gain, bias = _surface_gain_bias(bd.albedo, bd.contrast, AMBIENT + 0.5 * DIFFUSE)
        texel = 2 * math.pi * bd.radius / size  # one atlas period around the circle: seamless
        off = rng.uniform(0, size, 2)
        backdrop_tex = (0.0, float(off[1]), 1.0 / texel, gain, bias)
        heights = np.asarray(bd.heights, np.float32)
    f32 = np.float32
    return _CompiledScene(
        rect_axis=np.array(axes, np.int64),
        rect_axes=np.array([[a, *(b for b in range(3) if b != a)] for a in axes], np.int64).reshape(-1, 3).T,
        rect_c=np.array(cs, float), rect_sign=np.array(signs, float),
        rect_bounds=np.array(bounds, float).reshape(-1, 4),
        rect_corners=np.array(corners, float).reshape(-1, 4, 3),
        rect_tex=np.array(tex, f32).reshape(-1, 5),
        frusta=np.array(frusta, float).reshape(-1, 6),
        frustum_corners=np.array(fcorners, float).reshape(-1, 8, 3),
        frustum_tex=np.array(ftex, f32).reshape(-1, 5),
        ground_tex=ground_tex, backdrop_tex=backdrop_tex, backdrop_heights=heights,
    )


# --------------------------------------------------------------------------------------------
# Scene factory
# --------------------------------------------------------------------------------------------


def make_scene(
    seed: int = 0,
    *,
    area_m: tuple[float, float, float, float] = (-40.0, 160.0, -60.0, 60.0),
    n_boxes: int = 60,
    box_size_m: tuple[float, float] = (2.0, 10.0),
    box_height_m: tuple[float, float] = (1.0, 6.0),
    n_trees: int = 120,
    tree_height_m: tuple[float, float] = (3.0, 9.0),
    clear_path_xy: np.ndarray | None = None,
    clear_radius_m: float = 0.0,
    min_gap_m: float = 1.0,
    ground_contrast: float = 1.0,
    ground_half_extent_m: float = math.inf,
    backdrop_radius_m: float | None = None,
    backdrop_centre_xy: tuple[float, float] = (0.0, 0.0),
    backdrop_height_m: tuple[float, float] = (15.0, 35.0),
    texture_size: int = DEFAULT_TEXTURE_SIZE,
) -> Scene:
    """Random scene, deterministic from ``seed`` (world ENU, metres).

    Structures are placed uniformly in ``area_m = (x_min, x_max, y_min, y_max)`` without overlapping
    (``min_gap_m`` apart) and at least ``clear_radius_m`` from the polyline ``clear_path_xy`` (M, 2)
    (keep a vehicle's route free). ``n_boxes`` buildings with footprint sides in ``box_size_m`` and
    heights in ``box_height_m``; ``n_trees`` trees with total heights in ``tree_height_m``.
    ``ground_contrast`` in [0, 1] scales the ground texture (0: uniform grey, featureless).
    ``backdrop_radius_m`` adds a textured "mountain" wall of that radius around ``backdrop_centre_xy``
    with heights varying smoothly in ``backdrop_height_m``.
    """
    rng = np.random.default_rng([int(seed), _STREAM_LAYOUT])
    x_min, x_max, y_min, y_max = area_m
    if x_max <= x_min or y_max <= y_min:
        raise ConfigError(f"area_m {area_m} is empty")
    path = None if clear_path_xy is None else np.asarray(clear_path_xy, float).reshape(-1, 2)
    placed: list[tuple[float, float, float]] = []  # (x, y, bounding radius)

    def free(x: float, y: float, r: float) -> bool:
        if path is not None and distance_to_polyline(np.array([x, y]), path)[0] < clear_radius_m + r:
            return False
        return all(math.hypot(x - px, y - py) >= r + pr + min_gap_m for px, py, pr in placed)

    max_tries = 50
    boxes: list[Box] = []
    for _ in range(n_boxes):
        for _try in range(max_tries):
            sx, sy = (float(v) for v in rng.uniform(*box_size_m, 2))
            x, y = float(rng.uniform(x_min, x_max)), float(rng.uniform(y_min, y_max))
            r = 0.5 * math.hypot(sx, sy)
            if free(x, y, r):
                placed.append((x, y, r))
                boxes.append(Box(x - sx / 2, y - sy / 2, x + sx / 2, y + sy / 2,
                                 float(rng.uniform(*box_height_m)),
                                 albedo=float(rng.uniform(0.7, 1.1)), contrast=float(rng.uniform(0.7, 1.0))))
                break
    trees: list[Tree] = []
    for _ in range(n_trees):
        for _try in range(max_tries):
            h = float(rng.uniform(*tree_height_m))
            trunk_h = h * float(rng.uniform(0.2, 0.4))
            crown_r = h * float(rng.uniform(0.15, 0.3))
            x, y = float(rng.uniform(x_min, x_max)), float(rng.uniform(y_min, y_max))
            if free(x, y, crown_r):
                placed.append((x, y, crown_r))
                trees.append(Tree(x, y, trunk_radius=float(h * rng.uniform(0.025, 0.04)),
                                  trunk_height=float(trunk_h),
                                  crown_radius=float(crown_r), crown_height=float(h - trunk_h),
                                  albedo=float(rng.uniform(0.6, 0.9)), contrast=float(rng.uniform(0.8, 1.0))))
                break
    backdrop = None
    if backdrop_radius_m is not None:
        phi = np.linspace(-np.pi, np.pi, BACKDROP_PROFILE_SAMPLES, endpoint=False)
        prof = np.zeros_like(phi)
        n_harmonics = 12
        for k in range(1, n_harmonics + 1):
            prof += rng.normal() / k * np.cos(k * phi + rng.uniform(0, 2 * np.pi))
        prof = (prof - prof.min()) / max(prof.max() - prof.min(), 1e-9)
        h_lo, h_hi = backdrop_height_m
        backdrop = Backdrop((float(backdrop_centre_xy[0]), float(backdrop_centre_xy[1])), float(backdrop_radius_m),
                            tuple(float(v) for v in h_lo + (h_hi - h_lo) * prof))
    ground = Ground(half_extent_m=ground_half_extent_m, contrast=ground_contrast)
    return Scene(seed=int(seed), ground=ground, boxes=tuple(boxes), trees=tuple(trees), backdrop=backdrop,
                 texture_size=texture_size)


def aerial_scene(seed: int = 0, **overrides) -> Scene:
    """Default multirotor scene: textured ground with buildings and trees over (-40..160) x (-60..60) m,
    no structure taller than 6 m (buildings) / 9 m (trees), so a 12 m flight is clear."""
    return make_scene(seed, **overrides)


def far_structure_scene(seed: int = 0, route_xy: np.ndarray | None = None, *,
                        centre_xy: tuple[float, float] = (0.0, 0.0), backdrop_radius_m: float = 60.0,
                        near_clearance_m: float = 25.0, **overrides) -> Scene:
    """Scene whose texture lies mostly far away, for ground-vehicle turning tests.

    The ground is faint (contrast 0.15); trees and buildings stand at least ``near_clearance_m`` from the
    route polyline ``route_xy`` (M, 2) (or from ``centre_xy`` when no route is given), and a textured
    mountain wall of ``backdrop_radius_m`` surrounds ``centre_xy``. With a 0.12 m baseline, 40 baselines
    is 4.8 m; with 0.537 m it is 21.5 m -- both well inside the clearance.
    """
    cx, cy = centre_xy
    r = backdrop_radius_m * 0.9
    path = np.array([centre_xy], float) if route_xy is None else np.asarray(route_xy, float)
    kw: dict = dict(area_m=(cx - r, cx + r, cy - r, cy + r), n_boxes=25, n_trees=60, box_size_m=(3.0, 12.0),
                    box_height_m=(3.0, 12.0), tree_height_m=(5.0, 14.0), clear_path_xy=path,
                    clear_radius_m=near_clearance_m, ground_contrast=0.15,
                    backdrop_radius_m=backdrop_radius_m, backdrop_centre_xy=centre_xy,
                    backdrop_height_m=(0.1 * backdrop_radius_m, 0.3 * backdrop_radius_m))
    kw.update(overrides)
    return make_scene(seed, **kw)


# --------------------------------------------------------------------------------------------
# Camera presets
# --------------------------------------------------------------------------------------------


def zed_camera() -> StereoCamera:
    """ZED-like rectified stereo camera at VGA (672x376, fx = fy = 350 px, 0.12 m baseline)."""
    return StereoCamera(fx=350.0, fy=350.0, cx=335.5, cy=187.5, baseline=0.12, width=672, height=376)


def kitti_like_camera() -> StereoCamera:
    """KITTI-odometry-like rectified stereo camera (1226x370, fx = 707.09 px, 0.537 m baseline)."""
    return StereoCamera(fx=707.0912, fy=707.0912, cx=601.8873, cy=183.1104, baseline=0.537,
                        width=1226, height=370)


# --------------------------------------------------------------------------------------------
# Trajectories
# --------------------------------------------------------------------------------------------


def camera_rotation(heading_rad: float, pitch_down_rad: float) -> np.ndarray:
    """R_world_cam (3x3) of a camera looking along ``heading_rad`` (ENU yaw, counter-clockwise from
    east) tilted ``pitch_down_rad`` below the horizon, with no roll (image x stays horizontal)."""
    ch, sh = math.cos(heading_rad), math.sin(heading_rad)
    cp, sp = math.cos(pitch_down_rad), math.sin(pitch_down_rad)
    z = np.array([cp * ch, cp * sh, -sp])  # optical axis
    x = np.array([sh, -ch, 0.0])  # image right
    y = np.cross(z, x)  # image down
    return np.stack([x, y, z], axis=1)


def camera_pose(position_world: Sequence[float], heading_rad: float, pitch_down_rad: float) -> np.ndarray:
    """T_world_cam (4x4) of a camera at ``position_world`` (ENU, m) looking along ``heading_rad`` (ENU yaw)
    pitched ``pitch_down_rad`` below the horizon, no roll (see :func:`camera_rotation`)."""
    return make_T(camera_rotation(heading_rad, pitch_down_rad), np.asarray(position_world, float))


def _arc_path(segments: Sequence[tuple[float, float]], s: np.ndarray, start_xy: tuple[float, float],
              heading_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) and headings (N,) at arc lengths ``s`` (m) along consecutive segments of
    (length m, curvature 1/m; positive turns left). Beyond the end the last segment continues."""
    s = np.asarray(s, float)
    xy = np.zeros((len(s), 2))
    psi = np.zeros(len(s))
    p0 = np.array(start_xy, float)
    h0 = float(heading_rad)
    s0 = 0.0
    done = np.zeros(len(s), bool)
    for i, (length, kappa) in enumerate(segments):
        last = i == len(segments) - 1
        sel = ~done & ((s <= s0 + length) | last)
        ds = s[sel] - s0
        if abs(kappa) < 1e-12:
            xy[sel] = p0 + ds[:, None] * np.array([math.cos(h0), math.sin(h0)])
            psi[sel] = h0
        else:
            h = h0 + kappa * ds
            xy[sel, 0] = p0[0] + (np.sin(h) - math.sin(h0)) / kappa
            xy[sel, 1] = p0[1] - (np.cos(h) - math.cos(h0)) / kappa
            psi[sel] = h
        done |= sel
        # advance to the segment end
        if abs(kappa) < 1e-12:
            p0 = p0 + length * np.array([math.cos(h0), math.sin(h0)])
        else:
            h1 = h0 + kappa * length
            p0 = p0 + np.array([math.sin(h1) - math.sin(h0), -(math.cos(h1) - math.cos(h0))]) / kappa
            h0 = h1
        s0 += length
    return xy, psi


def _poses_along(segments: Sequence[tuple[float, float]], spacing_m: float, start_offset_m: float,
                 start_xy: tuple[float, float], heading_rad: float, height_m: float, pitch_down_rad: float,
                 lateral_offset_m: float, vertical_offset_m: float, yaw_offset_rad: float) -> np.ndarray:
    if spacing_m <= 0:
        raise ConfigError(f"spacing_m must be positive, got {spacing_m}")
    total = sum(length for length, _ in segments)
    s = np.arange(start_offset_m, total + 1e-9, spacing_m)
    if len(s) == 0:
        raise ConfigError(f"start_offset_m {start_offset_m} is beyond the route length {total}")
    xy, psi = _arc_path(segments, s, start_xy, heading_rad)
    left = np.stack([-np.sin(psi), np.cos(psi)], axis=1)  # ENU left of the heading
    xy = xy + lateral_offset_m * left
    T = np.tile(np.eye(4), (len(s), 1, 1))
    for i in range(len(s)):
        T[i] = camera_pose([xy[i, 0], xy[i, 1], height_m + vertical_offset_m], psi[i] + yaw_offset_rad,
                           pitch_down_rad)
    return T


def aerial_route(
    length_m: float = 100.0,
    spacing_m: float = 1.0,
    *,
    altitude_m: float = DEFAULT_ALTITUDE_M,
    pitch_down_rad: float = DEFAULT_AERIAL_PITCH_RAD,
    curvature_per_m: float = 0.0,
    start_xy: tuple[float, float] = (0.0, 0.0),
    heading_rad: float = 0.0,
    lateral_offset_m: float = 0.0,
    vertical_offset_m: float = 0.0,
    yaw_offset_rad: float = 0.0,
    start_offset_m: float = 0.0,
) -> np.ndarray:
    """Multirotor camera poses ``T_world_cam`` (N, 4, 4): left rectified camera -> world (ENU, m).

    The path starts at ``start_xy`` heading ``heading_rad`` (ENU yaw) and runs ``length_m`` along an arc
    of constant ``curvature_per_m`` (0: straight; positive turns left), sampled every ``spacing_m``
    from arc length ``start_offset_m``. The camera flies at ``altitude_m`` above the ground, looks
    along the path tangent pitched ``pitch_down_rad`` below the horizon, with no roll.
    A repeat run of the same path is offset ``lateral_offset_m`` to the left (negative: right),
    ``vertical_offset_m`` up, and yawed by ``yaw_offset_rad``.
    """
    return _poses_along([(length_m, curvature_per_m)], spacing_m, start_offset_m, start_xy, heading_rad,
                        altitude_m, pitch_down_rad, lateral_offset_m, vertical_offset_m, yaw_offset_rad)


def drifting_aerial_route(length_m: float, spacing_m: float, lateral_offset_m: float, vertical_offset_m: float,
                          ramp_m: float, start_offset_m: float = 0.0, **kwargs) -> np.ndarray:
    """An aerial repeat that starts on the taught path and drifts to a constant offset over ``ramp_m``
    metres (as a vehicle leaving its path does; a repeat starts where the teach started). Same
    frames as :func:`aerial_route`; only the camera centres move."""
    on_path = aerial_route(length_m, spacing_m, start_offset_m=start_offset_m, **kwargs)
    off = aerial_route(length_m, spacing_m, lateral_offset_m=lateral_offset_m, vertical_offset_m=vertical_offset_m,
                       start_offset_m=start_offset_m, **kwargs)
    along = np.arange(len(on_path)) * spacing_m
    s = np.clip(along / max(ramp_m, 1e-9), 0.0, 1.0)
    T = on_path.copy()
    T[:, :3, 3] = (1 - s)[:, None] * on_path[:, :3, 3] + s[:, None] * off[:, :3, 3]
    return T


def segmented_aerial_route(
    segments: Sequence[tuple[float, float]],
    spacing_m: float = 1.0,
    *,
    altitude_m: float = DEFAULT_ALTITUDE_M,
    pitch_down_rad: float = DEFAULT_AERIAL_PITCH_RAD,
    start_xy: tuple[float, float] = (0.0, 0.0),
    heading_rad: float = 0.0,
    camera_heading_rad: float | None = None,
    yaw_offset_rad: float = 0.0,
    lateral_offset_m: float = 0.0,
    vertical_offset_m: float = 0.0,
    ramp_m: float = 0.0,
    start_offset_m: float = 0.0,
) -> np.ndarray:
    """Multirotor camera poses ``T_world_cam`` (N, 4, 4) along consecutive ``segments`` of (length m,
    curvature 1/m; positive turns left), e.g. a path with corners, at ``altitude_m`` (ENU, m).

    The camera looks along the path tangent turned by ``yaw_offset_rad`` or, with ``camera_heading_rad``,
    along that fixed ENU heading (a gimbal), pitched ``pitch_down_rad`` below the horizon, no roll. A
    repeat is offset ``lateral_offset_m`` to the left of the path and ``vertical_offset_m`` up; with
    ``ramp_m`` > 0 it starts on the path and reaches the offsets after ``ramp_m`` metres (as
    :func:`drifting_aerial_route`).
    """
    if spacing_m <= 0:
        raise ConfigError(f"spacing_m must be positive, got {spacing_m}")
    total = sum(length for length, _ in segments)
    s = np.arange(start_offset_m, total + 1e-9, spacing_m)
    if len(s) == 0:
        raise ConfigError(f"start_offset_m {start_offset_m} is beyond the route length {total}")
    xy, psi = _arc_path(segments, s, start_xy, heading_rad)
    blend = np.clip((s - s[0]) / ramp_m, 0.0, 1.0) if ramp_m > 0 else np.ones(len(s))
    left = np.stack([-np.sin(psi), np.cos(psi)], axis=1)
    xy = xy + (lateral_offset_m * blend)[:, None] * left
    z = altitude_m + vertical_offset_m * blend
    T = np.tile(np.eye(4), (len(s), 1, 1))
    for i in range(len(s)):
        cam = camera_heading_rad if camera_heading_rad is not None else psi[i] + yaw_offset_rad
        T[i] = camera_pose([xy[i, 0], xy[i, 1], z[i]], cam, pitch_down_rad)
    return T


def turning_route(
    spacing_m: float = 0.25,
    *,
    straight_before_m: float = 10.0,
    turn_angle_rad: float = math.pi / 2,
    turn_radius_m: float = 8.0,
    straight_after_m: float = 10.0,
    camera_height_m: float = DEFAULT_GROUND_CAMERA_HEIGHT_M,
    pitch_down_rad: float = 0.0,
    start_xy: tuple[float, float] = (0.0, 0.0),
    heading_rad: float = 0.0,
    lateral_offset_m: float = 0.0,
    vertical_offset_m: float = 0.0,
    yaw_offset_rad: float = 0.0,
    start_offset_m: float = 0.0,
) -> np.ndarray:
    """Ground-vehicle camera poses ``T_world_cam`` (N, 4, 4): left rectified camera -> world (ENU, m).

    Forward-looking camera ``camera_height_m`` above the ground: straight for ``straight_before_m``,
    then a turn of ``turn_angle_rad`` (positive: left) on ``turn_radius_m``, then straight for
    ``straight_after_m``; sampled every ``spacing_m`` of arc length. Offsets as in :func:`aerial_route`.
    """
    if turn_radius_m <= 0:
        raise ConfigError(f"turn_radius_m must be positive, got {turn_radius_m}")
    kappa = math.copysign(1.0 / turn_radius_m, turn_angle_rad)
    segments = [(straight_before_m, 0.0), (abs(turn_angle_rad) * turn_radius_m, kappa),
                (straight_after_m, 0.0)]
    return _poses_along(segments, spacing_m, start_offset_m, start_xy, heading_rad, camera_height_m,
                        pitch_down_rad, lateral_offset_m, vertical_offset_m, yaw_offset_rad)


def route_times(T_world_cam: np.ndarray, speed_mps: float, start_ns: int = 0) -> np.ndarray:
    """int64 ns timestamps for poses travelled at constant ``speed_mps`` (camera-centre path length)."""
    if speed_mps <= 0:
        raise ConfigError(f"speed_mps must be positive, got {speed_mps}")
    p = np.asarray(T_world_cam)[:, :3, 3]
    d = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    t = start_ns + np.round(d / speed_mps * NS_PER_S).astype(np.int64)
    if np.any(np.diff(t) <= 0):
        raise ConfigError("consecutive poses coincide: timestamps would not increase")
    return t


def T_left_right(camera: StereoCamera) -> np.ndarray:
    """Pose of the right rectified camera in the left one (``baseline`` m along +x)."""
    return make_T(np.eye(3), np.array([camera.baseline, 0.0, 0.0]))


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _ray_grid(fx: float, fy: float, cx: float, cy: float, width: int, height: int):
    """Camera-frame ray directions d = (xn, yn, 1) per pixel centre: xn (1, W), yn (H, 1), 1/|d| (H, W)."""
    xn = ((np.arange(width, dtype=np.float64) - cx) / fx).astype(np.float32)[None, :]
    yn = ((np.arange(height, dtype=np.float64) - cy) / fy).astype(np.float32)[:, None]
    inv_norm = (1.0 / np.sqrt(1.0 + xn**2 + yn**2)).astype(np.float32)
    for a in (xn, yn, inv_norm):
        a.setflags(write=False)
    return xn, yn, inv_norm


#: Hull edges of a rectangle's 4 corners (in order) and of a cuboid's 8 corners indexed
#: 4 * ix + 2 * iy + iz (edges join corners differing in one index).
_QUAD_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
_CUBOID_EDGES = np.array([[i, i ^ bit] for i in range(8) for bit in (1, 2, 4) if i < i ^ bit])


class _Frame:
    """Per-image ray-casting state: world ray directions and the nearest-hit buffers (flat, H*W)."""

    def __init__(self, camera: StereoCamera, T_world_cam: np.ndarray, scale: int):
        fx, fy = camera.fx * scale, camera.fy * scale
        cx, cy = (camera.cx + 0.5) * scale - 0.5, (camera.cy + 0.5) * scale - 0.5
        self.W, self.H = camera.width * scale, camera.height * scale
        self.fx, self.fy, self.cx, self.cy = fx, fy, cx, cy
        self.f = math.sqrt(fx * fy)
        xn, yn, inv_norm = _ray_grid(fx, fy, cx, cy, self.W, self.H)
        T = np.asarray(T_world_cam, float)
        self.R = T[:3, :3]
        self.C = T[:3, 3].copy()
        R32 = self.R.astype(np.float32)
        # world direction of the ray whose camera-frame z component is 1, so the hit parameter is depth
        self.d = np.empty((3, self.H * self.W), np.float32)
        for i in range(3):
            self.d[i].reshape(self.H, self.W)[...] = R32[i, 0] * xn + R32[i, 1] * yn + R32[i, 2]
        self.inv_norm = inv_norm.reshape(-1)
        n = self.H * self.W
        self.depth = np.full(n, np.inf, np.float32)
        self.tex_u = np.zeros(n, np.float32)
        self.tex_v = np.zeros(n, np.float32)
        self.footprint = np.ones(n, np.float32)  # level-0 texels per pixel
        self.gain = np.zeros(n, np.float32)
        self.bias = np.zeros(n, np.float32)

    def write(self, pix, t, u, v, fp, gain, bias) -> None:
        """Store surface attributes at flat pixel indices ``pix`` (depth already resolved or set here)."""
        for buf, val in ((self.depth, t), (self.tex_u, u), (self.tex_v, v), (self.footprint, fp),
                         (self.gain, gain), (self.bias, bias)):
            buf[pix] = val

    def resolve(self, pix: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Depth-test candidate hits (flat pixel, depth), possibly several per pixel: lower the depth
        buffer to the nearest and return the indices of the candidates that won their pixel."""
        closer = np.flatnonzero(t < self.depth[pix])
        pix, t = pix[closer], t[closer]
        np.minimum.at(self.depth, pix, t)
        return closer[t == self.depth[pix]]

    def candidates(self, corners_world: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels to test for convex primitives bounded by the convex hull of world corners (P, K, 3)
        with hull edges ``edges`` (E, 2) (corner index pairs): returns (primitive index, flat pixel index)
        for every pixel of each primitive's projected bounding rectangle, after clipping it to the near
        plane. Primitives entirely behind the near plane or off the image give none."""
        P = len(corners_world)
        if P == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        pc = (corners_world - self.C) @ self.R  # camera frame
        z = pc[..., 2]
        # near-plane clipping: the clipped hull is spanned by the corners in front of the plane and
        # the points where hull edges cross it
        pa, pb = pc[:, edges[:, 0]], pc[:, edges[:, 1]]
        za, zb = pa[..., 2], pb[..., 2]
        crosses = (za - NEAR_M) * (zb - NEAR_M) < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            w_edge = np.where(crosses, (NEAR_M - za) / (zb - za), 0.0)
        pts = np.concatenate([pc, pa + w_edge[..., None] * (pb - pa)], axis=1)
        valid = np.concatenate([z > NEAR_M, crosses], axis=1)
        zz = np.where(valid, np.maximum(pts[..., 2], NEAR_M), 1.0)
        u = self.fx * pts[..., 0] / zz + self.cx
        v = self.fy * pts[..., 1] / zz + self.cy
        u0 = np.clip(np.floor(np.where(valid, u, np.inf).min(axis=1)), 0, self.W)
        u1 = np.clip(np.ceil(np.where(valid, u, -np.inf).max(axis=1)) + 1, 0, self.W)
        v0 = np.clip(np.floor(np.where(valid, v, np.inf).min(axis=1)), 0, self.H)
        v1 = np.clip(np.ceil(np.where(valid, v, -np.inf).max(axis=1)) + 1, 0, self.H)
        u0, u1, v0, v1 = (a.astype(np.int64) for a in (u0, u1, v0, v1))
        w, h = u1 - u0, v1 - v0
        counts = np.where(valid.any(axis=1) & (w > 0) & (h > 0), w * h, 0)
        total = int(counts.sum())
        prim = np.repeat(np.arange(P), counts)
        local = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
        wp = w[prim]
        pix = (v0[prim] + local // wp) * self.W + u0[prim] + local % wp
        return prim, pix


def _cast_ground(fr: _Frame, scene: Scene) -> None:
    cz = fr.C[2]
    if cz <= 0:
        return
    off_u, off_v, inv_tex, gain, bias = scene._compiled.ground_tex
    dx, dy, dz = fr.d
    with np.errstate(divide="ignore"):
        t = np.float32(-cz) / dz  # negative or inf for rays that do not go down
    mask = (t > NEAR_M) & (t < np.inf)
    t[~mask] = 0.0
    # hit offsets from the camera (float32 precision independent of the distance from the origin)
    hx = t * dx
    hy = t * dy
    g = scene.ground
    if math.isfinite(g.half_extent_m):
        mask &= (np.abs(hx - np.float32(g.centre_xy[0] - fr.C[0])) <= g.half_extent_m)
        mask &= (np.abs(hy - np.float32(g.centre_xy[1] - fr.C[1])) <= g.half_extent_m)
    cos_inc = np.maximum(np.abs(dz) * fr.inv_norm, np.float32(MIN_COS_INCIDENCE))
    fp = t * np.float32(inv_tex / fr.f) / cos_inc
    size = scene.texture_size
    hx *= np.float32(inv_tex)
    hx += np.float32((fr.C[0] * inv_tex + off_u) % size)
    hy *= np.float32(inv_tex)
    hy += np.float32((fr.C[1] * inv_tex + off_v) % size)
    for buf, val in ((fr.depth, t), (fr.tex_u, hx), (fr.tex_v, hy), (fr.footprint, fp),
                     (fr.gain, np.float32(gain)), (fr.bias, np.float32(bias))):
        np.copyto(buf, val, where=mask)


def _cast_backdrop(fr: _Frame, scene: Scene) -> None:
    bd = scene.backdrop
    comp = scene._compiled
    if bd is None or comp.backdrop_tex is None or comp.backdrop_heights is None:
        return
    _, off_v, inv_tex, gain, bias = comp.backdrop_tex
    ox, oy = fr.C[0] - bd.centre_xy[0], fr.C[1] - bd.centre_xy[1]
    dist = math.hypot(ox, oy)
    # from inside, the wall is at least (radius - dist) m away along any ray: only pixels whose
    # current depth is beyond that can see it
    min_depth = (bd.radius - dist) * float(np.min(fr.inv_norm)) if dist < bd.radius else 0.0
    pix = np.flatnonzero(fr.depth > min_depth)
    dx, dy, dz = fr.d[0][pix], fr.d[1][pix], fr.d[2][pix]
    ox32, oy32 = np.float32(ox), np.float32(oy)
    a = dx * dx + dy * dy
    b = ox32 * dx + oy32 * dy  # half of the linear coefficient
    c = np.float32(ox * ox + oy * oy - bd.radius**2)
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        t_far = (-b + sq) / a
        t_near = (-b - sq) / a
    # inside the cylinder only the far root is ahead; from outside the near root is the visible side
    t = np.where(t_near > NEAR_M, t_near, t_far) if c > 0 else t_far
    hz = np.float32(fr.C[2]) + t * dz
    heights = comp.backdrop_heights
    keep = np.flatnonzero((disc >= 0) & (t > NEAR_M) & (t < fr.depth[pix]) & (hz >= 0)
                          & (hz <= heights.max()))
    pix, t, hz, dx, dy = pix[keep], t[keep], hz[keep], dx[keep], dy[keep]
    hx = ox32 + t * dx
    hy = oy32 + t * dy
    phi = np.arctan2(hy, hx)
    n = len(heights)
    pos = (phi + np.float32(np.pi)) * np.float32(n / (2 * np.pi))
    i0 = np.floor(pos)
    frac = pos - i0
    i0 = i0.astype(np.int64) % n
    h = heights[i0] * (1 - frac) + heights[(i0 + 1) % n] * frac
    k = np.flatnonzero(hz <= h)
    pix, t, hz, hx, hy, dx, dy, pos = pix[k], t[k], hz[k], hx[k], hy[k], dx[k], dy[k], pos[k]
    cos_inc = np.maximum(np.abs(hx * dx + hy * dy) * np.float32(1.0 / bd.radius) * fr.inv_norm[pix],
                         np.float32(MIN_COS_INCIDENCE))
    fp = t * np.float32(inv_tex / fr.f) / cos_inc
    u = pos * np.float32(scene.texture_size / n)  # one atlas period around the circle: seamless
    v = hz * np.float32(inv_tex) + np.float32(off_v)
    fr.write(pix, t, u, v, fp, np.float32(gain), np.float32(bias))


def _cast_rects(fr: _Frame, scene: Scene) -> None:
    comp = scene._compiled
    if len(comp.rect_axis) == 0:
        return
    # back-face culling: the camera must be on the normal's side of the face
    idx = np.flatnonzero(comp.rect_sign * (fr.C[comp.rect_axis] - comp.rect_c) > 0)
    prim, pix = fr.candidates(comp.rect_corners[idx], _QUAD_EDGES)
    if len(pix) == 0:
        return
    prim = idx[prim]
    axis, s_ax, t_ax = comp.rect_axes[:, prim]
    # per-face constants relative to the camera centre
    dc = (comp.rect_c - fr.C[comp.rect_axis]).astype(np.float32)
    rel = (comp.rect_bounds - fr.C[comp.rect_axes[1:]].T.repeat(2, axis=1)).astype(np.float32)
    t = dc[prim] / fr.d[axis, pix]
    ps = t * fr.d[s_ax, pix]
    pt = t * fr.d[t_ax, pix]
    r = rel[prim]
    hit = np.flatnonzero((t > NEAR_M) & (ps >= r[:, 0]) & (ps <= r[:, 1]) & (pt >= r[:, 2]) & (pt <= r[:, 3]))
    win = hit[fr.resolve(pix[hit], t[hit])]
    prim, pix, t, ps, pt, axis, s_ax, t_ax = (a[win] for a in (prim, pix, t, ps, pt, axis, s_ax, t_ax))
    # texture origin of each face relative to the camera, reduced modulo the atlas in float64
    tex = comp.rect_tex.astype(float)
    size = scene.texture_size
    base_u = ((fr.C[comp.rect_axes[1]] * tex[:, 2] + tex[:, 0]) % size).astype(np.float32)
    base_v = ((fr.C[comp.rect_axes[2]] * tex[:, 2] + tex[:, 1]) % size).astype(np.float32)
    _, _, inv_tex, gain, bias = comp.rect_tex[prim].T
    cos_inc = np.maximum(np.abs(fr.d[axis, pix]) * fr.inv_norm[pix], np.float32(MIN_COS_INCIDENCE))
    fp = t * inv_tex * np.float32(1.0 / fr.f) / cos_inc
    fr.write(pix, t, ps * inv_tex + base_u[prim], pt * inv_tex + base_v[prim], fp, gain, bias)


def _cast_frusta(fr: _Frame, scene: Scene) -> None:
    comp = scene._compiled
    if len(comp.frusta) == 0:
        return
    prim, pix = fr.candidates(comp.frustum_corners, _CUBOID_EDGES)
    if len(pix) == 0:
        return
    F = comp.frusta
    cz = fr.C[2]
    k_all = (F[:, 5] - F[:, 4]) / (F[:, 3] - F[:, 2])  # radius slope dr/dz
    # per-primitive constants (camera relative): ox, oy, a0 = radius at camera height, k, z0, z1
    consts = np.stack([fr.C[0] - F[:, 0], fr.C[1] - F[:, 1], F[:, 4] + k_all * (cz - F[:, 2]), k_all,
                       F[:, 2] - cz, F[:, 3] - cz], axis=1).astype(np.float32)
    ox, oy, a0, k, z0, z1 = consts[prim].T
    dx, dy, dz = fr.d[0][pix], fr.d[1][pix], fr.d[2][pix]
    qa = dx * dx + dy * dy - k * k * dz * dz
    qb = ox * dx + oy * dy - a0 * k * dz  # half of the linear coefficient
    qc = ox * ox + oy * oy - a0 * a0
    disc = qb * qb - qa * qc
    best = np.full(len(pix), np.inf, np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        ra, rb = (-qb - sq) / qa, (-qb + sq) / qa
        for root in (np.maximum(ra, rb), np.minimum(ra, rb)):  # the nearer valid root wins
            hz = root * dz
            ok = (root > NEAR_M) & (hz >= z0) & (hz <= z1)
            best = np.where(ok, root, best)
    cap = np.zeros(len(pix), np.int8)  # 0 lateral, -1 bottom disc, +1 top disc
    # caps: bottom disc (facing down) seen from below, top disc (facing up) seen from above
    for col_z, col_r, side in ((2, 4, -1), (3, 5, 1)):
        vis = (F[:, col_r] > 0) & (side * (cz - F[:, col_z]) > 0)
        if not vis.any():
            continue
        sel = np.flatnonzero(vis[prim])
        zc = (F[:, col_z] - cz).astype(np.float32)[prim[sel]]
        rc2 = (F[:, col_r] ** 2).astype(np.float32)[prim[sel]]
        tc = zc / dz[sel]
        px, py = ox[sel] + tc * dx[sel], oy[sel] + tc * dy[sel]
        ok = (tc > NEAR_M) & (px * px + py * py <= rc2) & (tc < best[sel])
        best[sel[ok]] = tc[ok]
        cap[sel[ok]] = side
    hit = np.flatnonzero(np.isfinite(best))
    win = hit[fr.resolve(pix[hit], best[hit])]
    prim, pix, t, cap, ox, oy, k, dx, dy, dz = (a[win] for a in (prim, pix, best, cap, ox, oy, k, dx, dy, dz))
    px = ox + t * dx
    py = oy + t * dy
    pz = np.float32(cz) + t * dz
    rho = np.maximum(np.sqrt(px * px + py * py), np.float32(1e-6))
    lateral = cap == 0
    # unit outward normal: lateral (px/rho, py/rho, -k)/sqrt(1+k^2); caps -z / +z
    inv_len = 1.0 / np.sqrt(1.0 + k * k)
    nx = np.where(lateral, px / rho * inv_len, np.float32(0.0))
    ny = np.where(lateral, py / rho * inv_len, np.float32(0.0))
    nz = np.where(lateral, -k * inv_len, cap.astype(np.float32))
    sun = SUN_DIRECTION_WORLD.astype(np.float32)
    shade = np.float32(AMBIENT) + np.float32(DIFFUSE) * np.maximum(nx * sun[0] + ny * sun[1] + nz * sun[2], 0)
    cos_inc = np.maximum(np.abs(nx * dx + ny * dy + nz * dz) * fr.inv_norm[pix],
                         np.float32(MIN_COS_INCIDENCE))
    off_u, off_v, inv_tex, albedo, contrast = comp.frustum_tex[prim].T
    r_ref = np.maximum(F[:, 4], F[:, 5]).astype(np.float32)[prim]
    # lateral texture: (azimuth * r_ref, z); caps: (x, y). Near a cone apex the azimuthal mapping
    # squeezes texels by r / r_ref: the footprint accounts for it.
    u = np.where(lateral, np.arctan2(py, px) * r_ref, px) * inv_tex + off_u
    v = np.where(lateral, pz, py) * inv_tex + off_v
    squeeze = np.where(lateral, np.maximum(r_ref / rho, np.float32(1.0)), np.float32(1.0))
    fp = t * inv_tex * np.float32(1.0 / fr.f) / cos_inc * squeeze
    k_gain = shade * albedo
    fr.write(pix, t, u, v, fp, k_gain * contrast, k_gain * np.float32(MID_GREY) * (1 - contrast))


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


def _cast(scene: Scene, camera: StereoCamera, T_world_view: np.ndarray, scale: int) -> _Frame:
    fr = _Frame(camera, T_world_view, scale)
    _cast_ground(fr, scene)
    _cast_backdrop(fr, scene)
    _cast_rects(fr, scene)
    _cast_frusta(fr, scene)
    return fr


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
    img: np.ndarray = (_texture(fr, scene.texture).reshape(-1) * fr.gain + fr.bias)
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
        res = render(scene, cam, T, noise_sigma=noise_sigma, noise_seed=2 * int(noise_seed) + j,
                     supersample=supersample, return_depth=return_depth, blur_sigma_px=blur_sigma_px)
        out.append(cast(tuple[np.ndarray, np.ndarray], res) if return_depth else (cast(np.ndarray, res), None))
    return StereoRender(out[0][0], out[1][0], out[0][1], out[1][1])


def backproject(camera: StereoCamera, T_world_cam: np.ndarray, depth: np.ndarray, u: np.ndarray,
                v: np.ndarray) -> np.ndarray:
    """World points (N, 3) (ENU, m) seen at integer left pixels (u, v) given a rendered depth map (m);
    NaN rows for sky pixels (infinite depth)."""
    u = np.asarray(u, int)
    v = np.asarray(v, int)
    z = depth[v, u].astype(float)
    z[~np.isfinite(z)] = np.nan
    p_cam = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], axis=1)
    T = np.asarray(T_world_cam, float)
    return p_cam @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------------------------
# Writing a sequence
# --------------------------------------------------------------------------------------------


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
        res = render_stereo(scene, camera, T[i], noise_sigma=noise_sigma,
                            noise_seed=noise_seed * 1_000_003 + i,
                            supersample=supersample, return_depth=write_depth, blur_sigma_px=blur_sigma_px,
                            right_cx_offset_px=right_cx_offset_px)
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
