"""Cost of multi-experience localization (docs/map.md, "Experiences"): localization time per keyframe of one flight
against a route with 1, 5 and 20 stored experiences, against the teach alone (single experience), in one run; and
the map's size after each flight appended (bytes per experience).

The route is the synthetic aerial one of tools/drifting_experiences.py; the experiences are flights at appearance
changes cycling through ``--variants`` rendered flights; the measured flight is one more at ``--probe`` change, flown
on a copy of the map (as ``--read-only-map`` does) with ``experiences.max_per_keyframe`` as configured, with it 0
(the teach alone) and with it raised to every experience (what the bound saves).

usage: python tools/bench_experiences.py [--out out/bench_experiences] [--length 16] [--threads 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np

from vtr.app.drifting import fly, render, repeat_route, route, teach
from vtr.config import Config

COUNTS = (1, 5, 20)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_experiences"))
    ap.add_argument("--length", type=float, default=16.0, help="route length, m")
    ap.add_argument("--variants", default="0.1,0.2,0.3,0.4,0.5", help="appearance changes of the stored flights")
    ap.add_argument("--probe", type=float, default=0.3, help="appearance change of the measured flight")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    config = Config()
    config.features.threads = args.threads
    taught_map = out / "teach.vtrmap"
    if taught_map.exists():
        taught = render(out / "teach", 0, route(args.length), 0.0)
    else:
        taught = teach(out / "teach", taught_map, args.length, 0, config)
    T = repeat_route(args.length, False)
    variants = [float(v) for v in args.variants.split(",")]
    grown = out / "grown.vtrmap"
    shutil.copyfile(taught_map, grown)
    sizes = [grown.stat().st_size]
    snapshots: dict[int, Path] = {}
    for k in range(1, max(COUNTS) + 1):
        change = variants[(k - 1) % len(variants)]
        folder = out / f"flight_{change:.2f}"
        fly(grown, folder, render(folder, 0, T, change), taught, change, False, config)
        sizes.append(grown.stat().st_size)
        if k in COUNTS:
            snapshots[k] = out / f"experiences_{k}.vtrmap"
            shutil.copyfile(grown, snapshots[k])
    probe = out / f"probe_{args.probe:.2f}"
    truth = render(probe, 0, T, args.probe)
    bound = config.experiences.max_per_keyframe

    def probe_flight(snapshot: Path, max_per_keyframe: int) -> dict:
        cfg = dataclasses.replace(config, experiences=dataclasses.replace(config.experiences,
                                                                          max_per_keyframe=max_per_keyframe))
        copy = out / "probe.vtrmap"
        shutil.copyfile(snapshot, copy)
        f = fly(copy, probe, truth, taught, args.probe, False, cfg)
        copy.unlink()
        per_kf = [len(loc.experiences) for loc in f.localizations if loc.success]
        ms = 1000 * np.array(f.keyframe_seconds)
        return {"ms_per_keyframe": float(ms.mean()), "median_ms": float(np.median(ms)), "first_ms": float(ms[0]),
                "correct": f.integrity.correct,
                "attempts": f.integrity.attempts, "wrong": f.integrity.wrong,
                "mean_experiences_per_success": float(np.mean(per_kf)) if per_kf else 0.0}

    rows = [{"stored": max(COUNTS), "max_per_keyframe": 0, **probe_flight(snapshots[max(COUNTS)], 0)}]
    for k in COUNTS:
        rows.append({"stored": k, "max_per_keyframe": bound, **probe_flight(snapshots[k], bound)})
    rows.append({"stored": max(COUNTS), "max_per_keyframe": max(COUNTS), **probe_flight(snapshots[max(COUNTS)],
                                                                                       max(COUNTS))})
    print("| experiences stored | matched per keyframe at most | localization ms per keyframe: median | mean | "
          "first keyframe (search) | correct | wrong | experiences per success (mean) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['stored']} | {r['max_per_keyframe']} | {r['median_ms']:.1f} | {r['ms_per_keyframe']:.1f} | "
              f"{r['first_ms']:.0f} | {r['correct']} / {r['attempts']} | {r['wrong']} | "
              f"{r['mean_experiences_per_success']:.1f} |")
    growth = np.diff(sizes)
    print(f"map bytes: teach {sizes[0]}, after each flight +{', +'.join(str(int(g)) for g in growth)}; "
          f"median {int(np.median(growth))} bytes per experience ({int(np.median(growth)) // len(T)} per vertex)")
    (out / "bench_experiences.json").write_text(json.dumps({"rows": rows, "map_bytes_per_flight": sizes}, indent=2)
                                                + "\n")


if __name__ == "__main__":
    main()
