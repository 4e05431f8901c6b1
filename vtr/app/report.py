"""Plots (PNG, headless Agg backend; matplotlib imported lazily)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from ..map import TaughtPath
    from ..navigation.localization import Localization
    from ..navigation.repeat_state import StateTable


def _pyplot() -> Any:
    import matplotlib  # matplotlib (~0.5 s) only when a report is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectory(
    path: Path, T_est: np.ndarray, T_gt: np.ndarray | None = None, failures: np.ndarray | None = None, title: str = ""
) -> None:
    """Plan view (camera x-z plane: x right, z forward) of the estimated and reference trajectories."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(T_est[:, 0, 3], T_est[:, 2, 3], "-", color="C0", label="estimate")
    if T_gt is not None:
        ax.plot(T_gt[:, 0, 3], T_gt[:, 2, 3], "--", color="k", label="ground truth")
    if failures is not None and np.any(failures):
        ax.plot(T_est[failures, 0, 3], T_est[failures, 2, 3], "x", color="C3", label="failure")
    ax.set_xlabel("x [m] (right of first camera)")
    ax.set_ylabel("z [m] (forward of first camera)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend()
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: how localization.csv statuses are drawn in the repeat report: (label, marker, colour)
STATUS_STYLE = {
    "localized": ("localized", "o", "C0"),
    "unconfirmed": ("place candidate, awaiting confirmation", "s", "0.55"),
    "off_route": ("off the route (beyond an end)", "D", "C4"),
}
FAILURE_STYLE = ("not localized (see status in localization.csv)", "x", "C3")


def _spans(mask: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [i, j) where ``mask`` is true."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(int), 0]))
    return list(zip(edges[::2], edges[1::2], strict=True))


def plot_repeat(
    path: Path,
    locs: Sequence[Localization],
    taught: TaughtPath,
    T_teach: np.ndarray,
    t_ns: np.ndarray,
    path_error_m: np.ndarray,
    state: StateTable | None = None,
    *,
    localized: np.ndarray | None = None,
    title: str = "repeat",
    min_inliers: int | None = None,
) -> None:
    """Repeat report: localization inliers per keyframe by outcome, the error to the taught path over time and
    the taught and repeated paths in plan view (teach run's first camera frame: x right, z forward), with
    the stretches where the repeat held no localization shaded.

    ``state`` (optional, e.g. a :class:`vtr.navigation.repeat_state.StateTable`: ``t_ns``, ``lateral``, ``vertical``)
    adds the smoothed signed lateral and vertical errors; ``localized`` (per frame) marks where the chain held a
    localization; ``min_inliers`` draws the inlier count a success needs."""
    plt = _pyplot()
    fig = plt.figure(figsize=(13, 7.5))
    ax1 = fig.add_subplot(2, 2, 1)
    ax2 = fig.add_subplot(2, 2, 3, sharex=ax1)
    ax3 = fig.add_subplot(1, 2, 2)
    t0 = t_ns[0] if len(t_ns) else 0
    tf = (np.asarray(t_ns) - t0) * 1e-9
    tl = np.array([(loc.t_ns - t0) * 1e-9 for loc in locs])
    inl = np.array([loc.inliers for loc in locs])
    status = np.array([getattr(loc.status, "value", "localized" if loc.success else "failed") for loc in locs])
    lost = np.zeros(len(tf), bool) if localized is None else ~np.asarray(localized, bool)
    for ax in (ax1, ax2):
        for i, j in _spans(lost):
            ax.axvspan(tf[i], tf[min(j, len(tf) - 1)], color="0.9", lw=0)
    n_ok = int(np.sum(status == "localized"))
    if len(locs):
        shown = np.zeros(len(locs), bool)
        for key, (label, marker, colour) in STATUS_STYLE.items():
            sel = status == key
            shown |= sel
            if sel.any():
                ax1.plot(tl[sel], inl[sel], marker, color=colour, ms=4, ls="none", label=f"{label} ({sel.sum()})")
        if (~shown).any():
            label, marker, colour = FAILURE_STYLE
            ax1.plot(
                tl[~shown], inl[~shown], marker, color=colour, ms=5, ls="none", label=f"{label} ({(~shown).sum()})"
            )
    if min_inliers is not None:
        ax1.axhline(min_inliers, color="k", lw=0.8, ls="--", label=f"inliers a success needs ({min_inliers})")
    ax1.set_ylabel("localization inliers per keyframe")
    ax1.set_title("localization against the taught path (grey: not localized)", fontsize="medium")
    ax1.legend(fontsize="x-small", loc="best")
    ax1.grid(True, alpha=0.3)
    err = np.asarray(path_error_m, float)
    finite = [a for a in (err, *(() if state is None else (state.lateral, state.vertical))) if np.isfinite(a).any()]
    peak = max((float(np.nanmax(np.abs(a))) for a in finite), default=0.0)
    scale, unit = (1000.0, "mm") if peak < 1.0 else (1.0, "m")
    ax2.plot(
        tf,
        scale * err,
        color="C2",
        label="distance to the taught polyline (chain pose: odometry since the last localization)",
    )
    if state is not None and len(state.t_ns):
        ts = (np.asarray(state.t_ns) - t0) * 1e-9
        ax2.plot(ts, scale * np.asarray(state.lateral), color="C1", lw=1, label="lateral, smoothed (+ left)")
        ax2.plot(ts, scale * np.asarray(state.vertical), color="C4", lw=1, label="vertical, smoothed (+ up)")
        ax2.axhline(0.0, color="k", lw=0.5)
    ax2.legend(fontsize="x-small")
    ax2.set_ylabel(f"error to the taught path [{unit}]")
    ax2.set_xlabel("time since the first frame [s]")
    ax2.set_title(
        "path-tracking error (the taught path is a polyline through its vertices: corners make kinks)", fontsize="small"
    )
    ax2.grid(True, alpha=0.3)
    ax3.plot(taught.positions[:, 0], taught.positions[:, 2], "o-", color="k", ms=3, label="taught path (teach run)")
    if len(T_teach):
        ax3.plot(T_teach[:, 0, 3], T_teach[:, 2, 3], "-", color="C0", lw=1, label="repeat (chain poses)")
        if lost.any():
            ax3.plot(
                T_teach[lost, 0, 3], T_teach[lost, 2, 3], ".", color="C3", ms=3, label="not localized (odometry only)"
            )
    ax3.set_xlabel("x, right of the first taught camera [m]")
    ax3.set_ylabel("z, ahead of the first taught camera [m]")
    ax3.set_title("plan view", fontsize="medium")
    ax3.set_aspect("equal", adjustable="datalim")
    ax3.legend(fontsize="small")
    ax3.grid(True, alpha=0.3)
    fig.suptitle(f"{title}: {len(tf)} frames, {len(locs)} keyframes, {n_ok} localized")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
