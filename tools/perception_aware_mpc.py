"""The thesis' perception-aware MPC experiment (§7.4, Fig. 7.6-7.8) on synthetic aerial maps.

usage: python tools/perception_aware_mpc.py --out OUT [--speed 8,10,12] [--direction forward|backward]
       [--cases toward,away]

One geometric path with two corners (east, left corner, north, right corner, east; 12 m above
ground) is taught twice in a synthetic aerial scene (buildings and trees on both sides, faint ground
texture, 175 features per image): the gimbal holds the camera (50 deg down) north (case "toward",
the path's first corner turns toward where it looks) or south (case "away"). Each teach is repeated
once off the path (drifting 3 m to one side
and 1.5 m up) through the real pipeline; the perception model is fitted (MLE) on both repeats'
landmarks.csv. Each case's map and that model make the taught-path field, and the flatness-based
MPC (thesis: 10 Hz, N = 15, 50 Hz outer loop, one QP a tick, OSQP; the library's ControlConfig
defaults) flies the taught path at each desired speed with no path constraint ("none"), a fixed
path-error bound of 1..6 m ("fixed_Xm"), and the perception-aware chance constraint ("pa"), the gimbal
holding each trunk's taught axis. ``--direction backward`` flies the route back from its taught end (the
return flight). The closed loop uses the perception model as its measurement model (as the thesis'
simulation; no rendering in the loop).

Writes OUT/results.json (one row per case, direction, speed and controller: avg_speed_mps, min_bound =
min of mu - 3 sigma along the flown path, guaranteed = min_bound >= L_min, max path errors, slacks,
tick times), OUT/results.csv, OUT/flown_paths.png, OUT/bounds.png (the default speed if swept, else the
first; with a suffix ``_backward`` flown back), OUT/model.json and prints the table. Rendered sequences
and maps are cached under OUT (a second run only simulates). See docs/perception_aware_mpc/README.md.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from perception_model import frames
from vtr.app import mission
from vtr.cli.common import frame_progress
from vtr.config import Config, ControlConfig
from vtr.control.closed_loop import ClosedLoopResult, initial_state, simulate
from vtr.control.field import TaughtPathField
from vtr.control.mpc import PerceptionAwareMPC, TaughtPathReference
from vtr.map import Map
from vtr.navigation.trunk import BACKWARD, FORWARD
from vtr.sim import synthetic as syn

CORNER_RADIUS_M = 5.0  # larger than the repeat offsets (an offset path must not collapse at a corner)
SEGMENTS = [
    (24.0, 0.0),
    (0.5 * math.pi * CORNER_RADIUS_M, 1.0 / CORNER_RADIUS_M),
    (20.0, 0.0),
    (0.5 * math.pi * CORNER_RADIUS_M, -1.0 / CORNER_RADIUS_M),
    (24.0, 0.0),
]
CASES = {"toward": math.pi / 2, "away": -math.pi / 2}  # gimbal heading (ENU): north, south
REPEAT_OFFSETS = {"toward": (3.0, 1.5), "away": (-3.0, 1.5)}  # (left, up) m, reached after RAMP_M
RAMP_M = 6.0
SPACING_M = 1.0
FIXED_BOUNDS_M = (1, 2, 3, 4, 5, 6)
SCENE_SEED = 3
#: Features per image and ground texture contrast: a sparser scene than the default synthetic one, so that the
#: trunks hold a few hundred landmarks (the thesis: 600-800) and L_min = 30 matters a few metres off the path.
FEATURES_PER_IMAGE = 175
GROUND_CONTRAST = 0.2
PITCH_DOWN_RAD = math.radians(50.0)


def scene() -> syn.Scene:
    """Buildings and trees on both sides of the path over faint ground texture; the route is kept clear."""
    route = syn.segmented_aerial_route(SEGMENTS, 2.0)[:, :2, 3]
    return syn.aerial_scene(
        SCENE_SEED,
        area_m=(-15.0, 75.0, -30.0, 55.0),
        n_boxes=50,
        n_trees=110,
        clear_path_xy=route,
        clear_radius_m=4.0,
        ground_contrast=GROUND_CONTRAST,
    )


def say(text: str) -> None:
    """A progress line on stderr (the experiment takes minutes)."""
    print(text, file=sys.stderr, flush=True)


def prepare(out: Path, cfg: Config) -> tuple[dict[str, Path], dict[str, np.ndarray], Path, list[dict]]:
    """Teach both cases, repeat each once off the path, fit the model: (maps, up vectors, model path, repeats)."""
    sc = scene()
    maps, ups, files, reps = {}, {}, [], []
    for case, heading in CASES.items():
        T_teach = syn.segmented_aerial_route(
            SEGMENTS, SPACING_M, camera_heading_rad=heading, pitch_down_rad=PITCH_DOWN_RAD
        )
        say(f"{case}: rendering the teach sequence ({len(T_teach)} frames; cached after the first run)")
        seq = mission.render_sequence(
            out / case / "teach", sc, T_teach, progress=frame_progress(f"render {case} teach")
        )
        map_path = out / case / "route.vtrmap"
        stamp = out / case / "route.done"  # the map is reused only for the same taught poses and config
        key = hashlib.sha1(np.ascontiguousarray(T_teach).tobytes() + cfg.to_yaml().encode()).hexdigest()
        if not (stamp.is_file() and map_path.is_file() and stamp.read_text().strip() == key):
            say(f"{case}: teaching the route")
            mission.teach_sequence(seq, map_path, cfg)
            stamp.write_text(key + "\n")
            shutil.rmtree(out / case / "repeat", ignore_errors=True)
        maps[case], ups[case] = map_path, mission.up_in_map(T_teach[0])
        dy, dz = REPEAT_OFFSETS[case]
        T_rep = syn.segmented_aerial_route(
            SEGMENTS[:-1] + [(SEGMENTS[-1][0] - 1.0, 0.0)],
            SPACING_M,
            camera_heading_rad=heading,
            pitch_down_rad=PITCH_DOWN_RAD,
            lateral_offset_m=dy,
            vertical_offset_m=dz,
            ramp_m=RAMP_M,
            start_offset_m=0.5 * SPACING_M,
        )
        say(f"{case}: rendering the repeat {dy:+g} m / {dz:+g} m off the path")
        rep_seq = mission.render_sequence(
            out / case / "repeat_seq", sc, T_rep, noise_seed=1, progress=frame_progress(f"render {case} repeat")
        )
        rep_dir = out / case / "repeat"
        if not (rep_dir / "landmarks.csv").is_file():
            say(f"{case}: repeating through the pipeline (localization against the taught map)")
            summary = mission.repeat_sequence(rep_seq, map_path, rep_dir, cfg, skip_first_m=RAMP_M)
            reps.append(
                {
                    "case": case,
                    "lateral_m": dy,
                    "vertical_m": dz,
                    "localizations": summary.localizations,
                    "successes": summary.successes,
                }
            )
        files.append(rep_dir / "landmarks.csv")
    model_path = out / "model.json"
    say(f"fitting the perception model on {len(files)} repeats' landmarks")
    model = mission.fit_model(files)
    model.save(model_path)
    return maps, ups, model_path, reps


def build_field(
    map_path: Path, up: np.ndarray, model_path: Path, control: ControlConfig, cfg: Config
) -> TaughtPathField:
    """The case's taught-path field."""
    from perception_model.model import PerceptionModel

    with Map.open(map_path, "r") as m:
        return TaughtPathField.from_map(
            m,
            PerceptionModel.load(model_path),
            up_map=up,
            config=cfg.localization,
            l_min=control.l_min,
            c_bar=control.c_bar,
            control=control,
        )


