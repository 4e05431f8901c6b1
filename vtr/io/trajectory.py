"""Trajectory files: TUM (``t x y z qx qy qz qw``, seconds), KITTI (3x4 row-major), EuRoC
(``#timestamp [ns],p_x,p_y,p_z,q_w,q_x,q_y,q_z`` CSV). All readable by ``evo``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..conventions import NS_PER_S
from ..errors import DataError
from ..geometry import QUATERNION_NORM_TOLERANCE, T_to_tum, tum_to_T
from .kitti import read_kitti_poses, write_kitti_poses

TRAJECTORY_FORMATS = ("tum", "kitti", "euroc")


def write_tum(path: str | Path, t_ns: np.ndarray, T: np.ndarray) -> None:
    """TUM format: time in seconds (ns precision), position, quaternion xyzw."""
    rows = T_to_tum(np.asarray(T))
    with open(path, "w") as f:
        f.write("# t x y z qx qy qz qw\n")
        for t, r in zip(np.asarray(t_ns, np.int64), rows, strict=True):
            f.write(f"{t // NS_PER_S}.{t % NS_PER_S:09d} " + " ".join(f"{v:.9f}" for v in r) + "\n")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file -> (t_ns int64, T (N, 4, 4)); names the file and line on malformed input."""
    path = Path(path)
    t_ns, rows = [], []
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise DataError(f"{path}: not a text file (expected a TUM trajectory)") from None
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        if len(parts) != 8:
            raise DataError(f"{path}:{lineno}: expected 8 columns (t x y z qx qy qz qw), got {len(parts)}")
        try:
            sec, _, frac = parts[0].partition(".")
            t_ns.append(int(sec) * NS_PER_S + int((frac + "000000000")[:9]))
            rows.append([float(v) for v in parts[1:]])
        except ValueError as err:
            raise DataError(f"{path}:{lineno}: not numbers: {s!r}") from err
        if not np.isfinite(rows[-1]).all():
            raise DataError(f"{path}:{lineno}: NaN or infinite value")
        q_norm = float(np.linalg.norm(rows[-1][3:]))
        if abs(q_norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise DataError(f"{path}:{lineno}: quaternion norm {q_norm:.6g} is not 1")
    if not rows:
        raise DataError(f"{path}: no poses")
    return np.array(t_ns, np.int64), tum_to_T(np.array(rows))


def write_euroc(path: str | Path, t_ns: np.ndarray, T: np.ndarray) -> None:
    """EuRoC ground-truth style CSV (ns, position, quaternion wxyz)."""
    rows = T_to_tum(np.asarray(T))
    with open(path, "w") as f:
        f.write("#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []\n")
        for t, r in zip(np.asarray(t_ns, np.int64), rows, strict=True):
            vals = [*r[:3], r[6], r[3], r[4], r[5]]
            f.write(f"{t}," + ",".join(f"{v:.9f}" for v in vals) + "\n")


def write_trajectory(path: str | Path, t_ns: np.ndarray, T: np.ndarray, fmt: str) -> None:
    """Write poses in one of ``TRAJECTORY_FORMATS`` (KITTI carries no times)."""
    if fmt == "tum":
        write_tum(path, t_ns, T)
    elif fmt == "kitti":
        write_kitti_poses(Path(path), np.asarray(T))
    elif fmt == "euroc":
        write_euroc(path, t_ns, T)
    else:
        raise DataError(f"unknown trajectory format {fmt!r}; known: {', '.join(TRAJECTORY_FORMATS)}")


__all__ = ["TRAJECTORY_FORMATS", "read_kitti_poses", "read_tum", "write_euroc", "write_trajectory", "write_tum"]
