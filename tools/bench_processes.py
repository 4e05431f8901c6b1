"""Whole ``vtr repeat`` and ``vtr odometry`` processes on the same frames, as a user runs them: frames/s of each
(frames over the wall time of the whole process, start-up to exit), their ratio, and where each process's wall time
goes (its phases).

usage: python tools/bench_processes.py [--rounds 4] [--clip datasets/kitti06_clip] [--teach-frames 0::2]
                                       [--frames 1::2] [--threads 1] [--code DIR [--code DIR]]
                                       [--out out/bench_processes]

The route is taught once (``vtr teach``, not timed); after an untimed warm-up round every round then runs ``vtr
odometry`` and ``vtr repeat`` on the same frames back to back, in alternating order, each repeat on a fresh copy of the
taught map (a repeat appends its run, which would change the next one). The machine is shared: the ratio is taken
within each round and the median over the rounds is printed, with the load average before each round. With two
``--code`` trees (e.g. the previous commit exported beside this one) every round runs both, in alternating order,
and the medians are printed before -> after.

Each command runs in a fresh ``python`` process through this file's ``--child`` mode: the same click command as
``python -m vtr`` (``vtr.cli.main``), with the run's named steps wrapped by a timer (a handful of calls per frame
at most, microseconds). Phases are exclusive (a step timed inside another is taken out of it):

- ``interpreter``: process start to this file's first line (Python's own start-up);
- ``imports``: ``vtr.cli`` and ``vtr.app.pipeline`` (numpy, OpenCV, numba, scipy, GTSAM...);
- ``cli``: click parsing, the config, the output-folder check, the summary lines printed (the command around its run);
- ``open``: the source, the output folder, and for the repeat the map (opened, the taught path, the place index:
  each vertex's checksums are verified when it is read) and the ``Repeat``;
- ``loop``: every frame (odometry; for the repeat also localization and the map writes, ``Repeat.steps``), less
  the following, timed on their own: ``state_add`` (the controller-state estimator fed each step),
  ``loc_rows`` (``localization.csv`` and ``landmarks.csv`` rows), ``finish_run`` (the run finished in the map),
  ``state_finish`` (the estimator's last solve);
- ``evaluate`` (path errors, ground truth), ``state_output`` (the smoothed state at the output rate), one phase per
  file written (``trajectory_tum.txt``, ``frames.csv``, ``state.csv``, ``trajectory.png``, ``report.png``),
  ``summarize``, ``run.json``, ``close`` (the map closed: its write-ahead log folded back);
- ``teardown``: the command's return to the process's exit (exit handlers, the interpreter's shutdown);
- ``other``: what no phase holds (the rest of the run's code between the steps).

The frames/s each command prints (run.json's ``fps``) are over its loop: they are recorded beside the whole-process
figures. Writes ``bench_processes.json`` (every process: wall, frames, frames/s, the command's own frames/s, phases)
and ``bench_processes.csv`` (one row per process, one column per phase) to ``--out``. Figures and what they showed:
docs/localization.md, "Whole process".
"""

from __future__ import annotations

import time

_T_CHILD_START = time.monotonic()  # the child's first line: the interpreter's start-up is over

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CLIP = ROOT / "datasets" / "kitti06_clip"
TARGET_RATIO = 0.9  # issue 33: a repeat at least 0.9x the odometry's frames/s

#: the phases in the order a run goes through them (``other`` last: the remainder)
PHASES = (
    "interpreter",
    "imports",
    "cli",
    "open",
    "loop",
    "state_add",
    "loc_rows",
    "finish_run",
    "state_finish",
    "evaluate",
    "state_output",
    "trajectory_tum.txt",
    "frames.csv",
    "state.csv",
    "trajectory.png",
    "report.png",
    "summarize",
    "run.json",
    "close",
    "teardown",
    "other",
)


# -- the child: one vtr command with its steps timed ---------------------------------------------------------------