def fly(field: TaughtPathField, control: ControlConfig, controller: str, direction: int) -> ClosedLoopResult:
    """One closed-loop flight from the route's start in the direction of travel (its taught end flown back)."""
    ref = TaughtPathReference.from_field(field, direction)
    if controller == "none":
        mpc = PerceptionAwareMPC(ref, control, mode="none", camera="taught")
    elif controller == "pa":
        mpc = PerceptionAwareMPC(ref, control, mode="perception", field=field, camera="taught")
    else:
        bound = float(controller.removeprefix("fixed_").removesuffix("m"))
        mpc = PerceptionAwareMPC(ref, control, mode="fixed", fixed_bound_m=bound, camera="taught")
    return simulate(field, mpc, initial_state(field, 0 if direction == FORWARD else -1))


def row(case: str, controller: str, r: ClosedLoopResult, control: ControlConfig) -> dict:
    return {
        "case": case,
        "direction": "forward" if r.direction == FORWARD else "backward",
        "speed_mps": control.speed_mps,
        "controller": controller,
        "avg_speed_mps": round(r.avg_speed_mps, 3),
        "min_bound": round(r.min_bound, 2),
        "guaranteed": bool(r.min_bound >= control.l_min),
        "completed": r.completed,
        "duration_s": round(r.duration_s, 2),
        "max_lateral_error_m": round(float(np.abs(r.lateral_m).max()), 2),
        "max_vertical_error_m": round(float(np.abs(r.vertical_m).max()), 2),
        "max_slack_m": round(float(r.max_slack_m.max()) if r.max_slack_m.size else 0.0, 4),
        "max_slack_inliers": round(float(r.max_slack_inliers.max()) if r.max_slack_inliers.size else 0.0, 3),
        "tick_ms_median": round(float(np.median(r.tick_ms)), 2),
        "tick_ms_p95": round(float(np.percentile(r.tick_ms, 95)), 2),
        "tick_ms_max": round(float(r.tick_ms.max()), 2),
    }


