"""The perception model end to end on imagery: teach, repeat, landmarks.csv, fit (binned and MLE), report.

usage: python tools/perception_end_to_end.py [OUT] [--lateral 0,2,4,8] [--vertical 0,3] [--length 30]
                                             [--kitti datasets/kitti06_clip] [--skip synthetic|kitti] [--reuse]

Two data sets:

- synthetic: an aerial route taught in a rendered scene (tools/synthetic_offsets.py) and repeated at
  every (lateral, vertical) offset; exact ground truth; with the defaults 95 % of the parallax angles
  lie below ~30 deg;
- kitti: the shipped KITTI clip, taught on frames 0::2 and repeated on 1::2 and 1::3 (each repeat
  against its own copy of the map). The repeat camera stays within ~1 m of the taught one, so the
  parallax range is narrow (a few degrees): read its fit as a check of the pipeline, not a model.

For each data set both fits (``perception_model.fit_observations``, 20 % of the localizations held
out) give c with 95 % intervals, R^2 over (alpha, theta) bins, log-loss (training, held out, and
the held-out log-loss of a constant predictor for scale); the signs of c3 (probability falls with
parallax) and c2 (falls with view angle), and model-free checks on the binned inlier frequencies:
marginal trends over alpha and theta bins and trends within bands of the other angle (Spearman
rho, steps down, steps up beyond 2 standard errors). Closed loop: the MLE model's expected inlier
count ``mu`` from the taught map (``vtr.app.perception``, what ``perception-model
constraint --map`` prints) at each repeat's camera positions (synthetic: true; KITTI: estimated),
beside the inlier counts the repeat observed (an in-sample consistency check, not a validation).

Writes OUT/<set>/model_{binned,mle}.json, OUT/<set>/fit_{binned,mle}.png (observed frequency beside
the fitted surface), OUT/summary.json and OUT/summary.csv, and prints a compact table. ``--reuse``
refits existing landmarks.csv files without running teach/repeat again. The default run takes ~4 min
on two shared cores (teach/repeat dominate; fits and checks take ~10 s).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import synthetic_offsets  # noqa: E402  (tools/ is not a package)

from perception_model.errors import PerceptionModelError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_KITTI = ROOT / "datasets" / "kitti06_clip"
KITTI_TEACH = "0::2"
KITTI_REPEATS = ("1::2", "1::3")
HOLDOUT = 0.2
ALPHA_BIN_DEG = 1.0
THETA_BIN_DEG = 2.5
MIN_BIN_COUNT = 10
SIGNIFICANT_SE = 2.0  # a step between bins counts as significant beyond this many standard errors
#: "well determined": relative standard error of every constant below this, correlations below the next
MAX_REL_SE = 0.25
MAX_ABS_CORR = 0.95
#: a constant this close to its lower bound 0 sits on the bound (its interval is then undefined)
AT_BOUND = 1e-6
PERCENTILES = (0, 5, 50, 95, 100)


# --------------------------------------------------------------------------- runs
def synthetic_runs(out: Path, lateral: list[float], vertical: list[float], length: float, seed: int,
                   reuse: bool) -> tuple[list[Path], list[dict]]:
    files = [out / synthetic_offsets.repeat_name(dy, dz) / "landmarks.csv" for dz in vertical for dy in lateral]
    if reuse and all(f.exists() for f in files):
        rows = _read_csv_dicts(out / "offsets.csv") if (out / "offsets.csv").exists() else []
        return files, [{k: float(v) for k, v in r.items()} for r in rows]
    out.mkdir(parents=True, exist_ok=True)
    rows = synthetic_offsets.run(out, lateral, vertical, length, seed)
    with open(out / "offsets.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    synthetic_offsets.plot(rows, out / "inliers_vs_offset.png")
    shutil.rmtree(out / "teach" / "image_0", ignore_errors=True)
    shutil.rmtree(out / "teach" / "image_1", ignore_errors=True)
    return files, rows


def kitti_runs(out: Path, source: Path, reuse: bool) -> tuple[list[Path], list[dict]]:
    names = [f"repeat_{spec.replace('::', '_every')}" for spec in KITTI_REPEATS]
    files = [out / n / "landmarks.csv" for n in names]
    if reuse and all(f.exists() for f in files):
        rows = [json.loads((out / n / "run.json").read_text()).get("summary", {}) for n in names
                if (out / n / "run.json").exists()]
        return files, rows
    from vtr.app.pipeline import repeat_command, teach_command
    from vtr.config import Config

    out.mkdir(parents=True, exist_ok=True)
    map_path = out / "route.vtrmap"
    for f in out.glob("*.vtrmap*"):
        f.unlink()
    teach = teach_command(source, map_path, KITTI_TEACH, Config(), out / "teach")
    rows = []
    for name, spec in zip(names, KITTI_REPEATS, strict=True):
        copy = out / f"{name}.vtrmap"
        shutil.copyfile(map_path, copy)
        summary = repeat_command(source, copy, out / name, spec, Config())
        rows.append({"repeat": spec, "teach": KITTI_TEACH, "teach_vertices": teach.vertices, **summary.to_dict()})
    return files, rows


def _read_csv_dicts(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# --------------------------------------------------------------------------- analysis
def trend_1d(x_deg: np.ndarray, y: np.ndarray, width: float, min_count: int) -> dict[str, Any]:
    """Inlier frequency over bins of one angle (pooled over the other): is it non-increasing?"""
    from scipy.stats import spearmanr

    idx = np.floor(x_deg / width).astype(np.int64)
    n = np.bincount(idx)
    k = np.bincount(idx, weights=y.astype(float))
    keep = np.flatnonzero(n >= min_count)
    f = k[keep] / n[keep]
    centre = (keep + 0.5) * width
    out = _steps(f, n[keep])
    out.update(bins=int(keep.size), centre_deg=centre.round(2).tolist(), frequency=f.round(4).tolist(),
               count=n[keep].tolist())
    out["spearman_rho"] = float(spearmanr(centre, f).statistic) if keep.size >= 3 else math.nan
    return out


def _steps(f: np.ndarray, n: np.ndarray) -> dict[str, Any]:
    if f.size < 2:
        return {"steps": 0, "steps_down": 0, "significant_up": 0, "significant_down": 0}
    d = np.diff(f)
    se = np.sqrt(f * (1 - f) / n)
    se_d = np.sqrt(se[1:] ** 2 + se[:-1] ** 2)
    se_d = np.maximum(se_d, 1e-12)
    return {"steps": int(d.size), "steps_down": int((d < 0).sum()),
            "significant_up": int((d > SIGNIFICANT_SE * se_d).sum()),
            "significant_down": int((d < -SIGNIFICANT_SE * se_d).sum())}


def trend_within(count: np.ndarray, inl: np.ndarray, axis: int, min_count: int) -> dict[str, Any]:
    """Steps along ``axis`` of the (alpha, theta) grid between adjacent bins (both >= min_count) in
    the same band of the other angle: a trend with the other angle held (nearly) fixed."""
    c = np.moveaxis(count, axis, 0)
    k = np.moveaxis(inl, axis, 0)
    tot = {"steps": 0, "steps_down": 0, "significant_up": 0, "significant_down": 0}
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


def _monotonic(obs: Any) -> dict[str, Any]:
    from perception_model.fit import BinSpec, bin_observations

    a_deg, t_deg, y = np.degrees(obs.alpha), np.degrees(obs.theta), obs.inlier
    grid = bin_observations(obs.alpha, obs.theta, y, BinSpec(math.radians(ALPHA_BIN_DEG), math.radians(THETA_BIN_DEG),
                                                             MIN_BIN_COUNT))
    out = {
        "alpha_marginal": trend_1d(a_deg, y, ALPHA_BIN_DEG, MIN_BIN_COUNT),
        "theta_marginal": trend_1d(t_deg, y, THETA_BIN_DEG, MIN_BIN_COUNT),
        "alpha_within_theta_bands": trend_within(grid.count_grid, grid.inlier_grid, 0, MIN_BIN_COUNT),
        "theta_within_alpha_bands": trend_within(grid.count_grid, grid.inlier_grid, 1, MIN_BIN_COUNT),
    }
    for name in ("alpha", "theta"):
        m, w = out[f"{name}_marginal"], out[f"{name}_within_{'theta' if name == 'alpha' else 'alpha'}_bands"]
        # falls: negative rank correlation over bins, more significant falls than rises, and a negative mean
        # step with the other angle held to one band; monotone: in addition no significant rise at all
        out[f"{name}_falls"] = bool(m["spearman_rho"] < 0 and m["significant_down"] > m["significant_up"]
                                    and w["mean_step"] < 0 and w["significant_down"] > w["significant_up"])
        out[f"{name}_monotone"] = bool(out[f"{name}_falls"] and m["significant_up"] == 0)
    return out


def _fit_summary(res: Any, obs_train_rate: float, caught: list[str]) -> dict[str, Any]:
    c = {ci.name: {"estimate": ci.estimate, "low": ci.low, "high": ci.high, "std_err": ci.std_err}
         for ci in res.intervals}
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
    from perception_model.cli import plot_fit
    from perception_model.fit import BinSpec, fit_observations
    from perception_model.io import read_landmarks_csvs

    obs = read_landmarks_csvs(files)
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
        "alpha_deg_percentiles": dict(zip(map(str, PERCENTILES), np.percentile(a_deg, PERCENTILES).round(3).tolist(),
                                          strict=True)),
        "theta_deg_percentiles": dict(zip(map(str, PERCENTILES), np.percentile(t_deg, PERCENTILES).round(3).tolist(),
                                          strict=True)),
        "monotonic": _monotonic(obs),
        "fits": {},
    }
    bins = BinSpec(math.radians(ALPHA_BIN_DEG), math.radians(THETA_BIN_DEG), MIN_BIN_COUNT)
    for method in ("binned", "mle"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                res = fit_observations(obs, method=method, angle_unit="deg", holdout_fraction=HOLDOUT, seed=seed,
                                       bins=bins)
            except PerceptionModelError as err:
                summary["fits"][method] = {"method": method, "error": str(err)}
                continue
        msgs = sorted({str(w.message) for w in caught})
        fs = _fit_summary(res, (res.n_inliers / res.n), msgs)
        res.model.save(out / f"model_{method}.json", fit=res.to_dict(), data=d)
        plot_fit(res, out / f"fit_{method}.png")
        fs["model"] = str(out / f"model_{method}.json")
        fs["heatmap"] = str(out / f"fit_{method}.png")
        summary["fits"][method] = fs
    return summary


def _kitti_poses(path: Path) -> np.ndarray:
    rows = np.loadtxt(path).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = rows
    return T


def synthetic_positions(out: Path, name: str) -> np.ndarray:
    """True camera centres of a synthetic repeat in the map frame (first teach camera), offset reached."""
    T_teach = _kitti_poses(out / "teach" / "poses_world.txt")
    T_rep = _kitti_poses(out / name / "poses_world.txt")
    return (np.linalg.inv(T_teach[0]) @ T_rep)[math.ceil(synthetic_offsets.RAMP_M):, :3, 3]


def kitti_positions(out: Path, name: str) -> np.ndarray:
    """Estimated camera centres of a KITTI repeat in the teach frame (its trajectory_tum.txt)."""
    return np.loadtxt(out / name / "trajectory_tum.txt", ndmin=2)[:, 1:4]


def mu_check(model_path: Path, map_path: Path, runs: list[tuple[str, np.ndarray, Path]]) -> list[dict[str, Any]]:
    """Closed loop: the constraint's ``mu`` on the taught map (``perception-model constraint --map``) at
    each repeat's camera positions, beside the inlier counts that repeat observed (landmarks.csv)."""
    from perception_model.constraint import THESIS_C_BAR, THESIS_L_MIN
    from perception_model.model import PerceptionModel
    from vtr.app.perception import evaluate_on_map

    model = PerceptionModel.load(model_path)
    out = []
    for name, positions, landmarks in runs:
        t = evaluate_on_map(model, map_path, positions, None, l_min=THESIS_L_MIN, c_bar=THESIS_C_BAR, exact=False)
        lm = np.genfromtxt(landmarks, delimiter=",", names=True)
        _, group = np.unique(lm["t_ns"], return_inverse=True)
        inliers = np.bincount(group, weights=lm["inlier"])
        in_view = np.bincount(group)
        out.append({"run": name, "positions": len(t), "localizations": int(inliers.size),
                    "predicted_mu_median": float(np.median(t.mu)), "observed_inliers_median": float(np.median(inliers)),
                    "predicted_mu_mean": float(t.mu.mean()), "observed_inliers_mean": float(inliers.mean()),
                    "predicted_sigma_median": float(np.median(t.sigma)),
                    "in_view_median_map": float(np.median(t.n_in_view)),
                    "in_view_median_observed": float(np.median(in_view))})
    return out


