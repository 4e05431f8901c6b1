"""Scale of ``perception-model fit``: seconds, rows/s and peak resident memory at 1 M and 10 M rows.

Generates synthetic landmarks files (CSV and Parquet, through ``perception_model``'s own writer)
with labels drawn from known model constants, then runs ``perception-model fit`` in a fresh
process per case exactly as a user would (``python -m perception_model.cli fit FILE --out ...``),
and measures that process: wall time and peak RSS (``os.wait4`` rusage of the child, the figure
``/usr/bin/time -v`` reports as "Maximum resident set size"). Prints a table and writes JSON.

    python tools/bench_fit_scale.py --out out/bench_fit_scale            # 1 M and 10 M, csv + parquet
    python tools/bench_fit_scale.py --rows 1000000 --methods binned,mle
    python tools/bench_fit_scale.py --rows 1000000 --formats csv --baseline-src /tmp/vtr_before

``--baseline-src DIR`` also runs the fit with ``PYTHONPATH=DIR`` (e.g. an export of an older
commit) on the CSV files, for before/after figures. Files are kept in ``OUT/data`` between runs
(regenerated with ``--regenerate``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from perception_model.landmarks_file import LandmarksWriter, Observations, SourceSpan  # noqa: E402
from perception_model.model import PerceptionModel  # noqa: E402

#: Constants the synthetic labels are drawn from (degrees), c1 < 1.
TRUE_CONSTANTS_DEG = (0.9, 0.028, -0.1)
LANDMARKS_PER_LOCALIZATION = 500
NS_PER_LOCALIZATION = 100_000_000
GENERATE_CHUNK_ROWS = 1_000_000
ALPHA_MAX_DEG, THETA_MAX_DEG = 20.0, 50.0
DEFAULT_ROWS = (1_000_000, 10_000_000)
RUN_TIMEOUT_S = 1800
KIB = 1024


def generate(path: Path, rows: int, seed: int) -> None:
    """Write ``rows`` synthetic landmark rows in chunks (memory bounded by one chunk)."""
    model = PerceptionModel(*TRUE_CONSTANTS_DEG, angle_unit="deg")
    rng = np.random.default_rng(seed)
    tmp = path.with_name(f"{path.stem}.part{path.suffix}")  # same suffix: the writer picks the format by it
    with LandmarksWriter(tmp) as w:
        for start in range(0, rows, GENERATE_CHUNK_ROWS):
            n = min(GENERATE_CHUNK_ROWS, rows - start)
            row = np.arange(start, start + n, dtype=np.int64)
            frame = row // LANDMARKS_PER_LOCALIZATION
            a = np.radians(rng.uniform(0.0, ALPHA_MAX_DEG, n))
            t = np.radians(rng.uniform(0.0, THETA_MAX_DEG, n))
            y = rng.random(n) < model.probability(a, t)
            w.write(
                Observations(
                    a, t, y, frame * NS_PER_LOCALIZATION, frame, frame, row % LANDMARKS_PER_LOCALIZATION,
                    rng.uniform(2.0, 40.0, n), (SourceSpan(str(path), start, n),), y | (rng.random(n) < 0.3),
                )
            )  # fmt: skip
    tmp.replace(path)


def run_fit(data: Path, out: Path, method: str, pythonpath: Path, label: str) -> dict[str, Any]:
    """One ``perception-model fit`` in a fresh process: wall seconds, peak RSS (wait4), exit code, constants."""
    model_path = out / f"model_{data.name}_{method}_{label}.json"
    log = out / f"log_{data.name}_{method}_{label}.txt"
    model_path.unlink(missing_ok=True)  # fit refuses to replace an existing model (no --force: older versions lack it)
    cmd = [sys.executable, "-m", "perception_model.cli", "fit", str(data), "--out", str(model_path),
           "--method", method]  # fmt: skip
    env = dict(os.environ, PYTHONPATH=str(pythonpath))
    with log.open("wb") as fh:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT, cwd=out)
        timer = threading.Timer(RUN_TIMEOUT_S, proc.kill)
        timer.start()
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage
        seconds = time.perf_counter() - t0
        timer.cancel()
    proc.returncode = os.waitstatus_to_exitcode(status)
    rows = _rows(data)
    result: dict[str, Any] = {
        "file": data.name,
        "format": data.suffix.lstrip("."),
        "rows": rows,
        "method": method,
        "code": label,
        "exit_code": proc.returncode,
        "seconds": round(seconds, 2),
        "rows_per_s": round(rows / seconds) if proc.returncode == 0 else None,
        "peak_rss_mb": round(usage.ru_maxrss * KIB / 1e6, 1),  # Linux: ru_maxrss in KiB
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 2),
    }
    if proc.returncode == 0:
        fitted = json.loads(model_path.read_text())
        result["constants"] = [fitted["c1"], fitted["c2"], fitted["c3"]]
        result["c1_at_bound"] = fitted.get("fit", {}).get("c1_at_bound")
    else:
        result["error"] = log.read_text(errors="replace")[-400:]
    return result


def _rows(path: Path) -> int:
    return int(path.name.split("_")[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("out/bench_fit_scale"))
    ap.add_argument("--rows", type=lambda s: [int(v) for v in s.split(",")], default=list(DEFAULT_ROWS))
    ap.add_argument("--formats", default="csv,parquet")
    ap.add_argument("--methods", default="binned")
    ap.add_argument(
        "--baseline-src",
        type=Path,
        default=None,
        help="also run this source tree's perception-model fit on the CSV files (before/after)",
    )
    ap.add_argument(
        "--baseline-max-rows", type=int, default=1_000_000, help="run the baseline only up to this many rows"
    )
    ap.add_argument("--regenerate", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out: Path = args.out
    (out / "data").mkdir(parents=True, exist_ok=True)
    formats = args.formats.split(",")
    methods = args.methods.split(",")
    results = []
    for rows in args.rows:
        for fmt in formats:
            data = out / "data" / f"landmarks_{rows}_rows.{fmt}"
            if args.regenerate or not data.is_file():
                t0 = time.perf_counter()
                generate(data, rows, args.seed)
                print(f"generated {data} ({data.stat().st_size / 1e6:.0f} MB) in {time.perf_counter() - t0:.1f} s",
                      flush=True)  # fmt: skip
            codes = [("after", ROOT)]
            if args.baseline_src is not None and fmt == "csv" and rows <= args.baseline_max_rows:
                codes.insert(0, ("before", args.baseline_src.resolve()))
            for method in methods:
                for label, src in codes:
                    r = run_fit(data, out, method, src, label)
                    r["file_mb"] = round(data.stat().st_size / 1e6, 1)
                    results.append(r)
                    print(_line(r), flush=True)
    report = {
        "true_constants_deg": TRUE_CONSTANTS_DEG,
        "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0], "load_avg_1min": os.getloadavg()[0]},
        "results": results,
    }
    (out / "bench_fit_scale.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out / 'bench_fit_scale.json'}")


def _line(r: dict[str, Any]) -> str:
    c = r.get("constants")
    cs = "(" + ", ".join(f"{v:.4g}" for v in c) + ")" if c else r.get("error", "")[-120:].replace("\n", " ")
    rate = f"{r['rows_per_s'] / 1e6:6.2f} M rows/s" if r["rows_per_s"] else "     failed"
    return (f"{r['code']:6s} {r['format']:7s} {r['rows']:>10,d} rows {r['method']:6s}  {r['seconds']:7.1f} s  "
            f"{rate}  peak RSS {r['peak_rss_mb']:7.0f} MB  c = {cs}"
            + ("  [c1 at bound]" if r.get("c1_at_bound") else ""))  # fmt: skip


if __name__ == "__main__":
    main()
