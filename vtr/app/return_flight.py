"""The return flight on the controller side (thesis §6.4.1): what a controller reads on a synthetic aerial route
flown out and back with the thesis' camera (pitched 50 degrees down, 12 m above the ground).

A route with an arc is taught (``vtr teach`` with ``--up`` from the scene), then repeated through ``vtr repeat``
twice, 2 m to the left of the taught heading at constant altitude: forward (taught order) and backward (from the end
back to the start and on past it, the camera facing as taught: the gimbal return). ``state.csv`` of each repeat is
judged against the generator's exact ground truth: the direction, the lateral error (left of the direction of
travel: +2 m forward, -2 m backward), the vertical error (0: level flight), the vertical speed (0) and, flown past the
taught start, whether any success or localized state lies beyond ``off_route_distance_m`` past it. See
docs/frames.md ("The return flight").
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..config import Config
from ..sim import synthetic as syn
from .mission import render_sequence, teach_sequence, up_in_map
from .pipeline import repeat_command
from .runfiles.state_csv import read_state_csv

#: the route: (length m, curvature 1/m) segments: a straight, a 45-degree left arc of 20 m radius, a straight
ROUTE_SEGMENTS = ((12.0, 0.0), (20.0 * math.pi / 4, 1.0 / 20.0), (12.0, 0.0))
CAMERA_RATE_HZ = 10.0


@dataclass(frozen=True)
class FlightCheck:
    """One repeat's ``state.csv`` against ground truth (medians over the localized rows on the route)."""

    name: str
    expected_direction: int
    expected_lateral_m: float
    rows: int
    localized_rows: int
    direction_right: float  # share of localized rows with the expected direction
    median_lateral_m: float
    median_vertical_m: float
    p95_abs_vertical_m: float
    median_vz_mps: float
    successes: int
    successes_past_start: int  # successes with the truth more than off_route_distance_m past the start
    localized_rows_past_start: int  # likewise, localized state rows
    off_route_rows: int
    accel_straight_median_mps2: float  # |a| on the straights (truth 0), away from the arc by the fit's reach
    accel_arc_median_mps2: float  # |a| on the arc
    accel_arc_expected_mps2: float  # v^2 / r of the flown arc
    accel_max_step_mps2: float  # largest change of a between consecutive localized rows


def _truth_arc(t_ns: np.ndarray, t_frames: np.ndarray, s_frames: np.ndarray) -> np.ndarray:
    """Arc length along the taught path (m; negative before its start) of the vehicle at each time."""
    return np.interp(np.asarray(t_ns, float), np.asarray(t_frames, float), s_frames)


def check_flight(
    name: str,
    out: Path,
    t_frames: np.ndarray,
    s_frames: np.ndarray,
    *,
    expected_direction: int,
    expected_lateral_m: float,
    past_m: float,
    arc_m: tuple[float, float],
    arc_accel_mps2: float,
    margin_m: float,
) -> FlightCheck:
    """Judge ``out/state.csv`` and ``out/localization.csv`` of a repeat whose frames were at ``t_frames`` and
    arc lengths ``s_frames`` along the taught path; the arc spans ``arc_m`` (taught arc length) with a centripetal
    acceleration ``arc_accel_mps2``; acceleration is judged ``margin_m`` away from where the curvature changes."""
    st = read_state_csv(out / "state.csv")
    assert st.localized is not None and st.direction is not None and st.status is not None
    s_truth = _truth_arc(st.t_ns, t_frames, s_frames)
    loc = st.localized
    on_route = loc & (s_truth >= 0.0)
    locs = np.genfromtxt(out / "localization.csv", delimiter=",", names=True, dtype=None, encoding=None)
    success = np.atleast_1d(locs["success"]).astype(bool)
    s_loc = _truth_arc(np.atleast_1d(locs["t_ns"]), t_frames, s_frames)
    vz = st.velocity[on_route, 2]
    vertical = st.vertical[on_route]
    a = np.linalg.norm(st.acceleration, axis=1)
    straight = on_route & ((s_truth < arc_m[0] - margin_m) | (s_truth > arc_m[1] + margin_m))
    arc = on_route & (s_truth > arc_m[0] + margin_m) & (s_truth < arc_m[1] - margin_m)
    both = loc[1:] & loc[:-1]
    steps = np.linalg.norm(np.diff(st.acceleration, axis=0), axis=1)[both]
    return FlightCheck(
        name=name,
        expected_direction=expected_direction,
        expected_lateral_m=expected_lateral_m,
        rows=len(st),
        localized_rows=int(loc.sum()),
        direction_right=float(np.mean(st.direction[loc] == expected_direction)) if loc.any() else 0.0,
        median_lateral_m=float(np.median(st.lateral[on_route])) if on_route.any() else math.nan,
        median_vertical_m=float(np.median(vertical)) if on_route.any() else math.nan,
        p95_abs_vertical_m=float(np.percentile(np.abs(vertical), 95)) if on_route.any() else math.nan,
        median_vz_mps=float(np.median(vz)) if on_route.any() else math.nan,
        successes=int(success.sum()),
        successes_past_start=int(np.sum(success & (s_loc < -past_m))),
        localized_rows_past_start=int(np.sum(loc & (s_truth < -past_m))),
        off_route_rows=int(np.sum(st.status == "off_route")),
        accel_straight_median_mps2=float(np.median(a[straight])) if straight.any() else math.nan,
        accel_arc_median_mps2=float(np.median(a[arc])) if arc.any() else math.nan,
        accel_arc_expected_mps2=arc_accel_mps2,
        accel_max_step_mps2=float(steps.max()) if len(steps) else math.nan,
    )