# --------------------------------------------------------------------------- report
def _fmt_c(c: dict[str, float], at_bound: bool, digits: int = 4) -> str:
    if at_bound:
        return f"{c['estimate']:+.{digits}f} {'(at bound 0)':>17s}"
    return f"{c['estimate']:+.{digits}f} [{c['low']:+.{digits}f}, {c['high']:+.{digits}f}]"


def table(results: list[dict[str, Any]]) -> str:
    lines = []
    hdr = (f"{'set':9s} {'n obs':>7s} {'inl%':>5s} {'alpha deg p5/50/95/max':>23s} "
           f"{'theta deg p5/50/95/max':>23s}  corr(alpha, theta)")
    lines.append(hdr)
    for r in results:
        a, t = r["alpha_deg_percentiles"], r["theta_deg_percentiles"]
        lines.append(f"{r['dataset']:9s} {r['n_observations']:7d} {100 * r['inlier_rate']:5.1f} "
                     f"{a['5']:5.1f}/{a['50']:4.1f}/{a['95']:4.1f}/{a['100']:5.1f}   "
                     f"{t['5']:5.1f}/{t['50']:4.1f}/{t['95']:4.1f}/{t['100']:5.1f}   "
                     f"{r['alpha_theta_correlation']:+.2f}")
    lines.append("")
    lines.append(f"{'set':9s} {'fit':6s} {'c1 [95% CI]':>26s} {'c2 [95% CI] /deg':>26s} {'c3 [95% CI] /deg':>26s} "
                 f"{'R2':>6s} {'LL':>6s} {'LLho':>6s} {'LL0':>6s}  d/dalpha d/dtheta   determined")
    for r in results:
        for method in ("binned", "mle"):
            f = r["fits"].get(method)
            if f is None:
                continue
            if "error" in f:
                lines.append(f"{r['dataset']:9s} {method:6s} error: {f['error']}")
                continue
            c = f["c"]
            sa = ("<0*" if f["falls_with_parallax_significant"] else "<0" if f["falls_with_parallax"] else ">=0")
            st = ("=0 (bound)" if "c2" in f["at_bound"] else "<0*" if f["falls_with_view_angle_significant"]
                  else "<0" if f["falls_with_view_angle"] else ">=0")
            det = "yes" if f["well_determined"] else "weak: " + ",".join(f["weakly_determined"])
            lines.append(f"{r['dataset']:9s} {method:6s} "
                         + " ".join(_fmt_c(c[k], k in f["at_bound"]) for k in ("c1", "c2", "c3"))
                         + f" "
                         f"{f['r2_binned']:6.3f} {f['log_loss']:6.3f} {f['holdout_log_loss']:6.3f} "
                         f"{f['holdout_base_rate_log_loss']:6.3f}  {sa:8s} {st:10s} {det}")
    lines.append("")
    lines.append(f"{'set':9s} {'trend of binned frequency':28s} {'rho':>6s} {'down/steps':>10s} {'sig up/down':>11s} "
                 f"{'within-band down/steps':>22s} {'sig up/down':>11s} {'mean step':>9s}  falls monotone")
    for r in results:
        m = r["monotonic"]
        for name, other in (("alpha", "theta"), ("theta", "alpha")):
            mg, wb = m[f"{name}_marginal"], m[f"{name}_within_{other}_bands"]
            lines.append(f"{r['dataset']:9s} {'over ' + name + ' bins':28s} {mg['spearman_rho']:6.2f} "
                         f"{mg['steps_down']:4d}/{mg['steps']:<5d} "
                         f"{mg['significant_up']:5d}/{mg['significant_down']:<5d} "
                         f"{wb['steps_down']:16d}/{wb['steps']:<5d} "
                         f"{wb['significant_up']:5d}/{wb['significant_down']:<5d} "
                         f"{wb['mean_step']:+9.4f}  {m[f'{name}_falls']!s:5s} {m[f'{name}_monotone']}")
    lines.append("")
    lines.append(f"{'set':9s} {'repeat':18s} {'n':>3s} {'mu (map, MLE fit)':>17s} {'sigma':>6s} "
                 f"{'inliers observed':>16s} {'in view map/obs':>16s}   (medians per localization)")
    for r in results:
        for c in r.get("mu_check", []):
            lines.append(f"{r['dataset']:9s} {c['run']:18s} {c['positions']:3d} {c['predicted_mu_median']:17.0f} "
                         f"{c['predicted_sigma_median']:6.1f} {c['observed_inliers_median']:16.0f} "
                         f"{c['in_view_median_map']:8.0f}/{c['in_view_median_observed']:<7.0f}")
    lines.append("(R2: count-weighted over (alpha, theta) bins of the training data; LL: log-loss training / held out "
                 "/ constant predictor on the held-out data; d/dalpha, d/dtheta: sign of the model's slope, "
                 "* = CI excludes 0; steps between adjacent bins of >= 10 observations, sig = beyond 2 s.e.)")
    return "\n".join(lines)


