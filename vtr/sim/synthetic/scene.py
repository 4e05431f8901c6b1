"""What a synthetic world contains (:class:`Box`, :class:`Tree`, :class:`Backdrop`, :class:`Ground` in a
:class:`Scene`, world ENU, metres) and the flat arrays a scene compiles into for the renderer."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ...errors import ConfigError
from .constants import (
    _STREAM_SURFACES,
    AMBIENT,
    DEFAULT_TEXTURE_SIZE,
    DIFFUSE,
    GROUND_TEXEL_M,
    MID_GREY,
    STRUCTURE_TEXEL_M,
    SUN_DIRECTION_WORLD,
)
from .texture import TextureAtlas, make_texture_atlas

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
        parts = ((0.0, tr.trunk_height, tr.trunk_radius, tr.trunk_radius), (tr.trunk_height, top, tr.crown_radius, 0.0))
        for z0, z1, r0, r1 in parts:
            r = max(r0, r1)
            frusta.append([tr.x, tr.y, z0, z1, r0, r1])
            fcorners.append([[tr.x + sx * r, tr.y + sy * r, z] for sx in (-1, 1) for sy in (-1, 1) for z in (z0, z1)])
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
        rect_c=np.array(cs, float),
        rect_sign=np.array(signs, float),
        rect_bounds=np.array(bounds, float).reshape(-1, 4),
        rect_corners=np.array(corners, float).reshape(-1, 4, 3),
        rect_tex=np.array(tex, f32).reshape(-1, 5),
        frusta=np.array(frusta, float).reshape(-1, 6),
        frustum_corners=np.array(fcorners, float).reshape(-1, 8, 3),
        frustum_tex=np.array(ftex, f32).reshape(-1, 5),
        ground_tex=ground_tex,
        backdrop_tex=backdrop_tex,
        backdrop_heights=heights,
    )
