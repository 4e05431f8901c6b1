"""Figures of a fit: the observed inlier frequency per (alpha, theta) bin beside the fitted surface.

Used by ``perception-model fit`` (``OUT/fit.png``), :func:`perception_model.analysis.analyse` and ``vtr batch
--fit``. matplotlib is imported inside the function (the Agg backend, no display), so importing this module
costs nothing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .outputs import replace_file

#: Resolution and size of the figure, and the probability levels of the fitted surface's contour lines.
PLOT_DPI = 120
PLOT_SIZE_IN = (12.0, 4.8)
PLOT_CONTOURS = (0.05, 0.1, 0.2, 0.3, 0.4)


def plot_fit(result: Any, path: Path, min_count: int | None = None) -> None:
    """Observed inlier frequency per (alpha, theta) bin beside the fitted surface (cf. thesis Fig. 7.3) and the
    number of observations per bin. Bins with fewer than ``min_count`` observations (the fit did not use
    them; default: the smallest count among the bins it used) are hatched, not coloured: a frequency of 0 or
    1 from a handful of samples says nothing."""
    import matplotlib  # matplotlib (~0.5 s) only when a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np  # here: perception-model --help imports this module (tests/cli/test_startup.py)
    from matplotlib.colors import LogNorm

    model = result.model
    k = model.unit_scale
    unit = model.angle_unit
    binned = result.binned
    counts = binned.count_grid
    if min_count is None:
        min_count = int(binned.count.min()) if binned.count.size else 1
    a_edges, t_edges = binned.alpha_edges, binned.theta_edges
    freq = np.where(counts >= min_count, binned.frequency_grid, np.nan)
    a_mid = 0.5 * (a_edges[1:] + a_edges[:-1])
    t_mid = 0.5 * (t_edges[1:] + t_edges[:-1])
    fitted = model.probability(a_mid[:, None], t_mid[None, :])
    vmax = float(np.nanmax([np.nanmax(freq) if np.isfinite(freq).any() else 0.0, fitted.max(), 1e-3]))
    fig, axes = plt.subplots(
        1, 3, figsize=(PLOT_SIZE_IN[0] * 1.4, PLOT_SIZE_IN[1]), sharey=True, constrained_layout=True
    )
    sparse = (counts > 0) & (counts < min_count)
    contours_drawable = len(a_mid) >= 2 and len(t_mid) >= 2
    for ax, data, title in (
        (axes[0], freq, f"observed inlier frequency (bins with >= {min_count} observations)"),
        (axes[1], fitted, f"fitted model ({result.method})"),
    ):
        mesh = ax.pcolormesh(a_edges * k, t_edges * k, data.T, vmin=0.0, vmax=vmax, cmap="viridis")
        if contours_drawable:  # contour lines need at least 2 x 2 bins (one view-angle row has none)
            cs = ax.contour(
                a_mid * k,
                t_mid * k,
                fitted.T,
                levels=[c for c in PLOT_CONTOURS if c < vmax],
                colors="k",
                linewidths=0.8,
            )
            ax.clabel(cs, fontsize=7)
        ax.set_xlabel(f"parallax angle alpha [{unit}]")
        ax.set_title(title, fontsize=9)
    if sparse.any() and contours_drawable:
        axes[0].contourf(
            a_mid * k, t_mid * k, sparse.T.astype(float), levels=[0.5, 1.5], colors="none", hatches=["////"]
        )
        axes[0].text(
            0.01,
            0.99,
            f"hatched: 1-{min_count - 1} observations (not used)",
            transform=axes[0].transAxes,
            va="top",
            fontsize=7,
            bbox={"facecolor": "white", "alpha": 0.7, "linewidth": 0},
        )
    axes[0].set_ylabel(f"view angle theta [{unit}]")
    fig.colorbar(mesh, ax=axes[:2], label="probability of inlier [-]", shrink=0.9)
    shown = np.where(counts > 0, counts, np.nan)
    cmesh = axes[2].pcolormesh(
        a_edges * k, t_edges * k, shown.T, cmap="magma", norm=LogNorm(vmin=1, vmax=max(2.0, float(counts.max())))
    )
    axes[2].set_xlabel(f"parallax angle alpha [{unit}]")
    axes[2].set_title("observations per bin (white: none)", fontsize=9)
    fig.colorbar(cmesh, ax=axes[2], label="observations [count]", shrink=0.9)
    c1, c2, c3 = model.constants
    fig.suptitle(
        f"perception model fit: p = {c1:.3f} cos({c2:.4f} theta) exp({c3:.4f} alpha), angles in {unit}   "
        f"R^2 = {result.r2:.3f}, n = {result.n}"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        replace_file(path, lambda tmp: fig.savefig(tmp, dpi=PLOT_DPI))  # never through a link at ``path``
    finally:
        plt.close(fig)


def figure_problem(path: Path) -> str | None:
    """Why ``path`` cannot be a figure (its suffix names no format matplotlib writes), as one line, or None."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # matplotlib only when a figure is checked

    formats = FigureCanvasAgg.get_supported_filetypes()
    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix in formats:
        return None
    return (
        f"{path}: not a figure file name (the suffix {('.' + suffix) if suffix else '(none)'} is no image "
        f"format; use one of {', '.join('.' + f for f in sorted(formats))})"
    )