def write_summary_csv(results: list[dict[str, Any]], path: Path) -> None:
    rows = []
    for r in results:
        for method, f in r["fits"].items():
            row: dict[str, Any] = {"dataset": r["dataset"], "method": method, "n_observations": r["n_observations"],
                                   "n_localizations": r["n_localizations"], "inlier_rate": r["inlier_rate"]}
            for q in ("5", "50", "95", "100"):
                row[f"alpha_deg_p{q}"] = r["alpha_deg_percentiles"][q]
            for q in ("5", "50", "95", "100"):
                row[f"theta_deg_p{q}"] = r["theta_deg_percentiles"][q]
            if "error" in f:
                row["error"] = f["error"]
            else:
                for name, c in f["c"].items():
                    row[name], row[f"{name}_low"], row[f"{name}_high"] = c["estimate"], c["low"], c["high"]
                for key in ("r2_binned", "log_loss", "holdout_log_loss", "holdout_base_rate_log_loss",
                            "falls_with_parallax", "falls_with_parallax_significant", "falls_with_view_angle",
                            "falls_with_view_angle_significant", "well_determined"):
                    row[key] = f[key]
            for name in ("alpha", "theta"):
                row[f"{name}_bins_falls"] = r["monotonic"][f"{name}_falls"]
                row[f"{name}_bins_monotone"] = r["monotonic"][f"{name}_monotone"]
            rows.append(row)
    fields: list[str] = []
    for row in rows:
        fields += [k for k in row if k not in fields]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)


