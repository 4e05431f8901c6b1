"""Analysis of perception-model fits on repeat data: both fits with their diagnostics, model-free trend
checks on the binned inlier frequency, and a compact text report.

``analyse`` fits ``p = c1 cos(c2 theta) exp(c3 alpha)`` by binned least squares and by Bernoulli maximum
likelihood on the ``landmarks.csv`` files of one data set (``SETTINGS``, the package's fit settings:
``holdout_fraction`` of the localizations held out) and reports c with 95 % intervals, whether each
constant is well determined, R² over (alpha, theta) bins, log-loss (training, held out, and a constant
predictor's on the held-out data), the signs of the slopes, and model-free checks: trends of the binned
frequency over each angle, pooled and within bands of the other angle (Spearman rho, steps down, steps up
beyond ``SIGNIFICANT_SE`` standard errors).
``tools/perception_end_to_end.py`` runs it on synthetic and KITTI repeats.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from .errors import PerceptionModelError
from .fit import bin_observations, fit_observations
from .landmarks_file import FIT_FIELDS, read_landmarks_files
from .plots import plot_fit
from .settings import METHODS, FitSettings

#: Both fits and the model-free checks use the package's defaults (bins, ``holdout_fraction`` held out),
#: constants in degrees.
SETTINGS = FitSettings(angle_unit="deg")
SIGNIFICANT_SE = 2.0  # a step between bins counts as significant beyond this many standard errors
#: "well determined": relative standard error of every constant below this, correlations below the next
MAX_REL_SE = 0.25
MAX_ABS_CORR = 0.95
#: a constant this close to its lower bound 0 sits on the bound (its interval is then undefined)
AT_BOUND = 1e-6
PERCENTILES = (0, 5, 50, 95, 100)


# --------------------------------------------------------------------------- analysis
def trend_1d(x_deg: np.ndarray, y: np.ndarray, width: float, min_count: int) -> dict[str, Any]:
    """Inlier frequency over bins of one angle (pooled over the other): is it non-increasing?"""
    from scipy.stats import spearmanr  # scipy.stats costs ~0.8 s to import: only the trend check needs it

    idx = np.floor(x_deg / width).astype(np.int64)
    n = np.bincount(idx)
    k = np.bincount(idx, weights=y.astype(float))
    keep = np.flatnonzero(n >= min_count)
    f = k[keep] / n[keep]
    centre = (keep + 0.5) * width
    out = _steps(f, n[keep])
    out.update(
        bins=int(keep.size), centre_deg=centre.round(2).tolist(), frequency=f.round(4).tolist(), count=n[keep].tolist()
    )
    out["spearman_rho"] = float(spearmanr(centre, f).statistic) if keep.size >= 3 else math.nan
    return out


def _steps(f: np.ndarray, n: np.ndarray) -> dict[str, Any]:
    if f.size < 2:
        return {"steps": 0, "steps_down": 0, "significant_up": 0, "significant_down": 0}
    d = np.diff(f)
    se = np.sqrt(f * (1 - f) / n)
    se_d = np.sqrt(se[1:] ** 2 + se[:-1] ** 2)
    se_d = np.maximum(se_d, 1e-12)
    return {
        "steps": int(d.size),
        "steps_down": int((d < 0).sum()),
        "significant_up": int((d > SIGNIFICANT_SE * se_d).sum()),
        "significant_down": int((d < -SIGNIFICANT_SE * se_d).sum()),
    }


def trend_within(count: np.ndarray, inl: np.ndarray, axis: int, min_count: int) -> dict[str, Any]:
    """Steps along ``axis`` of the (alpha, theta) grid between adjacent bins (both >= min_count) in
    the same band of the other angle: a trend with the other angle held (nearly) fixed."""
    c = np.moveaxis(count, axis, 0)
    k = np.moveaxis(inl, axis, 0)
    tot: dict[str, float] = {"steps": 0, "steps_down": 0, "significant_up": 0, "significant_down": 0}
    wsum = wdiff = 0.0
    for j in range(c.shape[1]):
        n = c[:, j]
        ok = (n[:-1] >= min_count) & (n[1:] >= min_count)
        for i in np.flatnonzero(ok):
            f = k[i : i + 2, j] / n[i : i + 2]
            s = _steps(f, n[i : i + 2])
            for key in tot:
                tot[key] += s[key]
            w = float(min(n[i], n[i + 1]))
            wsum += w
            wdiff += w * float(f[1] - f[0])
    tot["mean_step"] = wdiff / wsum if wsum else math.nan  # count-weighted mean frequency change per bin
    return tot


def monotonic_checks(obs: Any) -> dict[str, Any]:
    """Model-free checks on the binned inlier frequency: marginal trends over alpha and theta bins and
    trends within bands of the other angle; ``<angle>_falls`` and ``<angle>_monotone`` verdicts."""
    a_deg, t_deg, y = np.degrees(obs.alpha), np.degrees(obs.theta), obs.inlier
    s = SETTINGS
    grid = bin_observations(obs.samples(), s.bins)
    out: dict[str, Any] = {
        "alpha_marginal": trend_1d(a_deg, y, s.alpha_bin_deg, s.min_bin_count),
        "theta_marginal": trend_1d(t_deg, y, s.theta_bin_deg, s.min_bin_count),
        "alpha_within_theta_bands": trend_within(grid.count_grid, grid.inlier_grid, 0, s.min_bin_count),
        "theta_within_alpha_bands": trend_within(grid.count_grid, grid.inlier_grid, 1, s.min_bin_count),
    }
    for name in ("alpha", "theta"):
        m, w = out[f"{name}_marginal"], out[f"{name}_within_{'theta' if name == 'alpha' else 'alpha'}_bands"]
        # falls: negative rank correlation over bins, more significant falls than rises, and a negative mean
        # step with the other angle held to one band; monotone: in addition no significant rise at all
        out[f"{name}_falls"] = bool(
            m["spearman_rho"] < 0
            and m["significant_down"] > m["significant_up"]
            and w["mean_step"] < 0
            and w["significant_down"] > w["significant_up"]
        )
        out[f"{name}_monotone"] = bool(out[f"{name}_falls"] and m["significant_up"] == 0)
    return out


def fit_summary(res: Any, obs_train_rate: float, caught: list[str]) -> dict[str, Any]:
    """The numbers of one fit: constants with intervals and correlations, whether they are well determined,
    R², log-loss (training, held out, constant predictor), the signs of the slopes, warnings caught."""
    c = {
        ci.name: {"estimate": ci.estimate, "low": ci.low, "high": ci.high, "std_err": ci.std_err}
        for ci in res.intervals
    }
    cov = np.asarray(res.covariance)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(sd, sd)
    rel_se = {k: abs(v["std_err"] / v["estimate"]) if v["estimate"] else math.inf for k, v in c.items()}
    pairs = {"c1_c2": corr[0, 1], "c1_c3": corr[0, 2], "c2_c3": corr[1, 2]}
    at_bound = [k for k, v in c.items() if k != "c3" and v["estimate"] <= AT_BOUND]  # c1, c2 >= 0 in both fits
    for k in at_bound:  # the model is flat in a constant at 0 (cos is even): no interval from the curvature
        c[k].update(low=math.nan, high=math.nan, std_err=math.nan)
    weak = [k for k, v in rel_se.items() if not v < MAX_REL_SE]
    weak += [k for k, v in pairs.items() if not abs(v) < MAX_ABS_CORR]
    ho = res.holdout
    base = math.nan
    if ho is not None:  # held-out log-loss of the constant predictor p = training inlier rate
        q = min(max(obs_train_rate, 1e-6), 1 - 1e-6)
        r = ho.n_inliers / ho.n
        base = -(r * math.log(q) + (1 - r) * math.log(1 - q))
    return {
        "method": res.method,
        "ci_method": res.ci_method,
        "n_train": res.n,
        "c": c,
        "c1_at_bound": res.c1_at_bound,  # c1 = 1: the fit's probability bound is active
        "correlation": {k: float(v) for k, v in pairs.items()},
        "relative_std_err": rel_se,
        "at_bound": at_bound,
        "well_determined": not weak,
        "weakly_determined": weak,
        "r2_binned": res.r2,
        "log_loss": res.log_loss,
        "n_bins": res.n_bins,
        "holdout_log_loss": ho.log_loss if ho else math.nan,
        "holdout_r2_binned": ho.r2 if ho else math.nan,
        "holdout_brier": ho.brier if ho else math.nan,
        "holdout_base_rate_log_loss": base,
        "converged": res.converged,
        "falls_with_parallax": c["c3"]["estimate"] < 0,
        "falls_with_parallax_significant": c["c3"]["high"] < 0,
        "falls_with_view_angle": c["c2"]["estimate"] > AT_BOUND,
        "falls_with_view_angle_significant": c["c2"]["low"] > 0,
        "warnings": caught,
    }


def analyse(name: str, files: list[Path], out: Path, seed: int) -> dict[str, Any]:
    """Fit both models (binned, MLE; ``SETTINGS.holdout_fraction`` held out) on the ``landmarks.csv`` files of one
    data set, save ``model_<method>.json`` and ``fit_<method>.png`` under ``out``; summary with the checks."""

    obs = read_landmarks_files(files, FIT_FIELDS)
    a_deg, t_deg = np.degrees(obs.alpha), np.degrees(obs.theta)
    d = obs.describe()
    summary: dict[str, Any] = {
        "dataset": name,
        "files": [str(f) for f in files],
        "n_observations": d["n_observations"],
        "n_inliers": d["n_inliers"],
        "n_localizations": d["n_localizations"],
        "inlier_rate": d["n_inliers"] / max(d["n_observations"], 1),
        "alpha_theta_correlation": float(np.corrcoef(a_deg, t_deg)[0, 1]),
        "alpha_deg_percentiles": dict(
            zip(map(str, PERCENTILES), np.percentile(a_deg, PERCENTILES).round(3).tolist(), strict=True)
        ),
        "theta_deg_percentiles": dict(
            zip(map(str, PERCENTILES), np.percentile(t_deg, PERCENTILES).round(3).tolist(), strict=True)
        ),
        "monotonic": monotonic_checks(obs),
        "fits": {},
    }
    for method in METHODS:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                res = fit_observations(obs, SETTINGS.replace(method=method, seed=seed))
            except PerceptionModelError as err:
                summary["fits"][method] = {"method": method, "error": str(err)}
                continue
        msgs = sorted({str(w.message) for w in caught})
        fs = fit_summary(res, (res.n_inliers / res.n), msgs)
        res.model.save(out / f"model_{method}.json", fit=res.to_dict(), data=d)
        plot_fit(res, out / f"fit_{method}.png")
        fs["model"] = str(out / f"model_{method}.json")
        fs["heatmap"] = str(out / f"fit_{method}.png")
        summary["fits"][method] = fs
    return summary


# --------------------------------------------------------------------------- report
def _fmt_c(c: dict[str, float], at_bound: bool, digits: int = 4) -> str:
    if at_bound:
        return f"{c['estimate']:+.{digits}f} {'(at bound 0)':>17s}"
    return f"{c['estimate']:+.{digits}f} [{c['low']:+.{digits}f}, {c['high']:+.{digits}f}]"


def table(results: list[dict[str, Any]]) -> str:
    """A compact text report of :func:`analyse` summaries (with ``mu_check`` rows when present)."""
    lines = []
    hdr = (
        f"{'set':9s} {'n obs':>7s} {'inl%':>5s} {'alpha deg p5/50/95/max':>23s} "
        f"{'theta deg p5/50/95/max':>23s}  corr(alpha, theta)"
    )
    lines.append(hdr)
    for r in results:
        a, t = r["alpha_deg_percentiles"], r["theta_deg_percentiles"]
        lines.append(
            f"{r['dataset']:9s} {r['n_observations']:7d} {100 * r['inlier_rate']:5.1f} "
            f"{a['5']:5.1f}/{a['50']:4.1f}/{a['95']:4.1f}/{a['100']:5.1f}   "
            f"{t['5']:5.1f}/{t['50']:4.1f}/{t['95']:4.1f}/{t['100']:5.1f}   "
            f"{r['alpha_theta_correlation']:+.2f}"
        )
    lines.append("")
    lines.append(
        f"{'set':9s} {'fit':6s} {'c1 [95% CI]':>26s} {'c2 [95% CI] /deg':>26s} {'c3 [95% CI] /deg':>26s} "
        f"{'R2':>6s} {'LL':>6s} {'LLho':>6s} {'LL0':>6s}  d/dalpha d/dtheta   determined"
    )
    for r in results:
        for method in ("binned", "mle"):
            f = r["fits"].get(method)
            if f is None:
                continue
            if "error" in f:
                lines.append(f"{r['dataset']:9s} {method:6s} error: {f['error']}")
                continue
            c = f["c"]
            sa = "<0*" if f["falls_with_parallax_significant"] else "<0" if f["falls_with_parallax"] else ">=0"
            st = (
                "=0 (bound)"
                if "c2" in f["at_bound"]
                else "<0*"
                if f["falls_with_view_angle_significant"]
                else "<0"
                if f["falls_with_view_angle"]
                else ">=0"
            )
            det = "yes" if f["well_determined"] else "weak: " + ",".join(f["weakly_determined"])
            lines.append(
                f"{r['dataset']:9s} {method:6s} "
                + " ".join(_fmt_c(c[k], k in f["at_bound"]) for k in ("c1", "c2", "c3"))
                + f" "
                f"{f['r2_binned']:6.3f} {f['log_loss']:6.3f} {f['holdout_log_loss']:6.3f} "
                f"{f['holdout_base_rate_log_loss']:6.3f}  {sa:8s} {st:10s} {det}"
            )
    lines.append("")
    lines.append(
        f"{'set':9s} {'trend of binned frequency':28s} {'rho':>6s} {'down/steps':>10s} {'sig up/down':>11s} "
        f"{'within-band down/steps':>22s} {'sig up/down':>11s} {'mean step':>9s}  falls monotone"
    )
    for r in results:
        m = r["monotonic"]
        for name, other in (("alpha", "theta"), ("theta", "alpha")):
            mg, wb = m[f"{name}_marginal"], m[f"{name}_within_{other}_bands"]
            lines.append(
                f"{r['dataset']:9s} {'over ' + name + ' bins':28s} {mg['spearman_rho']:6.2f} "
                f"{mg['steps_down']:4d}/{mg['steps']:<5d} "
                f"{mg['significant_up']:5d}/{mg['significant_down']:<5d} "
                f"{wb['steps_down']:16d}/{wb['steps']:<5d} "
                f"{wb['significant_up']:5d}/{wb['significant_down']:<5d} "
                f"{wb['mean_step']:+9.4f}  {m[f'{name}_falls']!s:5s} {m[f'{name}_monotone']}"
            )
    lines.append("")
    lines.append(
        f"{'set':9s} {'repeat':18s} {'n':>3s} {'mu (map, MLE fit)':>17s} {'sigma':>6s} "
        f"{'inliers observed':>16s} {'in view map/obs':>16s}   (medians per localization)"
    )
    for r in results:
        for c in r.get("mu_check", []):
            lines.append(
                f"{r['dataset']:9s} {c['run']:18s} {c['positions']:3d} {c['predicted_mu_median']:17.0f} "
                f"{c['predicted_sigma_median']:6.1f} {c['observed_inliers_median']:16.0f} "
                f"{c['in_view_median_map']:8.0f}/{c['in_view_median_observed']:<7.0f}"
            )
    lines.append(
        "(R2: count-weighted over (alpha, theta) bins of the training data; LL: log-loss training / held out "
        "/ constant predictor on the held-out data; d/dalpha, d/dtheta: sign of the model's slope, "
        "* = CI excludes 0; steps between adjacent bins of >= 10 observations, sig = beyond 2 s.e.)"
    )
    return "\n".join(lines)
