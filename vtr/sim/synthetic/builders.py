"""Random scenes deterministic from a seed: :func:`make_scene` and its presets :func:`aerial_scene` and
:func:`far_structure_scene`."""

from __future__ import annotations

import math

import numpy as np

from ...errors import ConfigError
from ...geometry import distance_to_polyline
from .constants import _STREAM_LAYOUT, BACKDROP_PROFILE_SAMPLES, DEFAULT_TEXTURE_SIZE
from .scene import Backdrop, Box, Ground, Scene, Tree


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
                boxes.append(
                    Box(
                        x - sx / 2,
                        y - sy / 2,
                        x + sx / 2,
                        y + sy / 2,
                        float(rng.uniform(*box_height_m)),
                        albedo=float(rng.uniform(0.7, 1.1)),
                        contrast=float(rng.uniform(0.7, 1.0)),
                    )
                )
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
                trees.append(
                    Tree(
                        x,
                        y,
                        trunk_radius=float(h * rng.uniform(0.025, 0.04)),
                        trunk_height=float(trunk_h),
                        crown_radius=float(crown_r),
                        crown_height=float(h - trunk_h),
                        albedo=float(rng.uniform(0.6, 0.9)),
                        contrast=float(rng.uniform(0.8, 1.0)),
                    )
                )
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
        backdrop = Backdrop(
            (float(backdrop_centre_xy[0]), float(backdrop_centre_xy[1])),
            float(backdrop_radius_m),
            tuple(float(v) for v in h_lo + (h_hi - h_lo) * prof),
        )
    ground = Ground(half_extent_m=ground_half_extent_m, contrast=ground_contrast)
    return Scene(
        seed=int(seed),
        ground=ground,
        boxes=tuple(boxes),
        trees=tuple(trees),
        backdrop=backdrop,
        texture_size=texture_size,
    )


def aerial_scene(seed: int = 0, **overrides) -> Scene:
    """Default multirotor scene: textured ground with buildings and trees over (-40..160) x (-60..60) m,
    no structure taller than 6 m (buildings) / 9 m (trees), so a 12 m flight is clear."""
    return make_scene(seed, **overrides)


def far_structure_scene(
    seed: int = 0,
    route_xy: np.ndarray | None = None,
    *,
    centre_xy: tuple[float, float] = (0.0, 0.0),
    backdrop_radius_m: float = 60.0,
    near_clearance_m: float = 25.0,
    **overrides,
) -> Scene:
    """Scene whose texture lies mostly far away, for ground-vehicle turning tests.

    The ground is faint (contrast 0.15); trees and buildings stand at least ``near_clearance_m`` from the
    route polyline ``route_xy`` (M, 2) (or from ``centre_xy`` when no route is given), and a textured
    mountain wall of ``backdrop_radius_m`` surrounds ``centre_xy``. With a 0.12 m baseline, 40 baselines
    is 4.8 m; with 0.537 m it is 21.5 m -- both well inside the clearance.
    """
    cx, cy = centre_xy
    r = backdrop_radius_m * 0.9
    path = np.array([centre_xy], float) if route_xy is None else np.asarray(route_xy, float)
    kw: dict = dict(
        area_m=(cx - r, cx + r, cy - r, cy + r),
        n_boxes=25,
        n_trees=60,
        box_size_m=(3.0, 12.0),
        box_height_m=(3.0, 12.0),
        tree_height_m=(5.0, 14.0),
        clear_path_xy=path,
        clear_radius_m=near_clearance_m,
        ground_contrast=0.15,
        backdrop_radius_m=backdrop_radius_m,
        backdrop_centre_xy=centre_xy,
        backdrop_height_m=(0.1 * backdrop_radius_m, 0.3 * backdrop_radius_m),
    )
    kw.update(overrides)
    return make_scene(seed, **kw)
