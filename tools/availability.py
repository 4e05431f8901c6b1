"""Availability as well as integrity: every repeat case this tool can build, judged against ground truth.

On the shipped clips (datasets/kitti06_clip, datasets/kitti00_ramp_clip) a teach on the even frames is
repeated on the odd ones: forward, backward (the clip reversed, the camera facing as taught), started at 1/3
and 2/3 of the route, with a 10-frame gap mid-route, under gamma 0.5 and 2.0, dusk, moving cloud shadows and
+-1 gray level of noise (tools/appearance_clip.py), at twice the speed, each of those also backward; and kidnapped
(a third of the route skipped with no time passing: integrity alone is judged); and taught on every 4th frame only
(vertices twice as far apart). On synthetic aerial routes (vtr.sim:
teach at 1 m spacing, repeat half a metre along and 1 m aside), straight and turning: forward, backward, across a
gap; and a route through another scene (every success there is wrong).

Each attempt is judged as the team's integrity check judges it: ``T_true = inv(G_leaf) @ G_trunk`` from the clips'
ground truth (nearest time), *correct* within 0.30 m and 2 deg, *wrong* a success that is not correct;
*availability* is the share of attempts from the first correct one on that are correct; *re-entry* is the
number of keyframes after the gap up to and including the first correct one. A refusal whose reported estimate
(``localization.csv`` keeps the refused estimate) is in fact correct is counted by its status: the gates'
losses.

With --odometry it measures instead what the gates must allow for: the error along its motion of odometry's newest
keyframe (the leaf), as the chain reads it, against ground truth (docs/localization.md, "The gates").

usage: python tools/availability.py [--out out/availability] [--only kitti06,ramp,aerial] [--cases SUBSTR] [--odometry]
Writes cases.csv, cases.json and availability.png in --out, one printed row per case (odometry.json with --odometry).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import importlib.util
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from vtr.app.pipeline import repeat_command, teach_command
from vtr.app.runfiles.localization_csv import read_localization_csv
from vtr.config import Config
from vtr.conventions import NS_PER_S
from vtr.io.kitti import write_reordered_clip
from vtr.map import Map

ROOT = Path(__file__).resolve().parents[1]
CLIPS = {"kitti06": ROOT / "datasets" / "kitti06_clip", "ramp": ROOT / "datasets" / "kitti00_ramp_clip"}
T_MAX_M, R_MAX_DEG = 0.30, 2.0  # a success further off is wrong (the team's integrity check)
GAP_FRAMES = 10
AVAILABILITY_BOUND = 0.97  # after the first correct
REENTRY_BOUND = 3  # keyframes after a gap, the first correct included
APPEARANCE = {
    "gamma0.5": ("gamma", 0.5),
    "gamma2.0": ("gamma", 2.0),
    "dusk": ("dusk", 1.0),
    "shadows": ("shadows", 1.0),
    "noise": ("noise", 1.0),
}  # value: gamma, or noise sigma (gray levels)
AERIAL_LENGTH_M = 30.0
AERIAL_SPEED_MPS = 4.0
AERIAL_ASIDE_M = 1.0
AERIAL_CURVATURE_PER_M = 0.03  # the turning aerial route: about 50 deg over its length
AERIAL_GAP_M = 5  # frames (1 m apart) removed from the aerial gap case


def _appearance_module():
    spec = importlib.util.spec_from_file_location("appearance_clip", Path(__file__).with_name("appearance_clip.py"))
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# -- ground truth and judging ----------------------------------------------------------------------


def ground_truth(clip: Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_ns (N,), T_world_cam (N, 4, 4)) of a KITTI-layout clip; a synthetic one's scene-world poses
    (poses_world.txt) when it has them, so a teach and a repeat rendered apart share one world."""
    name = "poses_world.txt" if (clip / "poses_world.txt").exists() else "poses.txt"
    p = np.loadtxt(clip / name, ndmin=2)
    T = np.tile(np.eye(4), (len(p), 1, 1))
    T[:, :3, :] = p.reshape(-1, 3, 4)
    if (clip / "times_ns.txt").exists():
        t = np.loadtxt(clip / "times_ns.txt", ndmin=1, dtype=np.int64)
    else:
        t = np.rint(np.loadtxt(clip / "times.txt", ndmin=1) * NS_PER_S).astype(np.int64)
    return t, T


def _nearest(gt: tuple[np.ndarray, np.ndarray], t_ns: np.ndarray) -> np.ndarray:
    t, T = gt
    return T[np.argmin(np.abs(t[None, :] - np.asarray(t_ns)[:, None]), axis=1)]


def errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) of ``inv(T_true) @ T_est`` (N, 4, 4 each)."""
    E = np.linalg.inv(T_true) @ T_est
    cos = np.clip((np.trace(E[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(np.arccos(cos))


@dataclass
class Result:
    case: str
    attempts: int
    successes: int
    correct: int
    wrong: int
    first_correct: int | None
    availability: float  # correct share of the attempts from the first correct on
    reentry: int | None = None  # gap cases: keyframes after the gap to the first correct (inclusive)
    median_error_cm: float = float("nan")
    median_inliers_refused_right: float = float("nan")
    statuses: dict[str, int] = field(default_factory=dict)
    refused_right: dict[str, int] = field(default_factory=dict)  # refusals whose estimate was correct, by status
    fps: float = float("nan")
    integrity_only: bool = False  # judged on 0 wrong and re-entry alone (a kidnap must cost a keyframe)

    @property
    def passes(self) -> bool:
        return (
            self.wrong == 0
            and (self.integrity_only or self.availability >= AVAILABILITY_BOUND)
            and (self.reentry is None or self.reentry <= REENTRY_BOUND)
        )


def judge(
    case: str, locs, trunk_t_ns: np.ndarray, gt_repeat, gt_teach, gap_t_ns: int | None = None, foreign: bool = False
) -> Result:
    """A repeat's attempts (``Localization`` records, trunks taught at ``trunk_t_ns``) against ground truth."""
    n = len(locs)
    success = np.array([loc.success for loc in locs], bool)
    T_est = np.array([loc.T_leaf_trunk for loc in locs]).reshape(-1, 4, 4)
    t_leaf = np.array([loc.t_ns for loc in locs], np.int64)
    if n:
        T_true = np.linalg.inv(_nearest(gt_repeat, t_leaf)) @ _nearest(gt_teach, trunk_t_ns)
        e_t, e_r = errors(T_est, T_true)
        right = (e_t <= T_MAX_M) & (e_r <= R_MAX_DEG) & (not foreign)
    else:
        e_t = e_r = np.zeros(0)
        right = np.zeros(0, bool)
    ok = success & right
    first = int(np.argmax(ok)) if ok.any() else None
    status = np.array([loc.status.value for loc in locs])
    statuses = {str(k): int(v) for k, v in zip(*np.unique(status, return_counts=True), strict=True)}
    refused = ~success & right & np.isin(status, ["inconsistent_with_odometry", "unconfirmed"])
    refused_right = {str(k): int(v) for k, v in zip(*np.unique(status[refused], return_counts=True), strict=True)}
    inliers = np.array([loc.inliers for loc in locs])
    reentry = None
    if gap_t_ns is not None:
        after = np.flatnonzero(t_leaf >= gap_t_ns)
        hit = np.flatnonzero(ok[after])
        reentry = int(hit[0]) + 1 if len(hit) else None
    return Result(
        case,
        n,
        int(success.sum()),
        int(ok.sum()),
        int(success.sum() - ok.sum()),
        first,
        float(ok[first:].mean()) if first is not None else 0.0,
        reentry,
        float(100 * np.median(e_t[ok])) if ok.any() else float("nan"),
        float(np.median(inliers[refused])) if refused.any() else float("nan"),
        statuses,
        refused_right,
    )


# -- cases on the shipped clips --------------------------------------------------------------------


@dataclass(frozen=True)
class ClipCase:
    name: str
    clip: str  # key of CLIPS (the teach: its even frames)
    backward: bool = False
    start_fraction: float = 0.0
    gap: bool = False
    appearance: str | None = None
    kidnap: bool = False  # a third of the route skipped with no time passing: the chain must not vouch for it
    stride: int = 2  # 4: the repeat at twice the teach's speed (every other odd frame)
    teach_stride: int = 2  # 4: taught on every 4th frame (vertices 4 m apart on the ramp)


def clip_cases(clips: list[str]) -> list[ClipCase]:
    out = []
    for c in clips:
        for backward in (False, True):
            way = " backward" if backward else ""
            out.append(ClipCase(f"{c}{way}", c, backward))
            out += [
                ClipCase(f"{c}{way} from 1/3", c, backward, 1 / 3),
                ClipCase(f"{c}{way} from 2/3", c, backward, 2 / 3),
                ClipCase(f"{c}{way} gap", c, backward, gap=True),
            ]
            out += [ClipCase(f"{c}{way} {a}", c, backward, appearance=a) for a in APPEARANCE]
            out.append(ClipCase(f"{c}{way} twice as fast", c, backward, stride=4))
        out.append(ClipCase(f"{c} kidnapped", c, kidnap=True))
        out.append(ClipCase(f"{c} taught every 4th frame", c, teach_stride=4))
    return out