def _jsonable(x: Any) -> Any:
    """NaN/inf -> None (strict JSON), numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v.strip()]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("out", nargs="?", default="out/perception_end_to_end", type=Path)
    ap.add_argument("--lateral", default="0,2,4,8", help="lateral repeat offsets (m, left)")
    ap.add_argument("--vertical", default="0,3", help="vertical repeat offsets (m, up)")
    ap.add_argument("--length", type=float, default=30.0, help="taught synthetic route length (m)")
    ap.add_argument("--seed", type=int, default=0, help="scene seed and hold-out split seed")
    ap.add_argument("--kitti", type=Path, default=DEFAULT_KITTI, help="KITTI-layout source")
    ap.add_argument("--skip", action="append", choices=["synthetic", "kitti"], default=[])
    ap.add_argument("--reuse", action="store_true", help="refit existing landmarks.csv files (no teach/repeat)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results, timings, runs = [], {}, {}
    if "synthetic" not in args.skip:
        t0 = time.perf_counter()
        files, rows = synthetic_runs(args.out / "synthetic", _floats(args.lateral), _floats(args.vertical),
                                     args.length, args.seed, args.reuse)
        timings["synthetic_runs_s"] = time.perf_counter() - t0
        runs["synthetic"] = rows
        t0 = time.perf_counter()
        res = analyse("synthetic", files, args.out / "synthetic", args.seed)
        if "error" not in res["fits"]["mle"]:
            syn_out = args.out / "synthetic"
            res["mu_check"] = mu_check(syn_out / "model_mle.json", syn_out / "route.vtrmap",
                                       [(f.parent.name, synthetic_positions(syn_out, f.parent.name), f) for f in files])
        results.append(res)
        timings["synthetic_fit_s"] = time.perf_counter() - t0
    if "kitti" not in args.skip:
        t0 = time.perf_counter()
        files, rows = kitti_runs(args.out / "kitti", args.kitti, args.reuse)
        timings["kitti_runs_s"] = time.perf_counter() - t0
        runs["kitti"] = rows
        t0 = time.perf_counter()
        res = analyse("kitti", files, args.out / "kitti", args.seed)
        if "error" not in res["fits"]["mle"]:
            k_out = args.out / "kitti"
            res["mu_check"] = mu_check(k_out / "model_mle.json", k_out / "route.vtrmap",
                                       [(f.parent.name, kitti_positions(k_out, f.parent.name), f) for f in files])
        results.append(res)
        timings["kitti_fit_s"] = time.perf_counter() - t0
    summary = {"command": " ".join(sys.argv), "lateral_m": _floats(args.lateral), "vertical_m": _floats(args.vertical),
               "length_m": args.length, "kitti_teach": KITTI_TEACH, "kitti_repeats": list(KITTI_REPEATS),
               "timings_s": timings, "runs": runs, "results": results}
    (args.out / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2, allow_nan=False) + "\n")
    write_summary_csv(results, args.out / "summary.csv")
    print(table(results))
    print(f"wrote {args.out / 'summary.json'}, {args.out / 'summary.csv'} and the heatmaps "
          f"({', '.join(f'{k} {v:.0f} s' for k, v in timings.items())})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
