"""A synthetic aerial mission through the real pipeline: teach, repeats, the fitted model, the field.

Rendered stereo sequences (``vtr.sim.synthetic``) are taught into a map (``Teach``) and repeated
(``Repeat``) exactly as logged imagery would be; each repeat writes its ``landmarks.csv``; the
perception model is fitted on those files (``perception_model.fit``) and the taught-path field
(``vtr.control.field``) is built from the map and that model. Rendered sequences and maps are kept
under the output folder and reused when present (rendering is the slow part).

Frames: the synthetic world is ENU; the map frame is the teach run's first camera frame, so gravity
"up" in the map frame is ``R_world_cam0^T e_z`` (:func:`up_in_map`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception_model.landmarks_file import FIT_FIELDS, read_landmarks_files
from perception_model.model import PerceptionModel
from perception_model.settings import THESIS_C_BAR, THESIS_L_MIN, Method

from ..config import Config
from ..io import open_source
from ..map import Map
from ..map.database import SIDE_FILES
from ..navigation.experiences import single_experience
from ..navigation.localization import Localization
from ..navigation.repeat import Repeat
from ..sim import synthetic as syn
from .outputs import OutputFolder
from .perception import localization_envelope, write_envelope
from .pipeline import teach_command, write_landmarks_csv
from .repeat_run import run_repeat

#: Flight speed used for the synthetic timestamps (m/s).
SYNTHETIC_SPEED_MPS = 4.0


@dataclass(frozen=True)
class MissionRepeat:
    """One repeat of the mission: where its landmarks.csv is and how localization went."""

    name: str
    landmarks_csv: Path
    localizations_list: tuple[Localization, ...]  # the attempts after the drift ramp, in order

    @property
    def localizations(self) -> int:
        return len(self.localizations_list)

    @property
    def successes(self) -> int:
        return sum(loc.success for loc in self.localizations_list)

    @property
    def success_rate(self) -> float:
        return self.successes / max(self.localizations, 1)


def up_in_map(T_world_cam0: np.ndarray) -> np.ndarray:
    """Gravity up (3,) in the map frame of a teach whose first camera pose in ENU is ``T_world_cam0``."""
    return np.asarray(T_world_cam0, float)[:3, :3].T @ np.array([0.0, 0.0, 1.0])


def render_sequence(
    out_dir: Path,
    scene: syn.Scene,
    T_world_cam: np.ndarray,
    *,
    noise_seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
    speed_mps: float = SYNTHETIC_SPEED_MPS,
) -> Path:
    """Render (or reuse, when scene, poses, noise seed and speed are the same) a ZED-like stereo sequence in
    ``out_dir``, its frames timed as flown at ``speed_mps``."""
    key = hashlib.sha1(
        repr(scene).encode()
        + np.ascontiguousarray(T_world_cam).tobytes()
        + str(noise_seed).encode()
        + (b"" if speed_mps == SYNTHETIC_SPEED_MPS else f"{speed_mps!r}".encode())
    ).hexdigest()
    stamp = out_dir / "render.key"
    if stamp.is_file() and stamp.read_text().strip() == key and (out_dir / "image_0").is_dir():
        return out_dir
    if out_dir.exists():
        shutil.rmtree(out_dir)
    syn.write_sequence(
        out_dir,
        scene,
        syn.zed_camera(),
        T_world_cam,
        syn.route_times(T_world_cam, speed_mps),
        noise_seed=noise_seed,
        progress=progress,
    )
    stamp.write_text(key + "\n")
    return out_dir


def teach_sequence(seq_dir: Path, map_path: Path, config: Config, gravity_up: np.ndarray | None = None) -> Path:
    """Teach ``seq_dir`` into a new map at ``map_path`` (replacing an older one: the map and SQLite's files beside
    it, nothing else of a similar name), keeping ``gravity_up`` in it."""

    for f in (map_path, *(Path(f"{map_path}{s}") for s in SIDE_FILES)):
        if f.is_file() and not f.is_symlink():
            f.unlink()
    teach_command(seq_dir, map_path, None, config, gravity_up=gravity_up)
    return map_path


def repeat_sequence(
    seq_dir: Path, map_path: Path, out_dir: Path, config: Config, *, skip_first_m: float = 0.0, spacing_m: float = 1.0
) -> MissionRepeat:
    """Repeat ``seq_dir`` against the map; ``out_dir/landmarks.csv`` holds the localizations after ``skip_first_m``."""
    with open_source(seq_dir) as src, Map.open(map_path, "a") as m:
        # against the teach alone: the model is fitted on taught landmarks, and the other offsets' repeats appended
        # to this map must not help (docs/map.md, "Experiences")
        rp = Repeat(m, single_experience(config), str(seq_dir))
        locs = list(run_repeat(rp, rp.odometry.stereo.frames(iter(src)), keep_landmarks=True).localizations)
    skip = int(np.ceil(skip_first_m / spacing_m))
    kept = locs[skip:]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_landmarks_csv(out_dir / "landmarks.csv", kept)
    return MissionRepeat(name=out_dir.name, landmarks_csv=out_dir / "landmarks.csv", localizations_list=tuple(kept))


def fit_model(landmark_files: list[Path], method: Method = "mle") -> PerceptionModel:
    """The perception model fitted on repeat logs (``perception-model fit`` with a held-out split)."""
    from perception_model.fit import FitSettings, fit_observations  # the fit imports scipy.optimize (~1.3 s)

    return fit_observations(read_landmarks_files(landmark_files, FIT_FIELDS), FitSettings(method=method)).model


__all__ = ["MissionRepeat", "fit_model", "render_sequence", "repeat_sequence", "teach_sequence", "up_in_map"]


# --------------------------------------------------------------------------- the whole mission
#: Defaults of the aerial mission (``vtr demo`` step 4): route length, repeat offsets, drift ramp.
MISSION_LENGTH_M = 30.0
MISSION_LATERAL_M = (0.0, 1.0, 2.0, 4.0, 8.0)
#: repeats flown after the fit, not fitted on, on both sides of the envelope's boundary: the comparison then
#: shows the envelope predicting failure as well as success
MISSION_HELD_OUT_M = (16.0, 24.0)
#: the envelope's scan limit in the mission: beyond the widest held-out repeat
MISSION_ENVELOPE_MAX_M = 40.0
MISSION_RAMP_M = 6.0
MISSION_SCENE_SEED = 0


@dataclass(frozen=True)
class EnvelopeCheck:
    """One repeat of the mission against the envelope (the columns of the report's table, in order): its offset
    (m, left), whether it was fitted on, localizations and successes after the drift ramp, those the envelope says
    hold (offset inside their trunk's envelope) and how many of them localized, those it says fail and how many of
    them did not localize, and the median inliers."""

    lateral_m: float
    fitted: str  # "yes" or "held out"
    localizations: int
    successes: int
    envelope_holds: int
    holds_and_localized: int
    envelope_fails: int
    fails_and_not_localized: int
    median_inliers: float


@dataclass(frozen=True)
class MissionReport:
    """What the aerial mission produced (paths) and how the envelope compared with the repeats."""

    out_dir: Path
    map_path: Path
    model_path: Path
    envelope_csv: Path
    report_html: Path
    rows: tuple[EnvelopeCheck, ...]  # one per repeat, in the order flown


def run_aerial_mission(
    out_dir: Path,
    config: Config,
    *,
    length_m: float = MISSION_LENGTH_M,
    lateral_m: tuple[float, ...] = MISSION_LATERAL_M,
    held_out_m: tuple[float, ...] = MISSION_HELD_OUT_M,
    ramp_m: float = MISSION_RAMP_M,
    l_min: float = THESIS_L_MIN,
    c_bar: float = THESIS_C_BAR,
    progress: Callable[[str], Callable[[int, int], None] | None] | None = None,
) -> MissionReport:
    """Teach a straight aerial route, repeat it at lateral offsets (left), fit the model on the repeats'
    landmarks, compute the localization envelope and compare it with where the repeats localized."""

    own = OutputFolder.prepare(out_dir)  # the mission rewrites only the entries it made (see OutputFolder)
    own.claim_entries(
        [
            "teach",
            "route.vtrmap",
            "model.json",
            "envelope",
            "report.html",
            *(f"repeat_{dy:g}m" for dy in (*lateral_m, *held_out_m)),
        ]
    )
    scene = syn.aerial_scene(MISSION_SCENE_SEED)
    T_teach = syn.aerial_route(length_m, 1.0)
    seq = render_sequence(out_dir / "teach", scene, T_teach, progress=progress("teach") if progress else None)
    map_path = teach_sequence(seq, out_dir / "route.vtrmap", config, gravity_up=up_in_map(T_teach[0]))
    reps = []
    for dy in (*lateral_m, *held_out_m):
        T_rep = syn.drifting_aerial_route(length_m - 1.0, 1.0, dy, 0.0, ramp_m, 0.5)
        rseq = render_sequence(
            out_dir / f"repeat_{dy:g}m" / "images",
            scene,
            T_rep,
            noise_seed=1,
            progress=progress(f"repeat {dy:g} m") if progress else None,
        )
        reps.append((dy, repeat_sequence(rseq, map_path, out_dir / f"repeat_{dy:g}m", config, skip_first_m=ramp_m)))
    model = fit_model([r.landmarks_csv for dy, r in reps if dy in lateral_m])  # the held-out repeats are not fitted
    model_path = out_dir / "model.json"
    model.save(model_path)
    env = localization_envelope(model, map_path, l_min=l_min, c_bar=c_bar, max_m=MISSION_ENVELOPE_MAX_M)
    env_csv, env_png = write_envelope(env, out_dir / "envelope", l_min=l_min, title="synthetic aerial route")
    by_id = {r.vertex_id: r for r in env}
    rows: list[EnvelopeCheck] = []
    for dy, rs in reps:
        side = "left" if dy >= 0 else "right"
        # a capped envelope is at least as wide as the scan: beyond it nothing is predicted
        judged = [
            loc
            for loc in rs.localizations_list
            if loc.trunk_id in by_id
            and not (by_id[loc.trunk_id].capped[side] and abs(dy) > by_id[loc.trunk_id].distance_m[side])
        ]
        holds = [loc for loc in judged if by_id[loc.trunk_id].distance_m[side] >= abs(dy)]
        fails = [loc for loc in judged if loc not in holds]
        rows.append(
            EnvelopeCheck(
                lateral_m=dy,
                fitted="yes" if dy in lateral_m else "held out",
                localizations=rs.localizations,
                successes=rs.successes,
                envelope_holds=len(holds),
                holds_and_localized=sum(loc.success for loc in holds),
                envelope_fails=len(fails),
                fails_and_not_localized=sum(not loc.success for loc in fails),
                median_inliers=float(np.median([loc.inliers for loc in rs.localizations_list]))
                if rs.localizations_list
                else 0.0,
            )
        )
    html = out_dir / "report.html"
    _write_report(html, rows, env, env_png, model, l_min, c_bar)
    return MissionReport(
        out_dir=out_dir,
        map_path=map_path,
        model_path=model_path,
        envelope_csv=env_csv,
        report_html=html,
        rows=tuple(rows),
    )


def _write_report(
    path: Path,
    checks: list[EnvelopeCheck],
    env: list,
    env_png: Path,
    model: PerceptionModel,
    l_min: float,
    c_bar: float,
) -> None:
    rows = [dataclasses.asdict(c) for c in checks]
    left = [e.distance_m["left"] for e in env]
    n_capped = sum(e.capped["left"] for e in env)
    capped_note = (
        f" ({n_capped} of {len(env)} vertices capped at the scan limit {max(left):g} m: there the "
        "envelope is at least that wide, the number is the scan's limit, not a result)"
        if n_capped
        else ""
    )
    head = "".join(f"<th>{k}</th>" for k in rows[0])
    body = "".join(
        "<tr>" + "".join(f"<td>{v:g}</td>" if isinstance(v, float) else f"<td>{v}</td>" for v in r.values()) + "</tr>"
        for r in rows
    )
    path.write_text(f"""<!doctype html><html><head><meta charset="utf-8"><title>vtr: aerial mission</title></head>
<body style="font-family: sans-serif; max-width: 1100px">
<h1>Synthetic aerial mission: teach, repeats, model, envelope</h1>
<p>A ZED-like stereo camera 12 m above a synthetic scene (50 deg down) taught a straight route; the route was
repeated drifting to lateral offsets (left) through the real pipeline (stereo VO, localization chain). The
perception model was fitted (maximum likelihood) on the repeats' <code>landmarks.csv</code>:
c = ({model.c1:.3g}, {model.c2:.3g}, {model.c3:.3g}) per {model.angle_unit}. The <b>localization envelope</b>
(<code>perception-model envelope</code>) gives, for every taught vertex, how far the vehicle may move before
mu - {c_bar:g} sigma &lt; L_min = {l_min:g} (camera as taught); median allowed left offset {np.median(left):.2f} m
{capped_note}.</p>
<h2>Repeats against the envelope</h2>
<table border="1" cellpadding="4"><tr>{head}</tr>{body}</table>
<p><i>envelope_holds</i>: localizations (after the drift ramp) whose offset lies inside their trunk's
envelope; <i>holds_and_localized</i>: of those, the ones that localized; <i>envelope_fails</i>: those outside
it, <i>fails_and_not_localized</i>: of those, the ones that did not localize. Repeats marked <i>held out</i>
were flown after the fit and not fitted on.</p>
<img src="{env_png.relative_to(path.parent)}" width="100%">
</body></html>
""")


__all__ += ["EnvelopeCheck", "MissionReport", "run_aerial_mission"]
