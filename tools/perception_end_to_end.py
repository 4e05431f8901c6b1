"""The perception model end to end on imagery: teach, repeat, landmarks.csv, fit (binned and MLE), report.

usage: python tools/perception_end_to_end.py [OUT] [--lateral 0,2,4,8] [--vertical 0,3] [--length 30]
                                             [--kitti datasets/kitti06_clip] [--skip synthetic|kitti] [--reuse]

Two data sets:

- synthetic: an aerial route taught in a rendered scene (``vtr.app.offsets``) and repeated at
  every (lateral, vertical) offset; exact ground truth; with the defaults 95 % of the parallax angles
  lie below ~30 deg;
- kitti: the shipped KITTI clip, taught on frames 0::2 and repeated on 1::2 and 1::3 (each repeat
  against its own copy of the map). The repeat camera stays within ~1 m of the taught one, so the
  parallax range is narrow (a few degrees): read its fit as a check of the pipeline, not a model.

For each data set ``perception_model.analysis.analyse`` runs both fits (20 % of the localizations held
out) and give c with 95 % intervals, R^2 over (alpha, theta) bins, log-loss (training, held out, and
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
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import synthetic_offsets  # noqa: E402  (tools/ is not a package: its plot)

from perception_model.analysis import analyse, table  # noqa: E402
from vtr.app.offsets import RAMP_M, repeat_name, run_offset_repeats  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_KITTI = ROOT / "datasets" / "kitti06_clip"
KITTI_TEACH = "0::2"
KITTI_REPEATS = ("1::2", "1::3")


# --------------------------------------------------------------------------- runs
def synthetic_runs(
    out: Path, lateral: list[float], vertical: list[float], length: float, seed: int, reuse: bool
) -> tuple[list[Path], list[dict]]:
    files = [out / repeat_name(dy, dz) / "landmarks.csv" for dz in vertical for dy in lateral]
    if reuse and all(f.exists() for f in files):
        rows = _read_csv_dicts(out / "offsets.csv") if (out / "offsets.csv").exists() else []
        return files, [{k: float(v) for k, v in r.items()} for r in rows]
    out.mkdir(parents=True, exist_ok=True)
    rows = run_offset_repeats(out, lateral, vertical, length, seed)
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
        rows = [
            json.loads((out / n / "run.json").read_text()).get("summary", {})
            for n in names
            if (out / n / "run.json").exists()
        ]
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


def _kitti_poses(path: Path) -> np.ndarray:
    rows = np.loadtxt(path).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :] = rows
    return T


def synthetic_positions(out: Path, name: str) -> np.ndarray:
    """True camera centres of a synthetic repeat in the map frame (first teach camera), offset reached."""
    T_teach = _kitti_poses(out / "teach" / "poses_world.txt")
    T_rep = _kitti_poses(out / name / "poses_world.txt")
    return (np.linalg.inv(T_teach[0]) @ T_rep)[math.ceil(RAMP_M) :, :3, 3]


def kitti_positions(out: Path, name: str) -> np.ndarray:
    """Estimated camera centres of a KITTI repeat in the teach frame (its trajectory_tum.txt)."""
    return np.loadtxt(out / name / "trajectory_tum.txt", ndmin=2)[:, 1:4]


def mu_check(model_path: Path, map_path: Path, runs: list[tuple[str, np.ndarray, Path]]) -> list[dict[str, Any]]:
    """Closed loop: the constraint's ``mu`` on the taught map (``perception-model constraint --map``) at
    each repeat's camera positions, beside the inlier counts that repeat observed (landmarks.csv)."""
    from perception_model.model import PerceptionModel
    from perception_model.settings import THESIS_C_BAR, THESIS_L_MIN
    from vtr.app.perception import evaluate_on_map

    model = PerceptionModel.load(model_path)
    out = []
    for name, positions, landmarks in runs:
        t = evaluate_on_map(model, map_path, positions, None, l_min=THESIS_L_MIN, c_bar=THESIS_C_BAR, exact=False)
        lm = np.genfromtxt(landmarks, delimiter=",", names=True)
        _, group = np.unique(lm["t_ns"], return_inverse=True)
        inliers = np.bincount(group, weights=lm["inlier"])
        in_view = np.bincount(group)
        out.append(
            {
                "run": name,
                "positions": len(t),
                "localizations": int(inliers.size),
                "predicted_mu_median": float(np.median(t.mu)),
                "observed_inliers_median": float(np.median(inliers)),
                "predicted_mu_mean": float(t.mu.mean()),
                "observed_inliers_mean": float(inliers.mean()),
                "predicted_sigma_median": float(np.median(t.sigma)),
                "in_view_median_map": float(np.median(t.n_in_view)),
                "in_view_median_observed": float(np.median(in_view)),
            }
        )
    return out


def write_summary_csv(results: list[dict[str, Any]], path: Path) -> None:
    rows = []
    for r in results:
        for method, f in r["fits"].items():
            row: dict[str, Any] = {
                "dataset": r["dataset"],
                "method": method,
                "n_observations": r["n_observations"],
                "n_localizations": r["n_localizations"],
                "inlier_rate": r["inlier_rate"],
            }
            for q in ("5", "50", "95", "100"):
                row[f"alpha_deg_p{q}"] = r["alpha_deg_percentiles"][q]
            for q in ("5", "50", "95", "100"):
                row[f"theta_deg_p{q}"] = r["theta_deg_percentiles"][q]
            if "error" in f:
                row["error"] = f["error"]
            else:
                for name, c in f["c"].items():
                    row[name], row[f"{name}_low"], row[f"{name}_high"] = c["estimate"], c["low"], c["high"]
                for key in (
                    "r2_binned",
                    "log_loss",
                    "holdout_log_loss",
                    "holdout_base_rate_log_loss",
                    "falls_with_parallax",
                    "falls_with_parallax_significant",
                    "falls_with_view_angle",
                    "falls_with_view_angle_significant",
                    "well_determined",
                ):
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
        files, rows = synthetic_runs(
            args.out / "synthetic", _floats(args.lateral), _floats(args.vertical), args.length, args.seed, args.reuse
        )
        timings["synthetic_runs_s"] = time.perf_counter() - t0
        runs["synthetic"] = rows
        t0 = time.perf_counter()
        res = analyse("synthetic", files, args.out / "synthetic", args.seed)
        if "error" not in res["fits"]["mle"]:
            syn_out = args.out / "synthetic"
            res["mu_check"] = mu_check(
                syn_out / "model_mle.json",
                syn_out / "route.vtrmap",
                [(f.parent.name, synthetic_positions(syn_out, f.parent.name), f) for f in files],
            )
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
            res["mu_check"] = mu_check(
                k_out / "model_mle.json",
                k_out / "route.vtrmap",
                [(f.parent.name, kitti_positions(k_out, f.parent.name), f) for f in files],
            )
        results.append(res)
        timings["kitti_fit_s"] = time.perf_counter() - t0
    summary = {
        "command": " ".join(sys.argv),
        "lateral_m": _floats(args.lateral),
        "vertical_m": _floats(args.vertical),
        "length_m": args.length,
        "kitti_teach": KITTI_TEACH,
        "kitti_repeats": list(KITTI_REPEATS),
        "timings_s": timings,
        "runs": runs,
        "results": results,
    }
    (args.out / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2, allow_nan=False) + "\n")
    write_summary_csv(results, args.out / "summary.csv")
    print(table(results))
    print(
        f"wrote {args.out / 'summary.json'}, {args.out / 'summary.csv'} and the heatmaps "
        f"({', '.join(f'{k} {v:.0f} s' for k, v in timings.items())})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
