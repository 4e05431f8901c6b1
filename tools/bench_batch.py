"""Batch throughput and robustness: 2 synthetic aerial routes, each taught once and repeated with lateral
offsets (4 repeats each by default), run by ``vtr batch`` on a local Dask cluster of 1 and of 2 workers.

Shows: wall time with 1 and 2 workers of one thread each (and the ratio); a worker killed (SIGKILL)
mid-run is retried and every output equals the undisturbed run's; Ctrl-C (SIGINT to a ``vtr batch``
process) after some runs finished, then the same command again, runs only what was left and gives the same outputs.

usage: python tools/bench_batch.py [OUT] [--repeats-per-route 4] [--length 80] [--spacing 0.5] [--skip-ctrlc]
Rendered data is kept in OUT/data (made once); results go to OUT/w1, OUT/w2, OUT/killed, OUT/ctrlc and
OUT/bench_batch.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from machine_load import second_core_available  # tools/machine_load.py

from vtr.app.batch import BatchOptions, load_manifest, run_batch
from vtr.app.runfiles.run_json import run_status
from vtr.cli.summaries import batch_table
from vtr.sim.batch_routes import KillWorkerOnce, write_batch_routes

OUTPUTS = ("localization.csv", "landmarks.csv", "trajectory_tum.txt", "state.csv", "frames.csv")
CTRL_C_AFTER_RUNS = 4  # send SIGINT once this many runs have finished


def compare(a: Path, b: Path, manifest) -> list[str]:
    """Output files of every run that differ between batch folders a and b."""
    diff = []
    for spec in manifest.runs():
        for f in OUTPUTS:
            fa, fb = spec.folder(a) / f, spec.folder(b) / f
            if fa.exists() != fb.exists() or (fa.exists() and fa.read_bytes() != fb.read_bytes()):
                diff.append(f"{spec.route}/{spec.name}/{f}")
    return diff


def timed_batch(manifest, out: Path, workers: int, **kw) -> tuple[float, object]:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    result = run_batch(manifest, out, BatchOptions(workers=workers, **kw))
    return time.perf_counter() - t0, result


def ctrl_c_then_rerun(manifest_path: Path, out: Path, n_runs: int) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "vtr", "batch", str(manifest_path), "--out", str(out), "--workers", "2"]
    # SIGINT as a terminal's Ctrl-C; default disposition in the child (a shell's background job ignores SIGINT)
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    manifest = load_manifest(manifest_path)
    while proc.poll() is None:
        done = sum(run_status(s.folder(out)) == "finished" for s in manifest.runs())
        if done >= CTRL_C_AFTER_RUNS:
            proc.send_signal(signal.SIGINT)
            break
        time.sleep(0.05)
    code = proc.wait(timeout=120)
    finished_before = sum(run_status(s.folder(out)) == "finished" for s in manifest.runs())
    t0 = time.perf_counter()
    result = run_batch(manifest, out, BatchOptions(workers=2))
    statuses = [o.status for o in result.outcomes]
    return {
        "exit_code_after_sigint": code,
        "finished_before_rerun": finished_before,
        "rerun_resumed": statuses.count("resumed"),
        "rerun_finished": statuses.count("finished"),
        "rerun_s": time.perf_counter() - t0,
        "runs": n_runs,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", type=Path, default=Path("/tmp/vtr_bench_batch"))
    ap.add_argument("--repeats-per-route", type=int, default=4)
    ap.add_argument(
        "--length",
        type=float,
        default=80.0,
        help="route length (m); at 40 m per-run start-up is a third of a run (2 workers 1.46x, 80 m 1.91x)",
    )
    ap.add_argument("--spacing", type=float, default=0.5, help="frame spacing (m)")
    ap.add_argument("--skip-ctrlc", action="store_true")
    args = ap.parse_args()
    offsets = [float(k) for k in range(args.repeats_per_route)]
    t0 = time.perf_counter()
    manifest_path = write_batch_routes(args.out / "data", 2, offsets, args.length, args.spacing)
    print(f"data: {manifest_path} ({time.perf_counter() - t0:.0f} s to render or find)")
    manifest = load_manifest(manifest_path)
    n = len(manifest.runs())
    report: dict = {"runs": n, "routes": 2, "repeats": n - 2, "length_m": args.length, "spacing_m": args.spacing}
    wall, control = {}, {}
    for workers in (1, 2):
        control[workers] = second_core_available()
        wall[workers], result = timed_batch(manifest, args.out / f"w{workers}", workers, threads=1)
        assert not result.failed, batch_table(result)
        busy = sum(o.seconds for o in result.outcomes) / (workers * wall[workers])
        print(
            f"workers {workers}: {wall[workers]:.1f} s wall for {n} runs "
            f"({sum(o.frames for o in result.outcomes)} frames); workers busy {100 * busy:.0f} % of the wall time; "
            f"second core available before: {control[workers]:.2f}x"
        )
    report["second_core_available"] = control
    report["wall_s"] = wall
    report["speedup_2_vs_1"] = wall[1] / wall[2]
    print(f"2 workers vs 1: {report['speedup_2_vs_1']:.2f}x")
    for line in batch_table(result):
        print("    " + line)
    report["w1_equals_w2"] = not compare(args.out / "w1", args.out / "w2", manifest)

    marker = args.out / "killed.txt"
    marker.unlink(missing_ok=True)
    victim = manifest.routes[0].repeats[-1].name
    seconds, killed = timed_batch(manifest, args.out / "killed", 2, on_start=KillWorkerOnce(marker, victim))
    differ = compare(args.out / "killed", args.out / "w2", manifest)
    report["killed_worker"] = {
        "victim": f"{manifest.routes[0].name}/{victim}",
        "files_at_kill": marker.read_text(),
        "all_finished": not killed.failed,
        "differing_files": differ,
        "wall_s": seconds,
    }
    print(
        f"worker killed mid-run ({victim}; its folder held {marker.read_text().split()}): all finished "
        f"{not killed.failed}, outputs equal to the undisturbed run: {not differ} {differ or ''}"
    )

    if not args.skip_ctrlc:
        r = ctrl_c_then_rerun(manifest_path, args.out / "ctrlc", n)
        r["differing_files"] = compare(args.out / "ctrlc", args.out / "w2", manifest)
        report["ctrl_c"] = r
        print(
            f"Ctrl-C after {r['finished_before_rerun']} of {n} runs finished (exit {r['exit_code_after_sigint']}); "
            f"rerun: {r['rerun_resumed']} resumed, {r['rerun_finished']} run, {r['rerun_s']:.1f} s; outputs equal "
            f"to the undisturbed run: {not r['differing_files']}"
        )
    report["load_average"] = os.getloadavg()
    (args.out / "bench_batch.json").write_text(json.dumps(report, indent=2, default=str))
    print(
        f"load average {[round(x, 2) for x in os.getloadavg()]} (shared machine); wrote {args.out / 'bench_batch.json'}"
    )


if __name__ == "__main__":
    main()
