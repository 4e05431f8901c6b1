"""The procedural texture atlas: tileable multi-scale noise and random shapes, quantized, with its
wrap-around mip pyramid packed in one image (:class:`TextureAtlas`, :func:`make_texture_atlas`)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .constants import (
    _STREAM_TEXTURE,
    ATLAS_PAD,
    ATLAS_STRETCH_PERCENTILES,
    DEFAULT_TEXTURE_SIZE,
    NOISE_AMPLITUDE_EXPONENT,
    NOISE_MAX_WAVELENGTH_FRACTION,
    NOISE_MIN_WAVELENGTH,
    SHAPE_EDGE_BLUR_TEXELS,
    SHAPE_LEVEL_RANGE,
    SHAPE_SIZE_RANGE_TEXELS,
    SHAPES_PER_MEGATEXEL,
)


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
        return self.packed[y : y + n, x : x + n]


def _wrap_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur with periodic (tileable) borders."""
    pad = max(1, int(math.ceil(4 * sigma)))
    p = np.pad(img, pad, mode="wrap")
    return cv2.GaussianBlur(p, (0, 0), sigma)[pad:-pad, pad:-pad]


def _wrap_pyr_down(img: np.ndarray) -> np.ndarray:
    """``cv2.pyrDown`` with periodic borders: output texel i is centred on input texel 2 i."""
    pad = 4
    p = np.pad(img, pad, mode="wrap")
    return cv2.pyrDown(p)[pad // 2 : -pad // 2, pad // 2 : -pad // 2]


def _noise_octaves(rng: np.random.Generator, size: int) -> np.ndarray:
    """Sum of tileable value-noise octaves (cubic-interpolated random grids), float32."""
    img = np.zeros((size, size), np.float32)
    lam = NOISE_MIN_WAVELENGTH
    while lam <= size // NOISE_MAX_WAVELENGTH_FRACTION:
        n = size // lam
        grid = np.pad(rng.standard_normal((n, n), dtype=np.float32), 2, mode="wrap")
        up = cv2.resize(grid, ((n + 4) * lam, (n + 4) * lam), interpolation=cv2.INTER_CUBIC)
        img += np.float32(lam**NOISE_AMPLITUDE_EXPONENT) * up[2 * lam : 2 * lam + size, 2 * lam : 2 * lam + size]
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


def _draw_one(
    img: np.ndarray, kind: int, x: float, y: float, r: float, ang: float, asp: float, vang: np.ndarray, colour: float
) -> None:
    c = (round(x), round(y))
    if kind == 0:
        cv2.circle(img, c, max(1, round(r)), colour, -1)
    elif kind == 1:
        cv2.ellipse(img, c, (max(1, round(r)), max(1, round(r * asp))), math.degrees(ang), 0, 360, colour, -1)
    elif kind == 2:
        ca, sa = math.cos(ang), math.sin(ang)
        hx, hy = r, r * asp
        corners = [
            (x + ca * px - sa * py, y + sa * px + ca * py) for px, py in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))
        ]
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
        packed[y : y + n + 2 * p, size + 2 * p : size + 2 * p + n + 2 * p] = np.pad(lv, p, mode="wrap")
        ox.append(size + 3 * p)
        oy.append(y + p)
        y += n + 2 * p
    packed.setflags(write=False)
    return TextureAtlas(size, packed, np.array(ox, np.float32), np.array(oy, np.float32))
