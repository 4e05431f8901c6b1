"""Plots (PNG, headless Agg backend; matplotlib imported lazily)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


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
