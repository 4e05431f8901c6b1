"""The drift line says what it measures (sub-segments of 10-40 m, not KITTI's 100-800 m) and why when it
cannot measure (no segment: no NaN printed), and the odometry summary explains a single keyframe."""

from __future__ import annotations

import shutil

import numpy as np
from click.testing import CliRunner

from vtr.app.evaluation import drift_metrics
from vtr.cli import main


def _straight(n: int, step_m: float) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 2, 3] = step_m * np.arange(n)
    return T


def test_drift_line_names_the_segment_lengths():
    gt = _straight(60, 1.0)
    est = gt.copy()
    est[:, 2, 3] *= 1.01
    line = str(drift_metrics(est, gt))
    assert "t_err 1.000 %" in line and "sub-segments of 10-40 m" in line and "100-800 m" in line, line


def test_drift_line_on_a_short_path_says_why_instead_of_nan():
    gt = _straight(5, 1.0)  # 4 m: no 10 m segment
    line = str(drift_metrics(gt, gt))
    assert "nan" not in line.lower() and "not measured" in line and "4.0 m" in line, line


def test_euroc_revisit_pairs_print_no_nan(euroc_pairs, tmp_path):
    r = CliRunner().invoke(main, ["odometry", str(euroc_pairs), "--out", str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    assert "nan" not in r.stdout.lower() and "not measured" in r.stdout, r.stdout


def test_static_log_says_why_one_keyframe(kitti_clip, tmp_path):
    clip = tmp_path / "static"
    first = sorted((kitti_clip / "image_0").iterdir())[0].name
    for sub in ("image_0", "image_1"):
        (clip / sub).mkdir(parents=True)
        for i in range(5):  # the same stereo pair five times
            shutil.copy(kitti_clip / sub / first, clip / sub / f"{i:06d}.png")
    shutil.copy(kitti_clip / "calib.txt", clip / "calib.txt")
    (clip / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(5)))
    r = CliRunner().invoke(main, ["odometry", str(clip), "--out", str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    assert "keyframes 1 " in r.stdout and "only the first frame is a keyframe" in r.stdout, r.stdout
    assert "keyframe_translation_m" in r.stdout
