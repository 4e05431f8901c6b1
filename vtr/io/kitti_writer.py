"""Writing stereo pairs into a KITTI-layout folder (the reader is ``kitti``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..camera import StereoCamera
from ..conventions import NS_PER_S
from .kitti import write_kitti_poses


def write_kitti_calib(path: Path, camera: StereoCamera) -> None:
    """Write P0/P1 of a rectified stereo camera as KITTI ``calib.txt``."""
    K = camera.K
    P0 = np.hstack([K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -camera.fb
    with open(path, "w") as f:
        for name, P in (("P0", P0), ("P1", P1)):
            f.write(f"{name}: " + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n")


class KittiWriter:
    """Writes stereo pairs into a KITTI-layout folder (PNG, lossless)."""

    def __init__(self, path: str | Path, camera: StereoCamera):
        self.path = Path(path)
        (self.path / "image_0").mkdir(parents=True, exist_ok=True)
        (self.path / "image_1").mkdir(parents=True, exist_ok=True)
        write_kitti_calib(self.path / "calib.txt", camera)
        self._times: list[int] = []

    def add(self, t_ns: int, left: np.ndarray, right: np.ndarray) -> None:
        name = f"{len(self._times):06d}.png"
        cv2.imwrite(str(self.path / "image_0" / name), left)
        cv2.imwrite(str(self.path / "image_1" / name), right)
        self._times.append(int(t_ns))

    def close(self, T_world_cam: np.ndarray | None = None) -> None:
        """Write times.txt (and poses.txt when given) once all frames are in."""
        np.savetxt(self.path / "times.txt", np.asarray(self._times) / NS_PER_S, fmt="%.9f")
        np.savetxt(self.path / "times_ns.txt", np.asarray(self._times, np.int64), fmt="%d")
        if T_world_cam is not None:
            write_kitti_poses(self.path / "poses.txt", T_world_cam)