class _Clock:
    """Exclusive seconds per phase: a timed call inside another is taken out of the outer one's phase."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._inner: list[float] = []  # seconds spent in timed calls nested in each open call

    def wrap(self, owner: Any, attr: str, phase: str | Callable[..., str]) -> None:
        fn = getattr(owner, attr)
        clock = self

        def timed(*args: Any, **kwargs: Any) -> Any:
            name = phase(*args, **kwargs) if callable(phase) else phase
            clock._inner.append(0.0)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - t0
                inner = clock._inner.pop()
                clock.seconds[name] = clock.seconds.get(name, 0.0) + elapsed - inner
                if clock._inner:
                    clock._inner[-1] += elapsed

        timed.__wrapped__ = fn  # type: ignore[attr-defined]
        setattr(owner, attr, timed)


def _child(record: Path, argv: list[str]) -> int:
    """Run ``vtr ARGV`` (the click command of ``python -m vtr``) with its steps timed; the phases go to ``record``."""
    clock = _Clock()
    t0 = time.perf_counter()
    import vtr.app.pipeline as pipeline
    import vtr.cli

    clock.seconds["imports"] = time.perf_counter() - t0

    from perception_model.landmarks_file import LandmarksWriter
    from vtr.app import repeat_pipeline
    from vtr.app.outputs import OutputFolder
    from vtr.app.runfiles.localization_csv import LocalizationWriter
    from vtr.app.runfiles.run_json import RunLog
    from vtr.map.store import Map
    from vtr.map.writing import MapWriting
    from vtr.navigation.repeat_state import RepeatStateEstimator

    clock.wrap(vtr.cli.main, "invoke", "cli")
    clock.wrap(pipeline, "open_inputs", "open")
    for cls in (pipeline.OdometryRun, repeat_pipeline.RepeatRun):
        for step in ("loop", "evaluate", "summarize"):
            clock.wrap(cls, step, step)
        clock.wrap(cls, "write", "other")
    clock.wrap(repeat_pipeline.RepeatRun, "open", "open")
    clock.wrap(OutputFolder, "write", lambda _self, name, *a, **k: str(name))
    clock.wrap(RunLog, "write", "run.json")
    clock.wrap(RepeatStateEstimator, "add", "state_add")
    clock.wrap(RepeatStateEstimator, "finish", "state_finish")
    clock.wrap(RepeatStateEstimator, "output", "state_output")
    clock.wrap(LocalizationWriter, "write", "loc_rows")
    clock.wrap(LandmarksWriter, "write", "loc_rows")
    clock.wrap(MapWriting, "finish_run", "finish_run")
    clock.wrap(Map, "close", "close")
    code = 0
    try:
        vtr.cli.main.main(argv, prog_name="vtr", standalone_mode=True)
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    finally:
        record.write_text(json.dumps({"start": _T_CHILD_START, "end": time.monotonic(), "phases": clock.seconds}))
    return code


# -- the parent: rounds of whole processes -------------------------------------------------------------------------


def _process(args: list[str], record: Path, code: Path) -> dict:
    """One timed child process running ``vtr ARGS`` with the package at ``code`` first on the path: wall seconds
    and phases."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(record), "--", *args]
    env = {**os.environ, "PYTHONPATH": str(code)}
    t_spawn = time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    t_exit = time.monotonic()
    if done.returncode != 0:
        sys.exit(f"vtr {' '.join(args)} failed ({done.returncode}):\n{done.stderr}")
    child = json.loads(record.read_text())
    phases = {k: float(v) for k, v in child["phases"].items()}
    phases.pop("other", None)  # the run's own code between its steps: in the remainder below
    phases["interpreter"] = child["start"] - t_spawn
    phases["teardown"] = t_exit - child["end"]
    wall = t_exit - t_spawn
    phases["other"] = wall - sum(phases.values())
    return {"wall_s": wall, "phases": phases}


def _run_json(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())["summary"]


