"""What each run of a batch did (:class:`RunOutcome`, read back from its ``run.json``), the batch's result and its
table ``summary.csv``.

A run's ``run.json`` is read only as vtr writes it (:func:`checked_run`: one line naming the file and the field
otherwise). See the README's "Batches" section and ``docs/outputs.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...errors import DataError
from ..runfiles.run_json import STATUS_FAILED, STATUS_FINISHED, read_run
from ..runfiles.summary_csv import write_summary_csv
from .layout import DONE
from .manifest import RunSpec


@dataclass(frozen=True)
class RunOutcome:
    """What one run of a batch did (one row of the summary table)."""

    route: str
    name: str
    kind: str
    status: str  # FINISHED, RESUMED, FAILED, BLOCKED
    frames: int | None = None
    vertices: int | None = None
    localized: int | None = None  # repeats: localized vertices
    median_inliers: float | None = None
    seconds: float | None = None  # wall time of the run (as recorded in its run.json)
    error: str | None = None
    changed: str | None = None  # why a run finished before was run again (what of its key changed)

    @property
    def localized_pct(self) -> float | None:
        if self.localized is None or not self.vertices:
            return None
        return 100.0 * self.localized / self.vertices

    @property
    def ok(self) -> bool:
        return self.status in DONE


SUMMARY_NUMBERS = {"frames": int, "vertices": int, "localized": int, "median_inliers": float, "seconds": float}


def checked_run(folder: Path) -> dict[str, Any] | None:
    """``folder/run.json`` checked for what the batch reads from it: None when there is none; ``DataError``
    (one line naming the file and the field) when it is not what vtr writes (edited by hand?)."""
    p = Path(folder) / "run.json"
    if not p.exists() and not p.is_symlink():
        return None
    hint = f"; remove {p} to run it again"
    doc = read_run(folder)
    if doc is None:
        raise DataError(f"{p}: not a JSON object as vtr writes it{hint}")
    status = doc.get("status", STATUS_FINISHED)
    if status not in (STATUS_FINISHED, STATUS_FAILED):
        raise DataError(f"{p}: status {status!r} is not {STATUS_FINISHED!r} or {STATUS_FAILED!r}{hint}")
    summary = doc.get("summary", {})
    if not isinstance(summary, dict):
        raise DataError(f"{p}: 'summary' is {type(summary).__name__}, expected a mapping{hint}")
    for key, kind in SUMMARY_NUMBERS.items():
        v = summary.get(key)
        ok = v is None or (
            not isinstance(v, bool) and isinstance(v, int | float) and (kind is float or isinstance(v, int))
        )
        if not ok or (isinstance(v, float) and v != v and key != "median_inliers"):
            raise DataError(
                f"{p}: 'summary.{key}' is {v!r}, expected {'an integer' if kind is int else 'a number'}{hint}"
            )
    if doc.get("error") is not None and not isinstance(doc["error"], str):
        raise DataError(f"{p}: 'error' is {type(doc['error']).__name__}, expected text{hint}")
    return doc


def outcome_from_folder(spec: RunSpec, folder: Path, status: str, changed: str | None = None) -> RunOutcome:
    """The outcome recorded in ``folder/run.json``."""
    doc = checked_run(folder) or {}
    s = doc.get("summary") or {}
    return RunOutcome(
        spec.route,
        spec.name,
        spec.kind,
        status,
        frames=s.get("frames"),
        vertices=s.get("vertices"),
        localized=s.get("localized"),
        median_inliers=s.get("median_inliers"),
        seconds=s.get("seconds"),
        error=doc.get("error"),
        changed=changed,
    )


@dataclass
class BatchResult:
    out: Path
    outcomes: list[RunOutcome]
    seconds: float
    workers: str  # "local N" or the scheduler address
    fit: dict[str, Any] | None = None  # --fit: report (paths, numbers) or error
    summary_csv: Path | None = None

    @property
    def failed(self) -> list[RunOutcome]:
        return [o for o in self.outcomes if not o.ok]


__all__ = ["BatchResult", "RunOutcome", "checked_run", "outcome_from_folder", "write_summary_csv"]
