"""Plots (PNG, headless Agg backend; matplotlib imported lazily)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..map import TaughtPath


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectory(path: Path, T_est: np.ndarray, T_gt: np.ndarray | None = None,
                    failures: np.ndarray | None = None, title: str = "") -> None:
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


def plot_repeat(path: Path, locs, taught: TaughtPath, T_teach: np.ndarray, t_ns: np.ndarray,
                path_error_m: np.ndarray, state=None) -> None:
    """Repeat report: inliers along the path (failures marked), path-tracking error over time, and the
    taught and repeated paths in plan view (teach run's first camera frame: x right, z forward).

    ``state`` (optional, e.g. a :class:`vtr.navigation.repeat_state.StateTable`: ``t_ns``, ``lateral``, ``vertical``)
    adds the smoothed signed lateral and vertical errors to the path-tracking panel."""
    plt = _pyplot()
    fig = plt.figure(figsize=(12, 7))
    ax1 = fig.add_subplot(2, 2, 1)
    ax2 = fig.add_subplot(2, 2, 3)
    ax3 = fig.add_subplot(1, 2, 2)
    t0 = t_ns[0] if len(t_ns) else 0
    tl = np.array([(loc.t_ns - t0) * 1e-9 for loc in locs])
    inl = np.array([loc.inliers for loc in locs])
    ok = np.array([loc.success for loc in locs], bool)
    if len(locs):
        ax1.plot(tl, inl, ".-", color="C0", label="localization inliers")
        ax1.plot(tl[~ok], np.zeros((~ok).sum()), "x", color="C3", label="failure")
    ax1.set_ylabel("inliers")
    ax1.set_xlabel("time [s]")
    ax1.legend()
    ax1.grid(True, alpha=0.3)
    ax2.plot((t_ns - t0) * 1e-9, path_error_m, color="C2", label="distance (chain poses)")
    if state is not None and len(state.t_ns):
        ts = (np.asarray(state.t_ns) - t0) * 1e-9
        ax2.plot(ts, state.lateral, color="C1", lw=1, label="lateral, smoothed (+ left)")
        ax2.plot(ts, state.vertical, color="C4", lw=1, label="vertical, smoothed (+ up)")
        ax2.axhline(0.0, color="k", lw=0.5)
        ax2.legend(fontsize="small")
    ax2.set_ylabel("error to taught path [m]")
    ax2.set_xlabel("time [s]")
    ax2.grid(True, alpha=0.3)
    ax3.plot(taught.positions[:, 0], taught.positions[:, 2], "o-", color="k", ms=3, label="taught (privileged) path")
    ax3.plot(T_teach[:, 0, 3], T_teach[:, 2, 3], ".-", color="C0", ms=2, label="repeat")
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("z [m]")
    ax3.set_aspect("equal", adjustable="datalim")
    ax3.legend()
    ax3.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