def measure(
    clip: Path, teach_frames: str, frames: str, rounds: int, threads: int, codes: list[Path], work: Path
) -> list[dict]:
    """Teach once, then a warm-up and ``rounds`` rounds of odometry and repeat processes of each code tree; one
    record per timed process."""
    threads_args = ["--threads", str(threads)]
    taught = work / "route.vtrmap"
    teach = [sys.executable, "-m", "vtr", "teach", str(clip), "--map", str(taught), "--frames", teach_frames]
    env = {**os.environ, "PYTHONPATH": str(codes[0])}
    subprocess.run([*teach, *threads_args], check=True, capture_output=True, env=env)
    records = []
    for r in range(-1, rounds):  # round -1 warms each tree's compiled kernels and the file cache: not recorded
        load = os.getloadavg()[0]
        for code in codes if r % 2 == 0 else codes[::-1]:
            for command in ("odometry", "repeat") if r % 2 == 0 else ("repeat", "odometry"):
                out = work / f"{command}-{r}"
                args = [command, str(clip), "--frames", frames, "--out", str(out), *threads_args]
                route = work / f"route-{r}.vtrmap"
                if command == "repeat":
                    shutil.copyfile(taught, route)  # a fresh copy: a repeat appends its run
                    args += ["--map", str(route)]
                p = _process(args, work / f"{command}-{r}.json", code)
                summary = _run_json(out)
                shutil.rmtree(out)
                route.unlink(missing_ok=True)
                if r < 0:
                    continue
                records.append(
                    {
                        "round": r,
                        "code": str(code),
                        "command": command,
                        "load_1min": load,
                        "frames": summary["frames"],
                        "wall_s": p["wall_s"],
                        "fps": summary["frames"] / p["wall_s"],
                        "printed_fps": summary["fps"],
                        "phases": p["phases"],
                    }
                )
    return records


def summarize(records: list[dict], code: str) -> dict:
    """Medians over the rounds for one code tree: frames/s of each command, the ratio within each round, phases."""
    mine = [r for r in records if r["code"] == code]
    rounds = sorted({r["round"] for r in mine})
    by = {(r["round"], r["command"]): r for r in mine}
    ratios = [by[k, "repeat"]["fps"] / by[k, "odometry"]["fps"] for k in rounds]
    printed = [by[k, "repeat"]["printed_fps"] / by[k, "odometry"]["printed_fps"] for k in rounds]
    out: dict[str, Any] = {"code": code, "rounds": len(rounds), "ratio_median": statistics.median(ratios)}
    out["ratios"] = ratios
    out["printed_ratio_median"] = statistics.median(printed)
    out["load_1min"] = [by[k, "odometry"]["load_1min"] for k in rounds]
    for command in ("odometry", "repeat"):
        runs = [r for r in mine if r["command"] == command]
        out[command] = {
            "fps_median": statistics.median(r["fps"] for r in runs),
            "wall_s_median": statistics.median(r["wall_s"] for r in runs),
            "phases_median_s": {
                p: statistics.median(r["phases"].get(p, 0.0) for r in runs)
                for p in PHASES
                if any(p in r["phases"] for r in runs)
            },
        }
    return out


def write_outputs(out: Path, records: list[dict], summaries: list[dict], settings: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_processes.json").write_text(
        json.dumps({"settings": settings, "summaries": summaries, "processes": records}, indent=2) + "\n"
    )
    fields = ["round", "code", "command", "load_1min", "frames", "wall_s", "fps", "printed_fps"]
    with open(out / "bench_processes.csv", "w", newline="") as f:
        w = csv.DictWriter(f, [*fields, *PHASES])
        w.writeheader()
        for r in records:
            w.writerow({**{k: r[k] for k in fields}, **{p: r["phases"].get(p, 0.0) for p in PHASES}})