def run_return_flight(
    out: Path,
    *,
    offset_m: float = 2.0,
    speed_mps: float = 6.0,
    past_start_m: float = 10.0,
    segments: tuple[tuple[float, float], ...] = ROUTE_SEGMENTS,
    config: Config | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[FlightCheck]:
    """Teach the route, fly it forward and back ``offset_m`` to the left of the taught heading, judge both."""
    config = config or Config()
    say = progress or (lambda line: None)
    out = Path(out)
    scene = syn.aerial_scene(0)
    spacing = speed_mps / CAMERA_RATE_HZ
    total = sum(length for length, _ in segments)
    T_teach = syn.segmented_aerial_route(segments, spacing)
    say(f"rendering the teach ({len(T_teach)} frames)")
    teach_seq = render_sequence(out / "teach" / "images", scene, T_teach, speed_mps=speed_mps)
    up = up_in_map(T_teach[0])
    map_path = teach_sequence(teach_seq, out / "route.vtrmap", config, gravity_up=up)
    say(f"taught {map_path} (up {np.round(up, 4).tolist()} in the first camera)")
    flights = {
        # forward: the taught order, from just after the start to just before the end
        "forward": (1, offset_m, np.arange(spacing, total - spacing + 1e-9, spacing)),
        # backward: from the end back to the start and on past it; the camera faces as taught (gimbal return)
        "backward": (-1, -offset_m, np.arange(-past_start_m, total - spacing + 1e-9, spacing)[::-1]),
    }
    # the arc (the one curved segment) and the centripetal acceleration on the flown one (offset to the left)
    starts = np.cumsum([0.0] + [length for length, _ in segments])
    curved = [i for i, (_, kappa) in enumerate(segments) if kappa != 0.0]
    arc_m = (float(starts[curved[0]]), float(starts[curved[0] + 1])) if curved else (math.inf, math.inf)
    radius_m = 1.0 / segments[curved[0]][1] - offset_m if curved else math.inf
    margin_m = config.smoothing.acceleration_window_s * speed_mps  # the acceleration fit's reach
    checks = []
    for name, (direction, lateral, s) in flights.items():
        start = float(min(s[0], s[-1]))
        T = syn.segmented_aerial_route(segments, spacing, lateral_offset_m=offset_m, start_offset_m=start)
        T = T[: len(s)] if direction > 0 else T[: len(s)][::-1].copy()
        say(f"rendering the {name} repeat ({len(T)} frames)")
        seq = render_sequence(out / name / "images", scene, T, noise_seed=1, speed_mps=speed_mps)
        t_frames = syn.route_times(T, speed_mps)
        rep_out = out / name / "repeat"
        repeat_command(seq, map_path, rep_out, None, config, read_only_map=True)
        checks.append(
            check_flight(
                name,
                rep_out,
                t_frames,
                s,
                expected_direction=direction,
                expected_lateral_m=lateral,
                past_m=config.localization.off_route_distance_m,
                arc_m=arc_m,
                arc_accel_mps2=speed_mps**2 / radius_m,
                margin_m=margin_m,
            )
        )
        say(format_check(checks[-1]))
    (out / "return_flight.json").write_text(json.dumps([asdict(c) for c in checks], indent=2) + "\n")
    return checks


def format_check(c: FlightCheck) -> str:
    return (
        f"{c.name:8s} direction right {100 * c.direction_right:5.1f} % of {c.localized_rows} localized rows; "
        f"lateral median {c.median_lateral_m:+.3f} m (truth {c.expected_lateral_m:+.1f}); vertical median "
        f"{c.median_vertical_m:+.3f} m, p95 |.| {c.p95_abs_vertical_m:.3f} m; vz median {c.median_vz_mps:+.3f} "
        f"m/s; successes {c.successes} ({c.successes_past_start} past the start); localized rows past the "
        f"start {c.localized_rows_past_start}; off_route rows {c.off_route_rows}; |a| straight median "
        f"{c.accel_straight_median_mps2:.3f}, arc median {c.accel_arc_median_mps2:.3f} (v^2/r "
        f"{c.accel_arc_expected_mps2:.3f}) m/s^2, largest step {c.accel_max_step_mps2:.3f} m/s^2"
    )


__all__ = ["FlightCheck", "ROUTE_SEGMENTS", "check_flight", "format_check", "run_return_flight"]
