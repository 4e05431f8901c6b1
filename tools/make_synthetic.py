"""Write example synthetic stereo sequences (KITTI layout) with exact ground truth.

Usage: ``python tools/make_synthetic.py [OUT_DIR]`` (default ``/tmp/vtr_synthetic``). Writes:

- ``aerial_teach/``: multirotor, ZED-like camera, 12 m altitude, camera pitched 50 deg down, 60 m
  straight line, one frame per metre at 2 m/s;
- ``aerial_repeat/``: the same path flown 2 m to the left and 1 m higher, frames offset by half a
  spacing (teach and repeat never share a viewpoint);
- ``turn_far/``: ground vehicle, ZED-like camera 1.5 m high, straight-90 deg turn-straight, in a
  scene whose texture lies mostly beyond 40 baselines (faint ground, structures >= 25 m away,
  mountain backdrop at 60 m).

``poses.txt`` in each folder is T_cam0_cam (KITTI convention: world = first left camera);
``poses_world.txt`` is T_world_cam in the scene's ENU world, shared by teach and repeat.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from vtr.sim import synthetic as syn

DEFAULT_OUT = Path("/tmp/vtr_synthetic")
SEED = 0
AERIAL_LENGTH_M = 60.0
AERIAL_SPACING_M = 1.0
AERIAL_SPEED_MPS = 2.0
REPEAT_LATERAL_OFFSET_M = 2.0
REPEAT_VERTICAL_OFFSET_M = 1.0
TURN_SPACING_M = 0.25
TURN_SPEED_MPS = 2.5
TURN_CENTRE_XY = (10.0, 8.0)  # centre of the default turn (10 m straight, then radius 8 m left)
NOISE_SIGMA = 1.0


def write_examples(out_dir: Path) -> list[Path]:
    camera = syn.zed_camera()
    aerial = syn.aerial_scene(SEED)
    written = []
    teach = syn.aerial_route(AERIAL_LENGTH_M, AERIAL_SPACING_M)
    repeat = syn.aerial_route(
        AERIAL_LENGTH_M,
        AERIAL_SPACING_M,
        start_offset_m=AERIAL_SPACING_M / 2,
        lateral_offset_m=REPEAT_LATERAL_OFFSET_M,
        vertical_offset_m=REPEAT_VERTICAL_OFFSET_M,
    )
    for name, T, seed in (("aerial_teach", teach, 1), ("aerial_repeat", repeat, 2)):
        t_ns = syn.route_times(T, AERIAL_SPEED_MPS)
        written.append(
            syn.write_sequence(out_dir / name, aerial, camera, T, t_ns, noise_sigma=NOISE_SIGMA, noise_seed=seed)
        )
    turn = syn.turning_route(TURN_SPACING_M)
    far = syn.far_structure_scene(SEED, route_xy=turn[:, :2, 3], centre_xy=TURN_CENTRE_XY)
    t_ns = syn.route_times(turn, TURN_SPEED_MPS)
    written.append(
        syn.write_sequence(out_dir / "turn_far", far, camera, turn, t_ns, noise_sigma=NOISE_SIGMA, noise_seed=3)
    )
    return written


def main() -> None:
    ap = argparse.ArgumentParser(description="Write example synthetic stereo sequences (KITTI layout).")
    ap.add_argument("out", nargs="?", type=Path, default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    out = ap.parse_args().out
    t0 = time.perf_counter()
    for path in write_examples(out):
        n = len(list((path / "image_0").iterdir()))
        print(f"{path}: {n} stereo pairs")
    print(f"done in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
