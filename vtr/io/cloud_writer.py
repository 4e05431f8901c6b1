"""Writes a CLOUD run folder in the layout :class:`vtr.io.cloud.CloudRun` reads (synthetic runs for tests and
tools; docs/inputs.md, "CLOUD run folders")."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike

from ..errors import DataError
from .cloud import IMAGES_DIR, QUAT_ORDERS, STREAM_FILES
from .cloud_geometry import spatial_transform


class CloudRunWriter:
    """Writes a CLOUD run folder with the layout ``CloudRun`` reads (first accepted file names)."""

    def __init__(self, path: str | Path, quat_order: str = "xyzw"):
        if quat_order not in QUAT_ORDERS:
            raise DataError(f"quat_order {quat_order!r}: one of {', '.join(QUAT_ORDERS)}")
        self.path = Path(path)
        (self.path / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
        self.quat_order = quat_order

    def _write(self, name: str, t_ns: ArrayLike, cols: Sequence[ArrayLike], fmt: str) -> Path:
        f = self.path / STREAM_FILES[name][0]
        t_ns = np.asarray(t_ns, np.int64)
        vals = np.column_stack([np.asarray(c, float) for c in cols])
        with open(f, "w") as fh:
            for t, row in zip(t_ns, vals, strict=True):
                fh.write(f"{int(t)}," + ",".join(fmt % x for x in row) + "\n")
        return f

    def _q(self, R: ArrayLike) -> np.ndarray:
        q = spatial_transform().Rotation.from_matrix(np.asarray(R, float).reshape(-1, 3, 3)).as_quat()
        return q[:, [3, 0, 1, 2]] if self.quat_order == "wxyz" else q

    def write_images(self, t_ns: np.ndarray, images: Sequence[np.ndarray], ext: str = ".png") -> None:
        """``images/NNNNNN<ext>`` and the image-id stream (ids without extension)."""
        ids = []
        for k, img in enumerate(images):
            ids.append(f"{k:06d}")
            cv2.imwrite(str(self.path / IMAGES_DIR / f"{ids[-1]}{ext}"), img)
        with open(self.path / STREAM_FILES["image_ids"][0], "w") as fh:
            for t, i in zip(np.asarray(t_ns, np.int64), ids, strict=True):
                fh.write(f"{int(t)},{i}\n")

    def write_velocities(self, t_ns: ArrayLike, v_enu: ArrayLike) -> None:
        """Velocity (m/s) in ground ENU."""
        self._write("velocities", t_ns, list(np.asarray(v_enu, float).T), "%.9f")

    def write_acceleration(self, t_ns: ArrayLike, a_vehicle: ArrayLike) -> None:
        """Specific force (m/s^2) in vehicle FLU."""
        self._write("acceleration", t_ns, list(np.asarray(a_vehicle, float).T), "%.9f")

    def write_attitude(self, t_ns: ArrayLike, R_enu_vehicle: ArrayLike) -> None:
        """Attitude rotations vehicle FLU -> ENU (N, 3, 3)."""
        self._write("attitude", t_ns, list(self._q(R_enu_vehicle).T), "%.12f")

    def write_gps(self, t_ns: ArrayLike, lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> None:
        """WGS84 fixes (deg, deg, m)."""
        self._write("gps", t_ns, [lat_deg, lon_deg, alt_m], "%.12f")

    def write_gimbal_state(self, t_ns: ArrayLike, T_base_camera: ArrayLike) -> None:
        """Camera poses on the base (N, 4, 4)."""
        T = np.asarray(T_base_camera, float).reshape(-1, 4, 4)
        self._write("gimbal_state", t_ns, [*T[:, :3, 3].T, *self._q(T[:, :3, :3]).T], "%.12f")

    def write_gimbal_angles(self, t_ns: ArrayLike, roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> None:
        """Gimbal angles given in rad, written in degrees."""
        self._write("gimbal_angles", t_ns, [np.degrees(roll), np.degrees(pitch), np.degrees(yaw)], "%.9f")
