"""Synthetic aerial routes for batch runs: each route a scene of its own, taught once and repeated with
lateral offsets, written as KITTI-layout folders with a ``vtr batch`` manifest beside them; and a
simulated crash (``KillWorkerOnce``) for testing that a batch survives a worker dying mid-run.

Rendered folders are kept: a folder whose ``times_ns.txt`` exists (written last by the KITTI writer) and
whose ``render_key.txt`` matches what is asked (scene, poses, noise) is not rendered again, so a
benchmark's data is made once; other parameters (a longer route) render it anew.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import yaml

from . import synthetic as syn

SPEED_MPS = 4.0  # flight speed: frame times follow from the 1 m frame spacing
RAMP_M = 4.0  # a repeat drifts to its lateral offset over this distance
REPEAT_PHASE_M = 0.5  # repeat frames fall between the taught ones


RENDER_KEY = "render_key.txt"


def _sequence(folder: Path, scene_index: int, T, noise_seed: int) -> Path:
    key = hashlib.sha256(f"{scene_index} {noise_seed} {SPEED_MPS} ".encode() + T.tobytes()).hexdigest()
    if (
        (folder / "times_ns.txt").is_file()
        and (folder / RENDER_KEY).is_file()
        and (folder / RENDER_KEY).read_text().strip() == key
    ):
        return folder
    if folder.exists():
        shutil.rmtree(folder)  # rendered with other parameters (or unfinished)
    syn.write_sequence(
        folder, syn.aerial_scene(scene_index), syn.zed_camera(), T, syn.route_times(T, SPEED_MPS), noise_seed=noise_seed
    )
    (folder / RENDER_KEY).write_text(key + "\n")
    return folder


def write_batch_routes(
    root: str | Path, n_routes: int, offsets_m: Sequence[float], length_m: float, spacing_m: float = 1.0
) -> Path:
    """``n_routes`` routes under ``root`` (``route_<k>/teach``, ``route_<k>/rep_<offset>``: one repeat per
    lateral offset) and ``root/manifest.yaml`` listing them. Returns the manifest's path."""
    root = Path(root)
    routes = []
    for k in range(n_routes):
        name = f"route_{k}"
        T_teach = syn.aerial_route(length_m, spacing_m)
        teach = _sequence(root / name / "teach", k, T_teach, noise_seed=0)
        repeats = []
        for j, dy in enumerate(offsets_m):
            T_rep = syn.drifting_aerial_route(length_m - 1.0, spacing_m, dy, 0.0, RAMP_M, REPEAT_PHASE_M)
            rep = _sequence(root / name / f"rep_{dy:g}m", k, T_rep, noise_seed=j + 1)
            repeats.append(str(rep.relative_to(root)))
        routes.append({"name": name, "teach": str(teach.relative_to(root)), "repeats": repeats})
    manifest = root / "manifest.yaml"
    manifest.write_text(yaml.safe_dump({"routes": routes}, sort_keys=False))
    return manifest


KILL_POLL_S = 0.005


class KillWorkerOnce:
    """A batch ``on_start`` hook that kills its own worker process (SIGKILL, as the OOM killer does) once
    the ``victim`` run has started writing (file ``after`` exists in its folder: a repeat's
    localization.csv, a teach's route.vtrmap-wal), on the first attempt only: ``marker`` records the
    attempt, with the run folder's file names at the kill."""

    def __init__(self, marker: str | Path, victim: str, after: str = "localization.csv"):
        self.marker, self.victim, self.after = Path(marker), victim, after

    def __call__(self, spec, folder: Path) -> None:
        if spec.name != self.victim or self.marker.exists():
            return
        self.marker.write_text("")

        def kill() -> None:
            while not (folder / self.after).exists():
                time.sleep(KILL_POLL_S)
            self.marker.write_text("\n".join(sorted(p.name for p in folder.iterdir())))
            os.kill(os.getpid(), signal.SIGKILL)

        threading.Thread(target=kill, daemon=True).start()
