"""The perception model on a taught ``vtr`` map: ``constraint --map`` and the localization envelope.

The map adapter of ``perception_model`` (which imports nothing from ``vtr``): taught vertices and
their landmarks come from :func:`vtr.control.field.read_taught_vertices`, trunks are chosen by the
localizer's rule (:meth:`vtr.control.field.TaughtPathField.select_trunks`), frames and yaw follow
``perception_model.frames`` (the map's gravity-aligned frame g; for a level first camera, up is the
map's ``-y``, which is the ``perception_model.map_landmarks`` yaw convention).

Landmarks counted: with ``in_view=True`` only trunk landmarks in front of the camera and inside the
image of the map's camera (the population of ``landmarks.csv``, so a model fitted on those files
applies); with ``in_view=False`` every trunk landmark (the model's view cut is then the field of view).

**Localization envelope** (:func:`localization_envelope`): for every taught vertex, how far the
vehicle may move to the taught vehicle's left/right (horizontal, perpendicular to its heading) and
up/down, with the camera as taught (same orientation), before ``mu - c_bar sigma < L_min`` against
that vertex's landmarks. Offsets are scanned on a grid of ``step_m`` up to ``max_m`` and the first
crossing is refined by bisection; a side that never crosses reports ``max_m`` (``*_capped``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception_model import frames
from perception_model.angles import parallax_angle, view_angle
from perception_model.constraint import PerceptionConstraint, check_bounds
from perception_model.errors import GeometryError, InputDataError
from perception_model.map_landmarks import (
    MapConstraintTable,
    camera_rotation_from_yaw,
    yaw_pitch_of_axis,
)
from perception_model.model import PerceptionModel
from perception_model.tails import inlier_moments, normal_tail, poisson_binomial_tail

from ..camera import StereoCamera
from ..control.field import TaughtPathField, TaughtVertex, read_taught_vertices
from ..errors import VtrError
from ..map import Map
from .outputs import OutputFolder
from .runfiles.envelope_csv import DIRECTIONS, envelope_row, write_envelope_rows

#: Envelope defaults: grid step and largest offset scanned (m), bisection steps on a crossing.
ENVELOPE_STEP_M = 0.25
ENVELOPE_MAX_M = 20.0
ENVELOPE_BISECTIONS = 6
#: Domain of the scan: at most this many grid cells per side (max / step) and offsets up to this far; the grid is
#: evaluated this many cells at a time, stopping at the first crossing (memory bounded whatever the grid).
ENVELOPE_MAX_CELLS = 20_000
ENVELOPE_LIMIT_M = 10_000.0
ENVELOPE_CHUNK = 256
#: Work bound of one envelope: at most this many grid evaluations of the bound in the worst case (vertices x 4
#: directions x max / step; each costs about half a millisecond, so this is minutes at most). A crossing is refined
#: by ENVELOPE_BISECTIONS bisections to step / 64 anyway: a finer step rarely changes a figure by a millimetre.
ENVELOPE_MAX_EVALUATIONS = 1_000_000


def open_map(path: str | Path) -> Map:
    """The map read-only; ``InputDataError`` (one line) if it cannot be opened."""
    try:
        return Map.open(Path(path), "r")
    except VtrError as err:
        raise InputDataError(str(err)) from None


def _read(path: str | Path) -> tuple[list[TaughtVertex], StereoCamera, np.ndarray]:
    """The taught vertices, the camera and the map's up direction (stored, else a level first camera's)."""
    with open_map(path) as m:
        try:
            up = m.gravity_up
            return read_taught_vertices(m), m.camera, np.asarray(frames.LEVEL_CAMERA_UP if up is None else up)
        except VtrError as err:
            raise InputDataError(str(err)) from None


def moments_at(
    model: PerceptionModel,
    vertex: TaughtVertex,
    positions_map: np.ndarray,
    R_map_cam: np.ndarray,
    camera: StereoCamera,
    *,
    l_min: float,
    c_bar: float,
    in_view_only: bool = True,
) -> list[np.ndarray]:
    """Inlier probabilities (one array per position) of ``vertex``'s landmarks from cameras at
    ``positions_map`` (K, 3) with rotations ``R_map_cam`` (K, 3, 3); in-view landmarks only by default."""
    pos = np.asarray(positions_map, float)
    if vertex.points_map.shape[0] == 0:
        return [np.zeros(0) for _ in pos]
    centre = vertex.T_map_camera[:3, 3]
    try:
        con = PerceptionConstraint(model, vertex.points_map - centre, l_min=l_min, c_bar=c_bar)
        p = con.evaluate(pos - centre, axes=R_map_cam[:, :, 2], gradient=False).p
    except GeometryError as err:
        raise InputDataError(f"trunk {vertex.vertex_id}: {err}") from None
    if not in_view_only:
        return list(p)
    # rows of (points - c) @ R are R^T (p - c): the landmarks in the camera frame
    return [p[k][camera.in_view((vertex.points_map - pos[k]) @ R_map_cam[k])] for k in range(len(pos))]


def evaluate_on_map(
    model: PerceptionModel,
    map_path: str | Path,
    positions: np.ndarray,
    yaw: np.ndarray | float | None = None,
    *,
    pitch_down: float | None = None,
    l_min: float,
    c_bar: float,
    in_view: bool = True,
    exact: bool = True,
) -> MapConstraintTable:
    """``mu``, ``sigma``, margins and failure probabilities at camera centres ``positions`` (N, 3), map frame.

    ``yaw`` (N,) radians (``perception_model.map_landmarks`` convention) or ``None`` (each trunk's
    orientation); ``pitch_down`` for yaw-defined axes (default the trunk's pitch). Trunks follow the
    localizer's rule from the vertex nearest to the first position.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or pos.shape[0] == 0:
        raise InputDataError(f"positions must have shape (N, 3) with N >= 1, got {pos.shape}")
    n = pos.shape[0]
    psi_in = None if yaw is None else np.broadcast_to(np.asarray(yaw, dtype=np.float64), (n,))
    vertices, camera, up_map = _read(map_path)
    field = TaughtPathField(model, vertices, T_g_map=frames.T_g_map_from_up(up_map), l_min=l_min, c_bar=c_bar)
    pos_g = pos @ field.T_g_map[:3, :3].T
    start = field.nearest_trunk(pos_g[0])
    if psi_in is None:  # selection with the nearest taught vertex's heading at each position
        near = [field.nearest_trunk(p) for p in pos_g]
        sel_yaw = field.vehicle_yaw_g[near]
    else:
        sel_yaw = psi_in
    trunk_idx = field.select_trunks(pos_g, sel_yaw, start)
    yaw_used, pitch_used, R = np.empty(n), np.empty(n), np.empty((n, 3, 3))
    for i, t in enumerate(trunk_idx):
        T = vertices[t].T_map_camera
        t_yaw, t_pitch = yaw_pitch_of_axis(T[:3, 2])
        if psi_in is None:
            R[i], yaw_used[i], pitch_used[i] = T[:3, :3], t_yaw, t_pitch
        else:
            pitch_used[i] = t_pitch if pitch_down is None else pitch_down
            yaw_used[i] = psi_in[i]
            R[i] = camera_rotation_from_yaw(psi_in[i], pitch_used[i])[0]
    p_rows: list[np.ndarray] = [np.zeros(0)] * n
    for t in np.unique(trunk_idx):
        sel = np.flatnonzero(trunk_idx == t)
        rows = moments_at(model, vertices[t], pos[sel], R[sel], camera, l_min=l_min, c_bar=c_bar, in_view_only=in_view)
        for i, p in zip(sel.tolist(), rows, strict=True):
            p_rows[i] = p
    mu = np.array([float(inlier_moments(p)[0]) for p in p_rows])
    sigma = np.sqrt([float(inlier_moments(p)[1]) for p in p_rows])
    used = {int(t) for t in trunk_idx}
    return MapConstraintTable(
        positions=pos,
        yaw=yaw_used,
        pitch_down=pitch_used,
        yaw_given=psi_in is not None,
        trunk_id=np.array([vertices[t].vertex_id for t in trunk_idx], dtype=np.int64),
        trunk_distance_m=np.linalg.norm(pos - np.stack([vertices[t].T_map_camera[:3, 3] for t in trunk_idx]), axis=1),
        n_landmarks=np.array([vertices[t].points_map.shape[0] for t in trunk_idx], dtype=np.int64),
        n_in_view=np.array([p.size for p in p_rows], dtype=np.int64),
        mu=mu,
        sigma=sigma,
        g=mu - c_bar * sigma - l_min,
        g_conservative=mu - c_bar * np.sqrt(mu) - l_min,
        p_fail_normal=np.array(
            [normal_tail(float(m), float(s), l_min, lower=True) for m, s in zip(mu, sigma, strict=True)]
        ),
        p_fail_exact=np.array([poisson_binomial_tail(p, l_min, lower=True) for p in p_rows]) if exact else None,
        n_map_landmarks=int(sum(vertices[t].points_map.shape[0] for t in used)),
    )


# --------------------------------------------------------------------------- envelope
@dataclass(frozen=True)
class EnvelopeRow:
    """How far (m) the vehicle may move from one taught vertex before the bound fails (camera as taught)."""

    vertex_id: int
    position_g: np.ndarray  # taught camera centre in the map's gravity-aligned frame g
    yaw_g: float  # taught heading of the optical axis in g
    bound_taught: float  # mu - c_bar sigma at the vertex itself
    distance_m: dict[str, float]
    capped: dict[str, bool]
    # the bound at that distance rests mostly (> EXTRAPOLATED_SHARE of the expected inliers) on landmarks seen at
    # angles beyond the model's valid range (the angles it was fitted on): a prediction, not a measurement
    extrapolated: dict[str, bool] = dataclasses.field(default_factory=dict)

    @property
    def any_extrapolated(self) -> bool:
        return any(self.extrapolated.values())


#: share of the expected inliers from landmarks outside the model's valid angle range above which a bound is
#: marked extrapolated
EXTRAPOLATED_SHARE = 0.5


def extrapolated_share(
    model: PerceptionModel,
    vertex: TaughtVertex,
    position_map: np.ndarray,
    camera: StereoCamera,
    l_min: float,
    c_bar: float,
) -> float:
    """Share of the expected inliers (sum of p over the in-view landmarks) of ``vertex`` seen from a camera at
    ``position_map`` (taught attitude) that come from landmarks outside the model's valid range of parallax and
    view angles."""

    pos = np.asarray(position_map, float)
    R = vertex.T_map_camera[:3, :3]
    p = moments_at(model, vertex, pos[None], R[None], camera, l_min=l_min, c_bar=c_bar)[0]
    if p.size == 0 or p.sum() <= 0:
        return 0.0
    pts = vertex.points_map[camera.in_view((vertex.points_map - pos) @ R)]
    centre = vertex.T_map_camera[:3, 3]
    alpha = parallax_angle(pts - centre, pos - centre)
    theta = view_angle(pts - centre, pos - centre, R[:, 2])
    outside = (np.nan_to_num(alpha) > model.alpha_max) | (np.nan_to_num(theta) > model.theta_max)
    return float(p[outside].sum() / p.sum())


def _bound(
    model: PerceptionModel,
    vertex: TaughtVertex,
    camera: StereoCamera,
    centres_map: np.ndarray,
    l_min: float,
    c_bar: float,
) -> np.ndarray:
    R = np.broadcast_to(vertex.T_map_camera[:3, :3], (len(centres_map), 3, 3))
    rows = moments_at(model, vertex, centres_map, R, camera, l_min=l_min, c_bar=c_bar)
    return np.array([float(inlier_moments(p)[0]) - c_bar * float(np.sqrt(inlier_moments(p)[1])) for p in rows])


def localization_envelope(
    model: PerceptionModel,
    map_path: str | Path,
    *,
    l_min: float,
    c_bar: float,
    up_map: np.ndarray | None = None,
    step_m: float = ENVELOPE_STEP_M,
    max_m: float = ENVELOPE_MAX_M,
    progress: Callable[[int, int], None] | None = None,
) -> list[EnvelopeRow]:
    """The localization envelope of every taught vertex (see the module docstring); ``up_map`` overrides the
    map's gravity (default: the map's stored up, else a level first camera). ``progress(i, n)`` is called after each
    vertex; the work is bounded (:func:`check_envelope_work`, before any is done)."""
    check_envelope_grid(step_m, max_m)
    check_bounds(l_min, c_bar)
    vertices, camera, stored_up = _read(map_path)
    check_envelope_work(len(vertices), step_m, max_m)
    T_g_map = frames.T_g_map_from_up(stored_up if up_map is None else up_map)
    R_map_g = T_g_map[:3, :3].T
    grid = np.arange(step_m, max_m + 1e-9, step_m)
    rows = []
    for i_vertex, v in enumerate(vertices):
        if progress is not None and i_vertex:
            progress(i_vertex, len(vertices))
        centre = v.T_map_camera[:3, 3]
        heading, _pitch = frames.heading_of_axis(T_g_map[:3, :3] @ v.T_map_camera[:3, 2])
        left = np.array([-np.sin(heading), np.cos(heading), 0.0])
        dirs_g = {"left": left, "right": -left, "up": frames.UP, "down": -frames.UP}
        base = float(_bound(model, v, camera, centre[None], l_min, c_bar)[0])
        dist, capped = {}, {}
        for name, d_g in dirs_g.items():
            d_map = R_map_g @ d_g
            if base < l_min:
                dist[name], capped[name] = 0.0, False
                continue
            first = None
            for k in range(0, len(grid), ENVELOPE_CHUNK):  # chunks: memory bounded, stops at the crossing
                g = grid[k : k + ENVELOPE_CHUNK]
                bad = np.flatnonzero(_bound(model, v, camera, centre + g[:, None] * d_map, l_min, c_bar) < l_min)
                if bad.size:
                    first = float(g[bad[0]])
                    break
            if first is None:
                dist[name], capped[name] = float(max_m), True
                continue
            hi = first
            lo = hi - step_m
            for _ in range(ENVELOPE_BISECTIONS):
                mid = 0.5 * (lo + hi)
                if _bound(model, v, camera, (centre + mid * d_map)[None], l_min, c_bar)[0] < l_min:
                    hi = mid
                else:
                    lo = mid
            dist[name], capped[name] = lo, False
        extrapolated = {
            name: dist[name] > 0
            and extrapolated_share(model, v, centre + dist[name] * (R_map_g @ d_g), camera, l_min, c_bar)
            > EXTRAPOLATED_SHARE
            for name, d_g in dirs_g.items()
        }
        rows.append(
            EnvelopeRow(v.vertex_id, T_g_map[:3, :3] @ centre, float(heading), base, dist, capped, extrapolated)
        )
    if progress is not None:
        progress(len(vertices), len(vertices))
    return rows


def check_envelope_work(n_vertices: int, step_m: float, max_m: float) -> None:
    """``InputDataError`` (one line naming ``--step``) when the worst case of the scan, ``n_vertices`` x 4
    directions x ``max_m / step_m`` evaluations, is above :data:`ENVELOPE_MAX_EVALUATIONS`; it names the finest
    step the map allows."""
    evaluations = n_vertices * len(DIRECTIONS) * (max_m / step_m)
    if evaluations > ENVELOPE_MAX_EVALUATIONS:
        finest = n_vertices * len(DIRECTIONS) * max_m / ENVELOPE_MAX_EVALUATIONS
        raise InputDataError(
            f"envelope --step {step_m:g} m with --max {max_m:g} m on {n_vertices} vertices is up to "
            f"{evaluations:.3g} evaluations of the bound (at most {ENVELOPE_MAX_EVALUATIONS:.0e}, a few minutes); use "
            f"--step {math.ceil(finest * 1e4) / 1e4:g} m or more (each crossing is refined by bisection to step/"
            f"{2**ENVELOPE_BISECTIONS} anyway) or a smaller --max"
        )


def check_envelope_grid(step_m: float, max_m: float) -> None:
    """``InputDataError`` (one line naming ``--step``/``--max``) unless the scan grid is finite and at most
    ``ENVELOPE_MAX_CELLS`` cells a side (``--step 1e-6`` is 2e7 cells: hours, and gigabytes before chunking)."""
    for name, v in (("--step", step_m), ("--max", max_m)):
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            raise InputDataError(f"envelope {name} {v!r}: expected a finite distance > 0 m")
    if max_m > ENVELOPE_LIMIT_M:
        raise InputDataError(f"envelope --max {max_m:g} m: at most {ENVELOPE_LIMIT_M:g} m")
    if step_m > max_m:
        raise InputDataError(f"envelope --step {step_m:g} m must be at most --max {max_m:g} m")
    cells = max_m / step_m
    if cells > ENVELOPE_MAX_CELLS:
        raise InputDataError(
            f"envelope --max {max_m:g} / --step {step_m:g} is {cells:.3g} grid cells a side; at "
            f"most {ENVELOPE_MAX_CELLS} (raise --step to {max_m / ENVELOPE_MAX_CELLS:.3g} m or more: "
            "each crossing is refined by bisection anyway)"
        )


def write_envelope(rows: list[EnvelopeRow], out_dir: Path, *, l_min: float, title: str = "") -> tuple[Path, Path]:
    """``out_dir/envelope.csv`` (one row per vertex) and ``out_dir/envelope.png`` (plan view); returns both paths."""

    folder = OutputFolder.prepare(out_dir, names=["envelope.csv", "envelope.png"])  # never through a link
    with folder.open("envelope.csv") as fh:
        write_envelope_rows(
            fh,
            [
                envelope_row(r.vertex_id, r.position_g, r.yaw_g, r.bound_taught, r.distance_m, r.capped, r.extrapolated)
                for r in rows
            ],
        )
    png = folder.write("envelope.png", lambda p: plot_envelope(rows, p, l_min=l_min, title=title))
    return out_dir / "envelope.csv", png


def plot_envelope(rows: list[EnvelopeRow], path: Path, *, l_min: float, title: str = "") -> None:
    """Plan view of the taught path with the left/right envelope as a band and heading arrows, and the four
    distances per vertex. Distances capped at the scan limit (no crossing found within ``--max``) are marked
    as capped: the true envelope there is at least that wide, the value is not a result."""
    import matplotlib  # matplotlib (~0.5 s) only when the plot is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = np.array([r.position_g for r in rows])
    h = np.array([r.yaw_g for r in rows])
    left = np.stack([-np.sin(h), np.cos(h)], axis=1)
    lm = np.array([r.distance_m["left"] for r in rows])
    rm = np.array([r.distance_m["right"] for r in rows])
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 5.5))
    lb = p[:, :2] + lm[:, None] * left
    rb = p[:, :2] - rm[:, None] * left
    ax.fill(
        np.r_[lb[:, 0], rb[::-1, 0]],
        np.r_[lb[:, 1], rb[::-1, 1]],
        color="tab:green",
        alpha=0.25,
        label="envelope (left/right)",
    )
    ax.plot(p[:, 0], p[:, 1], "k.-", ms=3, label="taught path (vehicle)")
    for edge, d in ((lb, "left"), (rb, "right")):
        capped = np.array([r.capped[d] for r in rows])
        if capped.any():
            ax.plot(
                edge[capped, 0],
                edge[capped, 1],
                "x",
                color="tab:gray",
                ms=4,
                label="capped at the scan limit" if d == "left" else None,
            )
    extent = float(np.ptp(np.r_[lb, rb], axis=0).max()) or 1.0
    every = max(1, len(rows) // 12)
    arrow = 0.1 * extent  # arrows in data units, long enough to see on any route
    ax.quiver(
        p[::every, 0],
        p[::every, 1],
        arrow * np.cos(h[::every]),
        arrow * np.sin(h[::every]),
        angles="xy",
        scale_units="xy",
        scale=1.0,
        width=0.008,
        color="tab:blue",
        zorder=3,
        label=f"heading (every {every} vertices)" if every > 1 else "heading",
    )
    ax.set_aspect("equal")
    ax.set_xlabel("x_g [m] (first taught heading)")
    ax.set_ylabel("y_g [m] (to its left)")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("plan view: where the vehicle may be (camera as taught)", fontsize=10)
    s = np.arange(len(rows))
    for d in DIRECTIONS:
        vals = np.array([r.distance_m[d] for r in rows])
        capped = np.array([r.capped[d] for r in rows])
        (line,) = ax2.plot(s, np.where(capped, np.nan, vals), label=d)
        if capped.any():
            ax2.plot(
                s[capped],
                vals[capped],
                "^",
                mfc="none",
                color=line.get_color(),
                ms=5,
                label=f"{d}: capped ({int(capped.sum())} of {len(rows)})",
            )
    ax2.set_xlabel("taught vertex [index along the path]")
    ax2.set_ylabel("allowed offset [m]")
    ax2.set_title("allowed offset per direction (open triangles: no crossing within the scan limit)", fontsize=10)
    ax2.grid(True, alpha=0.3)
    ax2.legend(fontsize=8, ncol=2)
    fig.suptitle(f"{title or 'localization envelope'} (offsets keeping mu - c_bar sigma >= L_min = {l_min:g} inliers)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


__all__ = [
    "EnvelopeRow",
    "evaluate_on_map",
    "localization_envelope",
    "moments_at",
    "open_map",
    "plot_envelope",
    "write_envelope",
]
