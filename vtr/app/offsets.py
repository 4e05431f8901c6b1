"""The synthetic offset experiment: teach an aerial route in a rendered scene, repeat it at lateral and
vertical offsets, and measure localization (success rate, inliers, estimated against true offset).

Each repeat writes its ``landmarks.csv`` (input of ``perception-model fit``); ``tools/synthetic_offsets.py``
runs a grid of offsets and plots it, ``tools/perception_end_to_end.py`` fits the perception model on the
result. Camera: ZED-like 672x376, 0.12 m baseline, 12 m above ground, 50 deg down.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from ..config import Config
from ..geometry import inv_T
from ..io import open_source
from ..map import Map, split_vertex_id
from ..navigation.experiences import single_experience
from ..navigation.repeat import Repeat
from ..sim import synthetic as syn
from .mission import teach_sequence
from .pipeline import write_landmarks_csv
from .repeat_run import run_repeat

SPEED_MPS = 4.0  # flight speed used for timestamps
REPEAT_PHASE_M = 0.5  # repeat frames sit half a spacing along from the taught ones
RAMP_M = 6.0  # the repeat leaves the taught path and reaches its offset over this distance


def lateral_offsets(T_world_teach: np.ndarray, T_world_repeat: np.ndarray, heading_rad: float) -> np.ndarray:
    """Signed left offset (m) of repeat camera centres from the straight taught path (ENU)."""
    left = np.array([-np.sin(heading_rad), np.cos(heading_rad), 0.0])
    return (T_world_repeat[:, :3, 3] - T_world_teach[0, :3, 3]) @ left


def repeat_name(lateral_m: float, vertical_m: float) -> str:
    """Folder (under OUT) of the repeat with these offsets; it holds that repeat's landmarks.csv."""
    return f"repeat_lat{lateral_m:g}_up{vertical_m:g}"


def run_offset_repeats(
    out: Path,
    lateral: list[float],
    vertical: list[float],
    length: float,
    seed: int = 0,
    ramp_m: float = RAMP_M,
    offsets: list[tuple[float, float]] | None = None,
) -> list[dict[str, float]]:
    """Teach ``length`` m, then one repeat per (vertical, lateral) offset reaching it over ``ramp_m`` m;
    localizations before the offset is reached are left out of the statistics and landmarks.csv.
    ``offsets`` (lateral, vertical) pairs replace the grid ``lateral`` x ``vertical`` when given."""
    cam = syn.zed_camera()
    scene = syn.aerial_scene(seed)
    cfg = Config()
    T_teach = syn.aerial_route(length, 1.0)
    teach_dir = syn.write_sequence(out / "teach", scene, cam, T_teach, syn.route_times(T_teach, SPEED_MPS))
    map_path = teach_sequence(teach_dir, out / "route.vtrmap", cfg)
    rows: list[dict[str, float]] = []
    pairs = offsets if offsets is not None else [(dy, dz) for dz in vertical for dy in lateral]
    for dy, dz in pairs:
        name = repeat_name(dy, dz)
        T_rep = syn.drifting_aerial_route(length - 1.0, 1.0, dy, dz, ramp_m, REPEAT_PHASE_M)
        rep_dir = syn.write_sequence(out / name, scene, cam, T_rep, syn.route_times(T_rep, SPEED_MPS), noise_seed=1)
        with open_source(rep_dir) as src, Map.open(map_path, "a") as m:
            teach_world = np.loadtxt(teach_dir / "poses_world.txt").reshape(-1, 3, 4)
            T_w_teach = np.tile(np.eye(4), (len(teach_world), 1, 1))
            T_w_teach[:, :3, :] = teach_world
            taught = m.taught_path()
            src_times = np.loadtxt(teach_dir / "times_ns.txt", dtype=np.int64)
            # each offset against the teach alone: the earlier offsets' repeats in this map must not help
            rp = Repeat(m, single_experience(cfg), str(rep_dir))
            loop = run_repeat(rp, rp.odometry.stereo.frames(iter(src)), keep_landmarks=True)
            locs, seconds = list(loop.localizations), loop.seconds
        est = []
        # judged once the offset is reached (1 m spacing: every frame is a keyframe)
        locs = [loc for loc in locs if split_vertex_id(loc.leaf_id)[1] >= ramp_m]
        for loc in locs:
            if not loc.success:
                continue
            k = int(np.searchsorted(src_times, taught.t_ns[taught.index(loc.trunk_id)]))
            T_w_leaf = T_w_teach[k] @ inv_T(loc.T_leaf_trunk)
            est.append(lateral_offsets(T_w_teach, T_w_leaf[None], 0.0)[0])
        ok = [loc for loc in locs if loc.success]
        write_landmarks_csv(out / name / "landmarks.csv", locs)
        row = {
            "lateral_m": dy,
            "vertical_m": dz,
            "vertices": len(locs),
            "localized": len(ok),
            "success_rate": len(ok) / max(len(locs), 1),
            "median_inliers": float(np.median([loc.inliers for loc in ok])) if ok else 0.0,
            "median_est_lateral_m": float(np.median(est)) if est else float("nan"),
            "max_abs_lateral_error_m": float(np.max(np.abs(np.array(est) - dy))) if est else float("nan"),
            "fps": len(src) / seconds,
        }
        rows.append(row)
        shutil.rmtree(rep_dir / "image_0")
        shutil.rmtree(rep_dir / "image_1")
    return rows
