"""The drifting-appearance case (docs/map.md, "Experiences"): a synthetic aerial route taught once, then flown with
its textures blended further toward another texture each flight, every flight appended to one map (multi-experience)
and, for comparison, flown against the teach alone; forward and backward. Prints one table (markdown) and writes it
with the per-flight figures as JSON.

usage: python tools/drifting_experiences.py [--out out/drifting_experiences] [--length 24]
                                            [--changes 0.2,0.35,0.5,0.65,0.8] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vtr.app.drifting import Flight, drifting_flights
from vtr.config import Config


def _cell(f: Flight) -> str:
    i = f.integrity
    first = "-" if i.first_correct is None else str(i.first_correct)
    covers = f"{100 * i.covered:.0f} %" if i.correct else "-"
    return f"{i.correct} / {i.attempts} | {i.wrong} | {first} | {100 * i.rate_after:.0f} % | {covers}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/drifting_experiences"))
    ap.add_argument("--length", type=float, default=24.0, help="route length, m (one frame a metre)")
    ap.add_argument("--changes", default="0.2,0.35,0.5,0.65,0.8", help="appearance change of each flight, in order")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    changes = [float(c) for c in args.changes.split(",")]
    config = Config().replace("features", threads=args.threads)
    rows, records = [], []
    for backward in (False, True):
        multi, alone = drifting_flights(args.out, changes, args.length, backward=backward, config=config)
        for m, a in zip(multi, alone, strict=True):
            rows.append(
                f"| {'backward' if backward else 'forward'} | {m.change:.2f} | {_cell(a)} | {_cell(m)} | "
                f"{m.with_experience} | {len(m.experiences_used)} | {1000 * a.seconds_per_keyframe:.0f} / "
                f"{1000 * m.seconds_per_keyframe:.0f} |"
            )
            records.append(
                {
                    "backward": backward,
                    "change": m.change,
                    "alone": a.integrity.to_dict(),
                    "experiences": m.integrity.to_dict(),
                    "localized_with_experience": m.with_experience,
                    "experiences_used": list(m.experiences_used),
                    "ms_per_keyframe_alone": 1000 * a.seconds_per_keyframe,
                    "ms_per_keyframe_experiences": 1000 * m.seconds_per_keyframe,
                }
            )
    head = (
        "| direction | change | teach alone: correct | wrong | first correct | correct after | 3-sigma covers | "
        "with experiences: correct | wrong | first correct | correct after | 3-sigma covers | used an experience | "
        "experiences used | ms per keyframe (alone / experiences) |"
    )
    table = "\n".join([head, "|" + "---|" * 15, *rows])
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "drifting.md").write_text(table + "\n")
    (args.out / "drifting.json").write_text(json.dumps(records, indent=2) + "\n")


if __name__ == "__main__":
    main()
