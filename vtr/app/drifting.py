"""The drifting-appearance case (docs/map.md, "Experiences"): a synthetic aerial route taught once, then flown again
and again while its textures drift further from the taught ones (:mod:`vtr.sim.drifting`), each flight appended to
one map, so later flights may localize against the earlier ones (experiences); every flight is also flown against the
teach alone for comparison. Judged against the generator's exact ground truth (:func:`vtr.app.evaluation.integrity_of`).
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import Config
from ..io import open_source
from ..io.base import GroundTruth
from ..map import Map
from ..navigation.experiences import single_experience
from ..navigation.localization import Localization
from ..navigation.repeat import Repeat
from ..navigation.teach import Teach
from ..sim import synthetic as syn
from ..sim.drifting import write_drifted_sequence
from .evaluation import Integrity, integrity_of

SPEED_MPS = 4.0  # flight speed (frame times from the 1 m frame spacing)
SPACING_M = 1.0  # between frames
REPEAT_PHASE_M = 0.5  # repeat frames fall between the taught ones
LATERAL_M = 0.5  # repeats fly this far to the side


@dataclass(frozen=True)
class Flight:
    """One repeat flight: its change, direction, integrity against ground truth, the localizations that used an
    experience, the distinct experiences used, localization seconds per keyframe, its map run and its localizations
    (without landmark records)."""

    change: float
    backward: bool
    integrity: Integrity
    with_experience: int
    experiences_used: tuple[int, ...]
    seconds_per_keyframe: float
    run: int
    localizations: tuple[Localization, ...] = ()
    keyframe_seconds: tuple[float, ...] = ()  # localization seconds of each keyframe, in order


def route(length_m: float) -> np.ndarray:
    """The taught route's camera poses."""
    return syn.aerial_route(length_m, SPACING_M)


def repeat_route(length_m: float, backward: bool) -> np.ndarray:
    """A repeat's camera poses: between the taught frames, ``LATERAL_M`` to the side, optionally from the end."""
    T = syn.aerial_route(
        length_m - 2 * REPEAT_PHASE_M, SPACING_M, start_offset_m=REPEAT_PHASE_M, lateral_offset_m=LATERAL_M
    )
    return T[::-1].copy() if backward else T


def render_flight(folder: Path, scene_seed: int, T: np.ndarray, change: float) -> GroundTruth:
    """Render (once: kept when ``times_ns.txt`` exists) a sequence of ``T`` at ``change``; its ground truth."""
    t = syn.route_times(T, SPEED_MPS)
    if not (folder / "times_ns.txt").is_file():
        if folder.exists():
            shutil.rmtree(folder)
        write_drifted_sequence(folder, syn.aerial_scene(scene_seed), syn.zed_camera(), T, t, change)
    return GroundTruth(t, T)


def teach_flight(
    folder: Path, map_path: Path, length_m: float, scene_seed: int = 0, config: Config | None = None
) -> GroundTruth:
    """Teach the route (unchanged appearance) into a new map at ``map_path``."""
    truth = render_flight(folder, scene_seed, route(length_m), 0.0)
    with open_source(folder) as src, Map.create(map_path, src.camera) as m:
        t = Teach(m, src.camera, config or Config(), str(folder))
        for images in src:
            t.process(images)
        t.finish()
    return truth


def fly(
    map_path: Path, folder: Path, truth: GroundTruth, taught: GroundTruth, change: float, backward: bool, config: Config
) -> Flight:
    """Repeat the flight in ``folder`` against the map (its run is appended to it) and judge it."""
    with open_source(folder) as src, Map.open(map_path, "a") as m:
        rp = Repeat(m, config, str(folder))
        steps = [rp.process(im) for im in src]
        locs = [dataclasses.replace(s.localization, landmarks=None) for s in steps if s.localization is not None]
        per_keyframe = tuple(s.localization_seconds for s in steps if s.localization is not None)
        seconds = sum(per_keyframe)
        trunk_t = np.array([m.vertex(loc.trunk_id).t_ns for loc in locs], np.int64)
        run = rp.run
    integrity = integrity_of(locs, trunk_t, truth, taught)
    used = sorted({e for loc in locs for e in loc.experiences})
    return Flight(
        change,
        backward,
        integrity,
        sum(1 for loc in locs if loc.experiences),
        tuple(used),
        seconds / max(len(locs), 1),
        run,
        tuple(locs),
        per_keyframe,
    )


def drifting_flights(
    root: Path,
    changes: Sequence[float],
    length_m: float,
    *,
    backward: bool = False,
    config: Config | None = None,
    scene_seed: int = 0,
) -> tuple[list[Flight], list[Flight]]:
    """Teach, then fly ``changes`` in order twice: appended one after another to one map (multi-experience), and
    each against a copy of the teach-only map (``experiences.max_per_keyframe`` 0: single experience). Returns
    (with experiences, teach alone). The grown map is ``root/experiences.vtrmap``."""
    root.mkdir(parents=True, exist_ok=True)
    config = config or Config()
    single = single_experience(config)
    taught_map = root / "teach.vtrmap"
    if not taught_map.exists():
        taught = teach_flight(root / "teach", taught_map, length_m, scene_seed, config)
    else:
        taught = render_flight(root / "teach", scene_seed, route(length_m), 0.0)
    grown = root / "experiences.vtrmap"
    grown.unlink(missing_ok=True)
    shutil.copyfile(taught_map, grown)
    multi, alone = [], []
    T = repeat_route(length_m, backward)
    for change in changes:
        name = f"{'back' if backward else 'fwd'}_{change:.2f}"
        truth = render_flight(root / name, scene_seed, T, change)
        multi.append(fly(grown, root / name, truth, taught, change, backward, config))
        copy = root / f"alone_{name}.vtrmap"
        shutil.copyfile(taught_map, copy)
        alone.append(fly(copy, root / name, truth, taught, change, backward, single))
        copy.unlink()
    return multi, alone


__all__ = ["Flight", "drifting_flights", "fly", "render_flight", "repeat_route", "route", "teach_flight"]
