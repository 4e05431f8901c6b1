"""``vtr batch --fit``: one perception-model fit over every finished repeat's ``landmarks.csv``, streamed (one file in
memory at a time), into ``OUT/fit/``. Each file read is the one vtr made there, never a link. See the README's "Batches"
section and ``docs/outputs.md``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perception_model.errors import PerceptionModelError
from perception_model.landmarks_file import FIT_FIELDS, read_landmarks
from perception_model.plots import plot_fit

from ...errors import DataError, VtrError
from ...io.outputs import check_no_links
from ..outputs import OutputFolder
from .layout import FIT_FOLDER
from .manifest import Manifest
from .outcome import RunOutcome

if TYPE_CHECKING:
    from perception_model.samples import Samples


def repeat_landmark_files(manifest: Manifest, out: Path, outcomes: list[RunOutcome]) -> Iterator[Path]:
    """The landmarks.csv of every finished repeat, each checked to be the file vtr made there (never a link:
    ``OutputError`` naming it, :meth:`vtr.app.outputs.OutputFolder.own_file`)."""
    ok = {(o.route, o.name) for o in outcomes if o.ok and o.kind == "repeat"}
    for spec in manifest.runs():
        if (spec.route, spec.name) in ok:
            folder = spec.folder(out)
            check_no_links(out, folder)
            p = OutputFolder(folder).own_file("landmarks.csv")
            if p is None:
                raise DataError(f"{folder / 'landmarks.csv'}: missing from a finished repeat")
            yield p


def fit_repeats(manifest: Manifest, out: Path, outcomes: list[RunOutcome]) -> dict[str, Any]:
    """One perception-model fit over every finished repeat's landmarks.csv, streamed (one file in memory at a
    time; the binned fit of the thesis protocol, sandwich intervals): OUT/fit/model.json and fit.png.
    Returns what to report, or the error."""
    from perception_model.fit import fit_binned_stream  # scipy.optimize (~1.3 s): only a fitting batch

    try:
        files = list(repeat_landmark_files(manifest, out, outcomes))
    except VtrError as err:
        return {"error": str(err)}
    if not files:
        return {"error": "no finished repeat to fit"}
    check_no_links(out, out / FIT_FOLDER)
    fit_folder = OutputFolder.prepare(out / FIT_FOLDER, names=["model.json", "fit.png"])
    folder = fit_folder.path

    def chunks() -> Iterator[Samples]:
        for f in files:
            own = OutputFolder(f.parent).own_file(f.name)  # again, just before reading it
            if own is None:
                raise PerceptionModelError(f"{f}: removed while the batch read it")
            obs = read_landmarks(own, fields=FIT_FIELDS)
            yield obs.samples()

    try:
        result = fit_binned_stream(chunks, source=f"{len(files)} repeats under {out}")
    except (PerceptionModelError, VtrError) as err:
        return {"error": str(err), "files": len(files)}
    data = {"files": [str(f) for f in files], "n_observations": result.n, "n_inliers": result.n_inliers}
    fit_folder.write("model.json", result.model.save, fit=result.to_dict(), data=data)
    fit_folder.write("fit.png", lambda p: plot_fit(result, p))
    return {
        "model": folder / "model.json",
        "plot": folder / "fit.png",
        "files": len(files),
        "observations": result.n,
        "constants": {c.name: c.estimate for c in result.intervals},
        "r2": result.r2,
        "log_loss": result.log_loss,
    }