def build_repeat_clip(case: ClipCase, work: Path) -> tuple[Path, str, int | None]:
    """The repeat's clip, its frame selection (the taught clip's odd frames) and, with a gap, the time (ns) of the
    first frame after it."""
    src = CLIPS[case.clip]
    n = len(list((src / "image_0").glob("*.png")))
    if case.appearance is not None:
        kind, value = APPEARANCE[case.appearance]
        changed = work / f"{case.clip}_{case.appearance}"
        if not changed.exists():
            _appearance_module().appearance_clip(src, changed, kind, g=value, sigma=value, seed=1)
        src = changed
    order = list(range(n - 1, -1, -1)) if case.backward else list(range(n))
    gap_at = None
    if case.gap:
        gap_at = n // 2 - GAP_FRAMES // 2
        order = order[:gap_at] + order[gap_at + GAP_FRAMES :]
    if case.kidnap:  # an even number of frames skipped: the repeat stays on odd frames
        gap_at = n // 3
        skip = 2 * ((n // 3) // 2)
        order = order[:gap_at] + order[gap_at + skip :]
    start = int(round(case.start_fraction * len(order)))
    first = next(k for k in range(start, len(order)) if order[k] % 2 == 1)
    picked = order[first :: case.stride]
    assert all(i % 2 == 1 for i in picked), "the repeat uses the frames the teach did not"
    slug = case.name.replace(" ", "_").replace("/", "-").replace(",", "")
    clip = write_reordered_clip(src, work / "clips" / slug, order)
    if case.kidnap:  # no time passes across the jump
        np.savetxt(clip / "times.txt", np.loadtxt(src / "times.txt", ndmin=1)[: len(order)], fmt="%.6e")
    gap_t = None
    if gap_at is not None:
        gap_t = int(round(np.loadtxt(clip / "times.txt", ndmin=1)[gap_at] * NS_PER_S))
    return clip, f"{first}::{case.stride}", gap_t


def taught_map(work: Path, clip: str, teach_stride: int, config: Config) -> Path:
    """The clip taught on every ``teach_stride``-th frame from its first (made once)."""
    path = work / f"{clip}_teach{'' if teach_stride == 2 else teach_stride}.vtrmap"
    if not path.exists():
        teach_command(CLIPS[clip], path, f"0::{teach_stride}", config)
    return path


def run_clip_case(case: ClipCase, work: Path, config: Config) -> Result:
    rep_clip, frames, gap_t = build_repeat_clip(case, work)
    slug = case.name.replace(" ", "_").replace("/", "-")
    r = _repeat_and_judge(
        case.name,
        taught_map(work, case.clip, case.teach_stride, config),
        CLIPS[case.clip],
        rep_clip,
        frames,
        work / slug,
        config,
        gap_t,
    )
    r.integrity_only = case.kidnap
    return r


def _repeat_and_judge(
    name: str,
    map_path: Path,
    teach_clip: Path,
    rep_clip: Path,
    frames: str | None,
    out: Path,
    config: Config,
    gap_t: int | None = None,
    foreign: bool = False,
) -> Result:
    local = out.parent / f"{out.name}_repeat.vtrmap"
    local.write_bytes(map_path.read_bytes())
    summary = repeat_command(rep_clip, local, out, frames, config)
    locs = read_localization_csv(out / "localization.csv")
    with Map.open(local) as m:
        trunk_t = np.array([m.vertex(loc.trunk_id).t_ns for loc in locs], np.int64)
    r = judge(name, locs, trunk_t, ground_truth(rep_clip), ground_truth(teach_clip), gap_t, foreign)
    r.fps = summary.frames / summary.seconds if summary.seconds > 0 else float("nan")
    r.integrity_only = foreign  # another place: judged on 0 wrong alone
    local.unlink()
    return r


# -- synthetic aerial cases ------------------------------------------------------------------------


def aerial_cases(work: Path, config: Config) -> list[Result]:
    """Teach a straight and a turning aerial route; repeat each forward, backward and with a gap (1 m aside,
    half a metre along), and the straight one through another scene (foreign: every success is wrong)."""
    from vtr.sim import synthetic as syn

    cam = syn.zed_camera()
    scene = syn.aerial_scene(0)
    results = []
    for route, curvature in (("aerial", 0.0), ("aerial turn", AERIAL_CURVATURE_PER_M)):
        slug = route.replace(" ", "_")
        T_teach = syn.aerial_route(AERIAL_LENGTH_M, 1.0, curvature_per_m=curvature)
        teach_clip = syn.write_sequence(
            work / f"{slug}_teach", scene, cam, T_teach, syn.route_times(T_teach, AERIAL_SPEED_MPS)
        )
        map_path = work / f"{slug}_teach.vtrmap"
        teach_command(teach_clip, map_path, None, config)
        T_rep = syn.aerial_route(
            AERIAL_LENGTH_M - 1.0, 1.0, curvature_per_m=curvature, start_offset_m=0.5, lateral_offset_m=AERIAL_ASIDE_M
        )
        variants: list[tuple[str, np.ndarray, object]] = [("", T_rep, scene), (" backward", T_rep[::-1].copy(), scene)]
        k = len(T_rep) // 2
        variants.append((" gap", np.concatenate([T_rep[:k], T_rep[k + AERIAL_GAP_M :]]), scene))
        if curvature == 0.0:
            variants.append((" other scene", syn.aerial_route(AERIAL_LENGTH_M - 4.0, 1.0), syn.aerial_scene(7)))
        for suffix, T, sc in variants:
            name = route + suffix
            cs = name.replace(" ", "_")
            t = syn.route_times(T, AERIAL_SPEED_MPS)
            if suffix == " gap":  # time runs on across the frames removed
                t[k:] += int(AERIAL_GAP_M / AERIAL_SPEED_MPS * NS_PER_S)
            rep_clip = syn.write_sequence(work / f"{cs}_clip", sc, cam, T, t, noise_seed=2)
            gap_t = int(t[k]) if suffix == " gap" else None
            results.append(
                _repeat_and_judge(
                    name,
                    map_path,
                    teach_clip,
                    rep_clip,
                    None,
                    work / cs,
                    config,
                    gap_t,
                    foreign=suffix == " other scene",
                )
            )
            print_row(results[-1])
    return results


# -- what the gates must allow for: odometry's newest keyframe --------------------------------------


def newest_keyframe_errors(clip: Path, first: int, stride: int, config: Config) -> np.ndarray:
    """Along-motion error (share of the motion, signed) of odometry's newest keyframe relative to the one before, as
    the chain reads it (both from the window right after the newest one's adjustment), against ground truth."""
    from vtr.geometry import inv_T
    from vtr.io import open_source
    from vtr.vo.odometry import OdometrySettings, StereoOdometry

    t_gt, G = ground_truth(clip)
    out, prev = [], None
    with open_source(clip) as src:
        vo = StereoOdometry(src.camera, OdometrySettings.of(config), keep_history=False)
        frames = list(range(first, len(t_gt), stride))
        for images in src.iter_frames(frames):
            r = vo.process(images)
            if r.new_keyframe is None:
                continue
            k, window = r.new_keyframe.id, vo.window_poses()
            G_k = _nearest((t_gt, G), np.array([r.t_ns]))[0]
            if prev is not None and prev[0] in window:
                m = (inv_T(G_k) @ prev[1])[:3, 3]  # the previous keyframe in the newest one's frame
                est = (inv_T(window[k]) @ window[prev[0]])[:3, 3]
                out.append(float((est - m) @ m) / float(m @ m))
            prev = (k, G_k)
    return np.array(out)


def odometry_table(work: Path, clips: list[str], config: Config) -> list[dict]:
    """:func:`newest_keyframe_errors` of every clip forward and backward at 2 and 4 frames per keyframe, and under
    each lighting change."""
    rows = []
    for c in clips:
        for case in [ClipCase(c, c), ClipCase(c, c, stride=4), ClipCase(c, c, True), ClipCase(c, c, True, stride=4)] + [
            ClipCase(c, c, appearance=a) for a in APPEARANCE
        ]:
            label = (
                f"{c}{' backward' if case.backward else ''}{' ' + case.appearance if case.appearance else ''}, "
                f"every {case.stride} frames"
            )
            clip, frames, _ = build_repeat_clip(dataclasses.replace(case, name=f"odometry {label}"), work)
            first, stride = (int(x) for x in frames.split("::"))
            e = np.abs(newest_keyframe_errors(clip, first, stride, config))
            rows.append(
                {
                    "case": label,
                    "first_steps_pct": [round(100 * float(x), 1) for x in e[:3]],
                    "max_pct": round(100 * float(e.max()), 1),
                    "median_pct": round(100 * float(np.median(e)), 1),
                }
            )
            print(
                f"{label:<36} |along-motion error| of the newest keyframe: median {rows[-1]['median_pct']:5.1f} %, "
                f"max {rows[-1]['max_pct']:5.1f} %, first three steps {rows[-1]['first_steps_pct']} %",
                flush=True,
            )
    return rows


# -- output ----------------------------------------------------------------------------------------

HEADER = (
    f"{'case':<32} {'att':>4} {'succ':>4} {'wrong':>5} {'first':>5} {'avail':>6} {'reentry':>7} "
    f"{'med cm':>6} {'pass':>4}  refused although right (median inliers)"
)


def print_row(r: Result) -> None:
    refused = ", ".join(f"{k} {v}" for k, v in r.refused_right.items()) or "-"
    if r.refused_right:
        refused += f" ({r.median_inliers_refused_right:.0f})"
    print(
        f"{r.case:<32} {r.attempts:>4} {r.successes:>4} {r.wrong:>5} {str(r.first_correct):>5} "
        f"{100 * r.availability:>5.0f}% {('-' if r.reentry is None else str(r.reentry)):>7} "
        f"{r.median_error_cm:>6.1f} {'yes' if r.passes else 'NO':>4}  {refused}",
        flush=True,
    )


def plot(results: list[Result], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 0.32 * len(results)), 4.5))
    x = np.arange(len(results))
    avail = [100 * r.availability for r in results]
    colours = ["C2" if r.passes else "C3" for r in results]
    ax.bar(x, avail, color=colours)
    for i, r in enumerate(results):
        if r.wrong:
            ax.text(i, 2, f"{r.wrong} wrong", rotation=90, ha="center", va="bottom", fontsize=7)
    ax.axhline(100 * AVAILABILITY_BOUND, color="k", lw=0.8, ls="--", label=f"{100 * AVAILABILITY_BOUND:.0f} %")
    ax.set_xticks(x, [r.case for r in results], rotation=90, fontsize=7)
    ax.set_ylabel("correct after the first correct [%]")
    ax.set_ylim(0, 105)
    ax.legend(loc="lower right")
    ax.set_title("availability per case (green: 0 wrong, >= 97 %, re-entry <= 3)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/availability"))
    ap.add_argument("--only", default="kitti06,ramp,aerial", help="comma-separated: kitti06, ramp, aerial")
    ap.add_argument("--cases", default="", help="run only the clip cases whose name contains this")
    ap.add_argument("--threads", type=int, default=1, help="features.threads of every run")
    ap.add_argument(
        "--odometry",
        action="store_true",
        help="only measure odometry's newest-keyframe error along its motion (what the gates allow for)",
    )
    args = ap.parse_args()
    work = args.out
    if work.exists() and any(work.iterdir()):
        raise SystemExit(f"out: {work} is not empty (choose another --out)")
    work.mkdir(parents=True, exist_ok=True)
    config = Config().replace("features", threads=args.threads)
    only = [s for s in args.only.split(",") if s]
    clips = [c for c in only if c in CLIPS]
    if args.odometry:
        rows = odometry_table(work, clips, config)
        (work / "odometry.json").write_text(json.dumps(rows, indent=1))
        print(f"wrote {work / 'odometry.json'}")
        return
    print(HEADER)
    results: list[Result] = []
    for case in clip_cases(clips):
        if args.cases and args.cases not in case.name:
            continue
        results.append(run_clip_case(case, work, config))
        print_row(results[-1])
    if "aerial" in only:
        results += aerial_cases(work, config)
    if not results:
        raise SystemExit("no case selected")
    rows = [
        {
            **{k: v for k, v in asdict(r).items() if k not in ("statuses", "refused_right")},
            "passes": r.passes,
            "statuses": ";".join(f"{k}={v}" for k, v in r.statuses.items()),
            "refused_right": ";".join(f"{k}={v}" for k, v in r.refused_right.items()),
        }
        for r in results
    ]
    with open(work / "cases.csv", "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (work / "cases.json").write_text(json.dumps([{**asdict(r), "passes": r.passes} for r in results], indent=1))
    plot(results, work / "availability.png")
    failing = [r.case for r in results if not r.passes]
    print(
        f"{len(results) - len(failing)} of {len(results)} cases pass (0 wrong, availability >= "
        f"{100 * AVAILABILITY_BOUND:.0f} %, re-entry <= {REENTRY_BOUND}); wrong in total "
        f"{sum(r.wrong for r in results)}" + (f"; failing: {', '.join(failing)}" if failing else "")
    )
    print(f"wrote {work / 'cases.csv'}, {work / 'cases.json'}, {work / 'availability.png'}")


if __name__ == "__main__":
    main()
