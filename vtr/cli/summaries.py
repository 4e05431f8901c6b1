"""The text of each command's summary: the library returns records (``vtr.app``), the command line turns them
into the lines it prints. Nothing numerical is imported at import time (the records are only type hints)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from ..conventions import NS_PER_S

if TYPE_CHECKING:
    from ..app.batch import BatchResult
    from ..app.convert import ConvertSummary
    from ..app.mission import MissionReport
    from ..app.pipeline import OdometrySummary, RepeatSummary, TeachSummary
    from ..map.check import CheckReport


def _fps(frames: int, seconds: float) -> float:
    return frames / seconds if seconds > 0 else float("nan")


def odometry_lines(s: OdometrySummary) -> list[str]:
    out = [f"frames {s.frames}  keyframes {s.keyframes}  failures {s.failures}  {s.fps:.1f} frames/s"]
    if s.note:
        out.append(s.note)
    if s.drift is not None:
        out.append(f"drift vs ground truth: {s.drift}")
    return out


def teach_lines(s: TeachSummary) -> list[str]:
    up = (
        "gravity: none stored (a level first camera is assumed; --up sets it)"
        if s.gravity_up is None
        else "gravity: up " + ",".join(f"{x:.4f}" for x in s.gravity_up) + " in the first camera, kept in the map"
    )
    return [
        f"teach: frames {s.frames}  vertices {s.vertices}  failures {s.failures}  "
        f"{_fps(s.frames, s.seconds):.1f} frames/s  -> {s.map_path}",
        up,
    ]


def refusals_line(statuses: dict[str, int]) -> str:
    """The attempts that did not localize, counted by their reason (``localization.csv``'s ``status``), most
    frequent first: ``refused: none`` when every attempt localized."""
    refused = sorted(((k, v) for k, v in statuses.items() if k != "localized" and v), key=lambda kv: (-kv[1], kv[0]))
    counts = ", ".join(f"{k} {v}" for k, v in refused) if refused else "none"
    return f"localization attempts: localized {statuses.get('localized', 0)}; refused by reason: {counts}"


def repeat_lines(s: RepeatSummary) -> list[str]:
    rate = f"({100 * s.success_rate:.1f} %)" if math.isfinite(s.success_rate) else "(no vertex)"
    inliers = f"{s.median_inliers:.0f}" if math.isfinite(s.median_inliers) else "none"
    out = [
        f"repeat: frames {s.frames}  vertices {s.vertices}  localized {s.localized} "
        f"{rate}  median inliers {inliers}  "
        f"{_fps(s.frames, s.seconds):.1f} frames/s"
    ]
    if s.statuses:
        out.append(refusals_line(s.statuses))
    if s.experiences and s.experiences["available"]:
        e = s.experiences
        out.append(
            f"experiences: {e['available']} in the map, {e['localized_with_experience']} localization(s) used "
            "one" + (" (" + ", ".join(f"run {k}: {v}" for k, v in e["used"].items()) + ")" if e["used"] else "")
        )
    out.append(
        f"path-tracking error to the taught path (localized frames): median {s.path_error_m:.3f} m"
        if math.isfinite(s.path_error_m)
        else "path-tracking error: none (never localized)"
    )
    if s.errors is not None:
        out.append(str(s.errors))
    if s.integrity is not None:
        out.append(str(s.integrity))
    elif s.ground_truth_note is not None:
        out.append(f"not judged against ground truth: {s.ground_truth_note}")
    if s.state:
        lateral = s.state.median_abs_lateral_m
        out.append(
            f"state.csv: {s.state.rows} rows at {s.state.rate_hz:g} Hz, smoothed lateral error "
            + (f"median {lateral:.3f} m" if lateral is not None else "none (never localized)")
            + f", smoother {s.state.smoother_ms_per_frame:.1f} ms/frame"
        )
        statuses = s.state.statuses
        if statuses:
            out.append("state.csv rows by status: " + ", ".join(f"{k} {v}" for k, v in sorted(statuses.items())))
        pauses = s.state.pauses_s
        if pauses:
            out.append(
                f"{len(pauses)} pause(s) without frames (longest {max(pauses):.3g} s, more than "
                "smoothing.max_extrapolation_s): a new smoother segment after each, the states across it "
                "unknown"
            )
    return out


def mission_lines(m: MissionReport) -> list[str]:
    out = [
        f"repeat {r.lateral_m:+g} m ({r.fitted}): localized {r.successes}/{r.localizations}; envelope says holds "
        f"at {r.envelope_holds} ({r.holds_and_localized} localized), fails at {r.envelope_fails} "
        f"({r.fails_and_not_localized} not localized)"
        for r in m.rows
    ]
    out.append(f"model {m.model_path.name}; envelope {m.envelope_csv}; report {m.report_html}")
    return out


def convert_line(s: ConvertSummary) -> str:
    span = (s.last_t_ns - s.first_t_ns) / NS_PER_S
    poses = ", with poses.txt" if s.wrote_poses else ""
    return (
        f"converted {s.frames} frames ({span:.3f} s of data) {s.source_format} -> {s.target}: "
        f"{s.out} ({s.bytes_written / 1e6:.1f} MB{poses}) in {s.seconds:.1f} s"
    )


def map_check_line(report: CheckReport, path: object) -> str:
    sums = "checksums verified" if report.checksums else "no checksums (map made before they existed)"
    return f"{path}: ok ({report.runs} runs, {report.vertices} vertices, {report.edges} edges checked; {sums})"


def batch_table(result: BatchResult) -> list[str]:
    """The batch's summary table, one line per run, and the counts."""
    from ..app.batch import BLOCKED, FAILED, FINISHED, RESUMED

    head = f"{'route':<14} {'run':<16} {'status':<9} {'frames':>6} {'localized':>9} {'inliers':>7} {'time s':>7}  error"
    lines = [head, "-" * len(head)]
    for o in result.outcomes:
        loc = f"{o.localized_pct:.1f} %" if o.localized_pct is not None else "-"
        inl = f"{o.median_inliers:.0f}" if o.median_inliers is not None else "-"
        sec = f"{o.seconds:.1f}" if o.seconds is not None else "-"
        frames = str(o.frames) if o.frames is not None else "-"
        note = (o.error or "").splitlines()[0] if o.error else (o.changed or "")
        lines.append(f"{o.route:<14} {o.name:<16} {o.status:<9} {frames:>6} {loc:>9} {inl:>7} {sec:>7}  {note}")
    n = {s: sum(o.status == s for o in result.outcomes) for s in (FINISHED, RESUMED, FAILED, BLOCKED)}
    lines.append(
        f"{len(result.outcomes)} runs: {n[FINISHED]} finished, {n[RESUMED]} resumed (done before), "
        f"{n[FAILED]} failed, {n[BLOCKED]} blocked; {result.seconds:.1f} s on {result.workers}"
    )
    return lines


__all__ = [
    "batch_table",
    "convert_line",
    "map_check_line",
    "mission_lines",
    "odometry_lines",
    "refusals_line",
    "repeat_lines",
    "teach_lines",
]
