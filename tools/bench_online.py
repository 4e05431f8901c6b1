"""The online repeat as a controller runs it: a camera thread feeding frames at 10 Hz and a control thread ticking at
100 Hz (state with covariance, a 3-sample output window, a 15-step perception constraint), on a synthetic aerial
flight flown backward (camera 50 degrees down) and on the kitti06 repeat (teach even frames, repeat odd).

usage: python tools/bench_online.py [--out OUT] [--camera-hz 10] [--control-hz 100] [--horizon 15]

Per case: the exceptions the control thread saw (NotLocalizedError before the first localization is expected; any
other counts), tick latency p50 / p99 / max against one odometry frame measured in the same run (median of the same
frames through stereo + odometry alone), and the calibration of the state's position covariance against ground truth
(NEES of the position relative to the trunk, 3 dof: median and the share inside the 99 % bound). The threaded
run's ticks fall as far after the newest frame as the feeder lags (a loaded machine extrapolates further), so the
calibration is also replayed without threads: every frame fed, then the state at each control tick until the next
camera frame (0, 10, ..., 90 ms after it), on these cases and on cases the estimator was not tuned on (the aerial
flight forward, kitti06 reversed, kitti00_ramp_clip forward and reversed; reversed: the repeat's frames in reverse
order with the times kept increasing). Writes OUT/online.json and OUT/online.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from perception_model.model import PerceptionModel
from vtr.app.mission import render_sequence, up_in_map
from vtr.app.pipeline import teach_command
from vtr.app.return_flight import CAMERA_RATE_HZ, ROUTE_SEGMENTS
from vtr.config import Config
from vtr.control.online import OnlineRepeat
from vtr.errors import NotLocalizedError
from vtr.geometry import exp_se3, inv_T, log_se3
from vtr.io import open_source
from vtr.map import Map
from vtr.navigation.state_view import RepeatStateView
from vtr.sim import synthetic as syn
from vtr.vo.odometry import OdometrySettings, StereoOdometry

ROOT = Path(__file__).resolve().parents[1]
NEES_BOUND = float(chi2.ppf(0.99, 3))


class Truth:
    """Left-camera poses of teach and repeat in one common frame, by time."""

    def __init__(self, t_teach: np.ndarray, T_teach: np.ndarray, t_rep: np.ndarray, T_rep: np.ndarray):
        self.t_teach, self.T_teach, self.t_rep, self.T_rep = t_teach, T_teach, t_rep, T_rep

    def repeat_at(self, t_ns: int) -> np.ndarray:
        """Camera pose at ``t_ns``: the constant-twist (SE(3) geodesic) motion between the repeat frames around it.
        (Positions on the straight chord cut the corner of a turn: 23 mm at the middle of the 0.2 s steps of
        kitti00_ramp_clip's odd frames against its even frames' ground truth, the geodesic 3.3 mm.)"""
        j = int(np.clip(np.searchsorted(self.t_rep, t_ns) - 1, 0, len(self.t_rep) - 2))
        a = (t_ns - self.t_rep[j]) / (self.t_rep[j + 1] - self.t_rep[j])
        return self.T_rep[j] @ exp_se3(a * log_se3(inv_T(self.T_rep[j]) @ self.T_rep[j + 1]))

    def teach_at(self, t_ns: int) -> np.ndarray:
        return self.T_teach[int(np.argmin(np.abs(self.t_teach - t_ns)))]


def odometry_frame_ms(source_dir: Path, indices: list[int]) -> float:
    """Median ms of one frame through stereo + odometry alone (the yardstick of a tick)."""
    with open_source(source_dir) as src:
        images = [src[i] for i in indices]
        odo = StereoOdometry(src.camera, OdometrySettings.of(Config()), keep_history=False)
    times = []
    for im in images:
        t0 = time.perf_counter()
        odo.process_frame(odo.stereo.process(im))
        times.append(time.perf_counter() - t0)
    return 1000 * float(np.median(times[2:]))


def run_case(name: str, map_path: Path, source_dir: Path, indices: list[int], truth: Truth, args) -> dict:
    with open_source(source_dir) as src:
        images = [src[i] for i in indices]
    with Map.open(map_path) as m:
        teach_t = {int(v): int(t) for v, t in zip(m.taught_path().ids, m.taught_path().t_ns, strict=True)}
    odo_ms = odometry_frame_ms(source_dir, indices)
    errors: dict[str, int] = {}
    not_localized = 0
    ticks: list[float] = []
    nees: list[float] = []
    done = threading.Event()
    clock: dict[str, float] = {}  # the frame time the feeder last published, and its wall time
    with OnlineRepeat(map_path, model=PerceptionModel.thesis()) as live:

        def control() -> None:
            nonlocal not_localized
            period = 1.0 / args.control_hz
            next_tick = time.perf_counter()
            while not done.is_set():
                now = time.perf_counter()
                t_frame = clock.get("t")
                t0 = time.perf_counter()
                try:
                    if t_frame is None:
                        raise NotLocalizedError("no frame yet")
                    t = int(t_frame + (now - clock["wall"]) * 1e9)
                    view = live.view  # one view for the state and its check (the feeder may publish between)
                    s = view.controller_state_at(t, with_covariance=True)
                    live.window(t, 3, 0.02)
                    p_g, psi_g = s.in_map_gravity_frame()
                    step = np.arange(args.horizon)[:, None] * np.r_[np.cos(psi_g), np.sin(psi_g), 0.0] * 0.5
                    live.constraint(p_g[None] + step, np.full(args.horizon, psi_g))
                    ticks.append(time.perf_counter() - t0)
                    if s.localized and s.position_covariance is not None:
                        nees.append(_nees(view, s, t, truth, teach_t))
                except NotLocalizedError:
                    not_localized += 1
                except Exception as err:  # noqa: BLE001 - counted and reported
                    errors[type(err).__name__] = errors.get(type(err).__name__, 0) + 1
                next_tick += period
                time.sleep(max(0.0, next_tick - time.perf_counter()))

        thread = threading.Thread(target=control, name="control")
        thread.start()
        feed_ms = []
        try:
            start = time.perf_counter()
            for k, im in enumerate(images):
                t0 = time.perf_counter()
                live.feed(im)
                feed_ms.append(1000 * (time.perf_counter() - t0))
                clock.update(t=float(im.t_ns), wall=time.perf_counter())
                time.sleep(max(0.0, start + (k + 1) / args.camera_hz - time.perf_counter()))
        finally:
            done.set()
            thread.join()
    tick_ms = 1000 * np.array(ticks)
    nees_a = np.array(nees)
    row = {
        "case": name,
        "frames": len(images),
        "ticks": len(ticks),
        "not_localized_ticks": not_localized,
        "other_exceptions": errors,
        "odometry_frame_ms": odo_ms,
        "feed_ms_median": float(np.median(feed_ms)),
        "tick_ms_p50": float(np.percentile(tick_ms, 50)),
        "tick_ms_p99": float(np.percentile(tick_ms, 99)),
        "tick_ms_max": float(tick_ms.max()),
        "tick_p99_per_odometry_frame": float(np.percentile(tick_ms, 99)) / odo_ms,
        "tick_max_per_odometry_frame": float(tick_ms.max()) / odo_ms,
        "nees_samples": len(nees_a),
        "nees_median": float(np.median(nees_a)) if len(nees_a) else None,
        "nees_inside_99": float(np.mean(nees_a <= NEES_BOUND)) if len(nees_a) else None,
    }
    return row


def _nees(view: RepeatStateView, s, t: int, truth: Truth, teach_t: dict[int, int]) -> float:
    """NEES (3 dof) of the state's position in o against the true pose relative to the true trunk (the trunk of the
    view the state was read from)."""
    k = int(view.trunk_index_at(np.array([t]))[0])
    trunk_id = int(view.route.path.ids[k])
    T_cam_trunk_true = truth.teach_at(teach_t[trunk_id])
    T_rel = inv_T(T_cam_trunk_true) @ truth.repeat_at(t)  # true repeat camera in the trunk camera
    T_vs = inv_T(view.route.T_sensor_vehicle)
    T_o_t = view.route.trunk(k)[0]
    p_true = (T_o_t @ T_vs @ T_rel @ view.route.T_sensor_vehicle)[:3, 3]
    e = s.position - p_true
    return float(e @ np.linalg.solve(s.position_covariance, e))


def replay_nees(map_path: Path, images: list, truth: Truth, args) -> dict:
    """Position NEES of the state at every control tick between camera frames, fed without threads."""
    with Map.open(map_path) as m:
        teach_t = {int(v): int(t) for v, t in zip(m.taught_path().ids, m.taught_path().t_ns, strict=True)}
    ticks = max(1, int(round(args.control_hz / args.camera_hz)))
    period_ns = int(round(1e9 / args.control_hz))
    nees: list[float] = []
    with OnlineRepeat(map_path) as live:
        for im in images:
            live.feed(im)
            if not live.localized:
                continue
            view = live.view
            for k in range(ticks):
                t = int(im.t_ns) + k * period_ns
                s = view.controller_state_at(t, with_covariance=True)
                nees.append(_nees(view, s, t, truth, teach_t))
    a = np.array(nees)
    return {
        "replay_nees_samples": len(a),
        "replay_nees_median": float(np.median(a)) if len(a) else None,
        "replay_nees_inside_99": float(np.mean(a <= NEES_BOUND)) if len(a) else None,
    }


def reversed_repeat(images: list, truth: Truth) -> tuple[list, Truth]:
    """The repeat's frames in reverse order with the times kept increasing (the route travelled backward, facing as
    taught), and the truth re-timed with them."""
    times = [int(im.t_ns) for im in images]
    rev = [dataclasses.replace(im, t_ns=t) for im, t in zip(images[::-1], times, strict=True)]
    T_rep = np.array([truth.repeat_at(int(im.t_ns)) for im in images[::-1]])
    return rev, Truth(truth.t_teach, truth.T_teach, np.array(times, np.int64), T_rep)


def aerial_case(out: Path, args) -> tuple[Path, Path, list[int], Truth]:
    """The backward synthetic aerial flight of tools/return_flight.py (camera as taught, 2 m to the side)."""
    scene = syn.aerial_scene(0)
    spacing = args.speed / CAMERA_RATE_HZ
    total = sum(length for length, _ in ROUTE_SEGMENTS)
    T_teach = syn.segmented_aerial_route(ROUTE_SEGMENTS, spacing)
    teach_seq = render_sequence(out / "aerial" / "teach", scene, T_teach, speed_mps=args.speed)
    map_path = out / "aerial" / "route.vtrmap"
    if not map_path.exists():
        teach_command(teach_seq, map_path, None, Config(), gravity_up=up_in_map(T_teach[0]))
    s = np.arange(spacing, total - spacing + 1e-9, spacing)[::-1]
    T = syn.segmented_aerial_route(ROUTE_SEGMENTS, spacing, lateral_offset_m=2.0, start_offset_m=float(s[-1]))
    T = T[: len(s)][::-1].copy()
    seq = render_sequence(out / "aerial" / "backward", scene, T, noise_seed=1, speed_mps=args.speed)
    truth = Truth(syn.route_times(T_teach, args.speed), T_teach, syn.route_times(T, args.speed), T)
    return map_path, seq, list(range(len(T))), truth


def aerial_forward_case(out: Path, args) -> tuple[Path, Path, list[int], Truth]:
    """The same route flown forward, 2 m to the side (another noise seed)."""
    map_path, _, _, _ = aerial_case(out, args)
    scene = syn.aerial_scene(0)
    spacing = args.speed / CAMERA_RATE_HZ
    total = sum(length for length, _ in ROUTE_SEGMENTS)
    T_teach = syn.segmented_aerial_route(ROUTE_SEGMENTS, spacing)
    s = np.arange(spacing, total - spacing + 1e-9, spacing)
    T = syn.segmented_aerial_route(ROUTE_SEGMENTS, spacing, lateral_offset_m=2.0, start_offset_m=float(s[0]))[: len(s)]
    seq = render_sequence(out / "aerial" / "forward", scene, T, noise_seed=2, speed_mps=args.speed)
    truth = Truth(syn.route_times(T_teach, args.speed), T_teach, syn.route_times(T, args.speed), T)
    return map_path, seq, list(range(len(T))), truth


def kitti_case(out: Path, clip_name: str = "kitti06_clip") -> tuple[Path, Path, list[int], Truth]:
    clip = ROOT / "datasets" / clip_name
    map_path = out / clip_name / "route.vtrmap"
    if not map_path.exists():
        map_path.parent.mkdir(parents=True, exist_ok=True)
        teach_command(clip, map_path, "0::2", Config())
    with open_source(clip) as src:
        gt = src.ground_truth()
        n = len(src)
    assert gt is not None
    truth = Truth(gt.t_ns, gt.T_world_cam, gt.t_ns, gt.T_world_cam)
    return map_path, clip, list(range(1, n, 2)), truth


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    rows = [r for r in rows if "tick_p99_per_odometry_frame" in r]  # the threaded runs
    names = [r["case"] for r in rows]
    for key, label in (("tick_p99_per_odometry_frame", "tick p99"), ("tick_max_per_odometry_frame", "tick max")):
        ax.bar([n + " " + label for n in names], [r[key] for r in rows])
    ax.axhline(0.5, color="k", lw=0.8, ls="--")
    ax.set_ylabel("tick / odometry frame")
    ax.tick_params(axis="x", labelrotation=20)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_online"))
    ap.add_argument("--camera-hz", type=float, default=10.0)
    ap.add_argument("--control-hz", type=float, default=100.0)
    ap.add_argument("--horizon", type=int, default=15)
    ap.add_argument("--speed", type=float, default=6.0, help="aerial flight speed (m/s)")
    ap.add_argument("--cases", default="aerial,kitti06", help="comma-separated: aerial, kitti06")
    ap.add_argument(
        "--switch-interval-ms",
        type=float,
        default=None,
        help="Python's thread switch interval for the run (sys.setswitchinterval; default: Python's, 5 ms)",
    )
    ap.add_argument(
        "--replay-cases",
        default="aerial forward,kitti06 reversed,ramp,ramp reversed",
        help="comma-separated cases replayed without threads only (calibration): aerial forward, "
        "kitti06 reversed, ramp, ramp reversed; empty for none",
    )
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.switch_interval_ms is not None:
        sys.setswitchinterval(args.switch_interval_ms / 1000)
    print(f"thread switch interval {1000 * sys.getswitchinterval():g} ms")
    rows = []
    cases = [
        (name, case)
        for name, case in (
            ("aerial backward", lambda: aerial_case(args.out, args)),
            ("kitti06", lambda: kitti_case(args.out)),
        )
        if name.split()[0] in args.cases.split(",")
    ]
    for name, case in cases:
        map_path, source, indices, truth = case()
        print(f"{name}: {len(indices)} frames at {args.camera_hz:g} Hz, control at {args.control_hz:g} Hz ...")
        row = run_case(name, map_path, source, indices, truth, args)
        with open_source(source) as src:
            row.update(replay_nees(map_path, [src[i] for i in indices], truth, args))
        rows.append(row)
        print("  " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    replays = {
        "aerial forward": lambda: aerial_forward_case(args.out, args),
        "kitti06 reversed": lambda: kitti_case(args.out),
        "ramp": lambda: kitti_case(args.out, "kitti00_ramp_clip"),
        "ramp reversed": lambda: kitti_case(args.out, "kitti00_ramp_clip"),
    }
    for name in [c.strip() for c in args.replay_cases.split(",") if c.strip()]:
        if name not in replays:
            raise SystemExit(f"--replay-cases: unknown case {name!r} (known: {', '.join(replays)})")
        map_path, source, indices, truth = replays[name]()
        with open_source(source) as src:
            images = [src[i] for i in indices]
        if name.endswith("reversed"):
            images, truth = reversed_repeat(images, truth)
        row = {"case": name, "frames": len(images), **replay_nees(map_path, images, truth, args)}
        rows.append(row)
        print("  " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    (args.out / "online.json").write_text(json.dumps(rows, indent=2) + "\n")
    plot(rows, args.out / "online.png")
    print(f"wrote {args.out}/online.json and online.png")


if __name__ == "__main__":
    main()