def report(records: list[dict], summary: dict) -> list[str]:
    """The lines printed for one code tree: each round, the medians, the phases side by side."""
    lines = [f"code {summary['code']}"]
    by = {(r["round"], r["command"]): r for r in records if r["code"] == summary["code"]}
    for k in sorted({r for r, _ in by}):
        o, p = by[k, "odometry"], by[k, "repeat"]
        lines.append(
            f"  round {k}: load {o['load_1min']:.2f}  odometry {o['fps']:.2f} frames/s ({o['wall_s']:.2f} s)  "
            f"repeat {p['fps']:.2f} frames/s ({p['wall_s']:.2f} s)  ratio {p['fps'] / o['fps']:.2f}  "
            f"(printed by the commands: {o['printed_fps']:.1f} / {p['printed_fps']:.1f})"
        )
    o, p = summary["odometry"], summary["repeat"]
    lines.append(
        f"  median over {summary['rounds']} rounds: odometry {o['fps_median']:.2f} frames/s, repeat "
        f"{p['fps_median']:.2f} frames/s, ratio (within rounds) {summary['ratio_median']:.2f} "
        f"(goal >= {TARGET_RATIO}); ratio of the frames/s the commands print {summary['printed_ratio_median']:.2f}"
    )
    lines.append(f"  {'phase (median s)':<20}{'odometry':>10}{'repeat':>10}{'extra':>10}")
    rows = [(phase, o["phases_median_s"].get(phase, 0.0), p["phases_median_s"].get(phase, 0.0)) for phase in PHASES]
    rows.append(("wall", o["wall_s_median"], p["wall_s_median"]))
    for phase, a, b in rows:
        if a or b:
            lines.append(f"  {phase:<20}{a:>10.3f}{b:>10.3f}{b - a:>+10.3f}")
    return lines


def compare(before: dict, after: dict) -> list[str]:
    """Two code trees' medians side by side: frames/s, ratio and each phase, before -> after."""
    lines = [f"{before['code']} -> {after['code']}"]
    for command in ("odometry", "repeat"):
        a, b = before[command], after[command]
        lines.append(
            f"  {command}: {a['fps_median']:.2f} -> {b['fps_median']:.2f} frames/s "
            f"({a['wall_s_median']:.2f} -> {b['wall_s_median']:.2f} s)"
        )
    lines.append(f"  ratio {before['ratio_median']:.2f} -> {after['ratio_median']:.2f}")
    for phase in PHASES:
        pa = [before[c]["phases_median_s"].get(phase, 0.0) for c in ("odometry", "repeat")]
        pb = [after[c]["phases_median_s"].get(phase, 0.0) for c in ("odometry", "repeat")]
        if any(pa + pb):
            lines.append(f"  {phase:<20} odometry {pa[0]:.3f} -> {pb[0]:.3f}   repeat {pa[1]:.3f} -> {pb[1]:.3f}")
    return lines


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        rest = sys.argv[3:]
        sys.exit(_child(Path(sys.argv[2]), rest[1:] if rest[:1] == ["--"] else rest))
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--clip", type=Path, default=CLIP)
    ap.add_argument("--teach-frames", default="0::2")
    ap.add_argument("--frames", default="1::2", help="frames of the odometry and the repeat")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--code",
        type=Path,
        action="append",
        help="a checkout of vtr to time (its root, put first on PYTHONPATH); give two for an A/B in alternating "
        "processes (e.g. an export of the previous commit: git archive HEAD~1 | tar -x -C /tmp/before). "
        "Default: this checkout",
    )
    ap.add_argument("--out", type=Path, default=Path("out/bench_processes"))
    a = ap.parse_args()
    if a.rounds < 1:
        ap.error("--rounds must be >= 1")
    codes = [c.resolve() for c in (a.code or [ROOT])]
    with tempfile.TemporaryDirectory(prefix="bench_processes-") as tmp:
        records = measure(a.clip, a.teach_frames, a.frames, a.rounds, a.threads, codes, Path(tmp))
    summaries = [summarize(records, str(c)) for c in codes]
    settings = {
        "clip": str(a.clip),
        "teach_frames": a.teach_frames,
        "frames": a.frames,
        "threads": a.threads,
        "rounds": a.rounds,
        "codes": [str(c) for c in codes],
        "python": sys.executable,
    }
    write_outputs(a.out, records, summaries, settings)
    for summary in summaries:
        for line in report(records, summary):
            print(line)
    if len(summaries) == 2:
        for line in compare(*summaries):
            print(line)
    print(f"wrote {a.out}/bench_processes.json, bench_processes.csv")


if __name__ == "__main__":
    main()