def plot(runs: dict, fields: dict, out: Path, l_min: float, suffix: str = "") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    show = ("none", "fixed_1m", "fixed_2m", "pa")
    fig, axes = plt.subplots(1, len(runs), figsize=(7 * len(runs), 6), squeeze=False)
    for ax, (case, by_ctrl) in zip(axes[0], runs.items(), strict=True):
        # g's x is the taught camera's heading: turn it back to the scene's east/north for comparison
        R = frames.rot_z(CASES[case])[:2, :2]
        taught = fields[case].vehicle_position_g[:, :2] @ R.T
        ax.plot(taught[:, 0], taught[:, 1], "k--", lw=1.5, label="taught path")
        for name in show:
            if name in by_ctrl:
                xy = by_ctrl[name].z[:, :2] @ R.T
                ax.plot(xy[:, 0], xy[:, 1], lw=2 if name == "pa" else 1.2, label=name)
        ax.annotate(
            "camera",
            (12.0, 5.0),
            xytext=(12.0, 5.0 + 6.0 * math.sin(CASES[case])),
            arrowprops={"arrowstyle": "<-"},
            ha="center",
        )
        ax.set_aspect("equal")
        ax.set_title(f"case {case}: flown paths (camera {case})")
        ax.set_xlabel("east [m]")
        ax.set_ylabel("north [m]")
        ax.legend(fontsize=8)
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / f"flown_paths{suffix}.png", dpi=110)
    plt.close(fig)
    fig, axes = plt.subplots(1, len(runs), figsize=(7 * len(runs), 4), squeeze=False)
    for ax, (case, by_ctrl) in zip(axes[0], runs.items(), strict=True):
        for name in show:
            if name in by_ctrl:
                r = by_ctrl[name]
                ax.plot(r.t_s, r.bound, label=name)
        ax.axhline(l_min, color="r", ls=":", label="L_min")
        ax.set_title(f"case {case}: predicted inlier bound along the flight")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("mu - 3 sigma [inliers]")
        ax.legend(fontsize=8)
        ax.grid(True, alpha=0.3)
    fig.suptitle("perception-aware MPC: localization bound (must stay above L_min)")
    fig.tight_layout()
    fig.savefig(out / f"bounds{suffix}.png", dpi=110)
    plt.close(fig)


