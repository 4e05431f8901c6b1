"""Cost of multi-experience localization (docs/map.md, "Experiences"): localization time per keyframe of one flight
against a route with 1, 5 and 20 stored experiences, against the teach alone (single experience), in one run; and
the map's size after each flight appended (bytes per experience).

The route is the synthetic aerial one of tools/drifting_experiences.py; the experiences are flights at appearance
changes cycling through ``--variants`` rendered flights; the measured flight is one more at ``--probe`` change, flown
on a copy of the map (as ``--read-only-map`` does) with ``experiences.max_per_keyframe`` as configured, with it 0
(the teach alone) and with it raised to every experience (what the bound saves). The experiences' place-recognition
words are stored in the maps first (a repeat stores them the first time it needs them).

usage: python tools/bench_experiences.py [--out out/bench_experiences] [--length 16] [--threads 1] [--rounds 3]
                                        [--reuse]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np

from vtr.app.drifting import fly, render_flight, repeat_route, route, teach_flight
from vtr.config import Config
from vtr.map import Map
from vtr.navigation.experiences import ExperienceSubmaps
from vtr.navigation.place import route_place_index

COUNTS = (1, 5, 20)


def warm(snapshot: Path, config: Config) -> None:
    """Store the experiences' place-recognition words in the map (what the first repeat against them does)."""
    with Map.open(snapshot, "a") as m:
        place = route_place_index(m, config.place, config.run.seed)
        sub = ExperienceSubmaps(
            m, m.taught_path(), config.experiences, config.localization.neighbour_vertices, m.camera, place
        )
        for run in sub.trusted:
            sub.run_words(run)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_experiences"))
    ap.add_argument("--length", type=float, default=16.0, help="route length, m")
    ap.add_argument("--variants", default="0.1,0.2,0.3,0.4,0.5", help="appearance changes of the stored flights")
    ap.add_argument("--probe", type=float, default=0.3, help="appearance change of the measured flight")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=3, help="measured flights per case, interleaved")
    ap.add_argument("--reuse", action="store_true", help="reuse the stored maps of an earlier run in --out")
    args = ap.parse_args()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    config = Config().replace("features", threads=args.threads)
    taught_map = out / "teach.vtrmap"
    if taught_map.exists():
        taught = render_flight(out / "teach", 0, route(args.length), 0.0)
    else:
        taught = teach_flight(out / "teach", taught_map, args.length, 0, config)
    T = repeat_route(args.length, False)
    variants = [float(v) for v in args.variants.split(",")]
    snapshots = {k: out / f"experiences_{k}.vtrmap" for k in COUNTS}
    sizes_file = out / "map_bytes_per_flight.json"
    if args.reuse and sizes_file.is_file() and all(p.is_file() for p in snapshots.values()):
        sizes = json.loads(sizes_file.read_text())
    else:
        grown = out / "grown.vtrmap"
        shutil.copyfile(taught_map, grown)
        sizes = [grown.stat().st_size]
        for k in range(1, max(COUNTS) + 1):
            change = variants[(k - 1) % len(variants)]
            folder = out / f"flight_{change:.2f}"
            fly(grown, folder, render_flight(folder, 0, T, change), taught, change, False, config)
            sizes.append(grown.stat().st_size)
            if k in snapshots:
                shutil.copyfile(grown, snapshots[k])
        sizes_file.write_text(json.dumps(sizes) + "\n")
    for snapshot in snapshots.values():  # the experiences' place words stored, as after one repeat
        warm(snapshot, config)
    probe = out / f"probe_{args.probe:.2f}"
    truth = render_flight(probe, 0, T, args.probe)
    bound = config.experiences.max_per_keyframe

    def probe_flight(snapshot: Path, max_per_keyframe: int):
        cfg = dataclasses.replace(
            config, experiences=dataclasses.replace(config.experiences, max_per_keyframe=max_per_keyframe)
        )
        copy = out / "probe.vtrmap"
        shutil.copyfile(snapshot, copy)
        f = fly(copy, probe, truth, taught, args.probe, False, cfg)
        copy.unlink()
        return f

    cases = [(max(COUNTS), 0)] + [(k, bound) for k in COUNTS] + [(max(COUNTS), max(COUNTS))]
    flights: dict[tuple[int, int], list] = {c: [] for c in cases}
    for _ in range(args.rounds):  # interleaved: the machine's load falls on every case alike
        for stored, most in cases:
            flights[(stored, most)].append(probe_flight(snapshots[stored], most))
    rows = []
    for (stored, most), fs in flights.items():
        ms = 1000 * np.array([f.keyframe_seconds for f in fs])  # (rounds, keyframes)
        per_kf = [len(loc.experiences) for loc in fs[0].localizations if loc.success]
        i = fs[0].integrity
        rows.append(
            {
                "stored": stored,
                "max_per_keyframe": most,
                "ms_per_keyframe": float(ms.mean()),
                "median_ms": float(np.median(ms[:, 1:])),
                "first_ms": float(np.median(ms[:, 0])),
                "correct": i.correct,
                "attempts": i.attempts,
                "wrong": max(f.integrity.wrong for f in fs),
                "mean_experiences_per_success": float(np.mean(per_kf)) if per_kf else 0.0,
            }
        )
    print(
        f"| experiences stored | matched per keyframe at most | localization ms per keyframe after the first: median "
        f"({args.rounds} rounds) | mean (all) | first keyframe (search) | correct | wrong | experiences per success "
        "(mean) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['stored']} | {r['max_per_keyframe']} | {r['median_ms']:.1f} | {r['ms_per_keyframe']:.1f} | "
            f"{r['first_ms']:.0f} | {r['correct']} / {r['attempts']} | {r['wrong']} | "
            f"{r['mean_experiences_per_success']:.1f} |"
        )
    growth = np.diff(sizes)
    print(
        f"map bytes: teach {sizes[0]}, after each flight +{', +'.join(str(int(g)) for g in growth)}; "
        f"median {int(np.median(growth))} bytes per experience ({int(np.median(growth)) // len(T)} per vertex)"
    )
    (out / "bench_experiences.json").write_text(
        json.dumps({"rows": rows, "map_bytes_per_flight": sizes}, indent=2) + "\n"
    )


if __name__ == "__main__":
    main()