def table(rows: list[dict]) -> str:
    cols = [
        "case",
        "direction",
        "speed_mps",
        "controller",
        "avg_speed_mps",
        "min_bound",
        "guaranteed",
        "max_lateral_error_m",
        "max_vertical_error_m",
        "max_slack_m",
        "max_slack_inliers",
        "tick_ms_median",
        "tick_ms_p95",
    ]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def summary(rows: list[dict]) -> list[str]:
    """Per case, direction and speed: P-A against the fastest guaranteed fixed bound."""
    out = []
    for key in dict.fromkeys((r["case"], r["direction"], r["speed_mps"]) for r in rows):
        group = [r for r in rows if (r["case"], r["direction"], r["speed_mps"]) == key]
        fixed_ok = [r for r in group if r["controller"].startswith("fixed") and r["guaranteed"]]
        best = max(fixed_ok, key=lambda r: r["avg_speed_mps"]) if fixed_ok else None
        pa = next(r for r in group if r["controller"] == "pa")
        faster = best is None or pa["avg_speed_mps"] > best["avg_speed_mps"]
        out.append(
            f"{key[0]} {key[1]} {key[2]:g} m/s: P-A {pa['avg_speed_mps']} m/s (guaranteed {pa['guaranteed']}, "
            f"min bound {pa['min_bound']}); fastest guaranteed fixed bound "
            f"{best['controller'] + ' ' + str(best['avg_speed_mps']) + ' m/s' if best else 'none'}; "
            f"P-A guaranteed and faster: {pa['guaranteed'] and faster}"
        )
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/perception_aware_mpc"))
    ap.add_argument(
        "--speed",
        default=f"{ControlConfig().speed_mps:g}",
        help="desired speed(s) (m/s), comma-separated: one sweep of every controller each",
    )
    ap.add_argument(
        "--direction",
        choices=("forward", "backward"),
        default="forward",
        help="fly the taught route forward or back from its end (the return flight)",
    )
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument(
        "--margin", type=float, default=None, help="P-A: linearized constraint margin (inliers; default the library's)"
    )
    args = ap.parse_args(argv)
    speeds = [float(v) for v in args.speed.split(",")]
    direction = FORWARD if args.direction == "forward" else BACKWARD
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = Config().replace("features", n_features=FEATURES_PER_IMAGE)
    base = ControlConfig() if args.margin is None else ControlConfig(perception_margin=args.margin)
    t0 = time.perf_counter()
    maps, ups, model_path, reps = prepare(args.out, cfg)
    print(f"maps and model ready in {time.perf_counter() - t0:.0f} s; repeats: {reps}", file=sys.stderr)
    controllers = ["none", *(f"fixed_{b}m" for b in FIXED_BOUNDS_M), "pa"]
    plotted = base.speed_mps if base.speed_mps in speeds else speeds[0]
    rows, runs, fields = [], {}, {}
    for case in args.cases.split(","):
        say(
            f"{case}: building the taught-path field, then flying {len(controllers)} controllers "
            f"{args.direction} at {args.speed} m/s"
        )
        fields[case] = field = build_field(maps[case], ups[case], model_path, base, cfg)
        runs[case] = {}
        for speed in speeds:
            control = dataclasses.replace(base, speed_mps=speed)
            for name in controllers:
                r = fly(field, control, name, direction)
                if speed == plotted:
                    runs[case][name] = r
                rows.append(row(case, name, r, control))
                print(
                    f"{case:7s} {args.direction} {speed:g} {name:9s} speed {rows[-1]['avg_speed_mps']:5.2f} m/s  "
                    f"min(mu-3sigma) {rows[-1]['min_bound']:7.1f}  guaranteed {rows[-1]['guaranteed']}",
                    file=sys.stderr,
                )
    suffix = "" if direction == FORWARD else "_backward"
    (args.out / f"results{suffix}.json").write_text(json.dumps(rows, indent=1))
    with open(args.out / f"results{suffix}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(runs, fields, args.out, base.l_min, suffix)
    print(table(rows))
    print("\n".join(summary(rows)))
    print(
        f"wrote {args.out}/results{suffix}.json, results{suffix}.csv, flown_paths{suffix}.png, bounds{suffix}.png "
        f"({time.perf_counter() - t0:.0f} s)"
    )


if __name__ == "__main__":
    main()
