"""Teach: odometry over a run, each keyframe written to the map (as its pose becomes final in the
odometry window) with a temporal edge to the previous one: the privileged path.
"""

from __future__ import annotations

from ..camera import StereoCamera
from ..config import Config
from ..errors import MapError
from ..map import Map
from ..types import Keyframe, OdometryResult, StereoImages
from ..vo.odometry import StereoOdometry


class Teach:
    """Builds the privileged path of a map from a stereo run."""

    def __init__(self, map_: Map, camera: StereoCamera, config: Config, source: str = ""):
        self.map = map_
        self.camera = camera
        self.odometry = StereoOdometry(camera, config, keep_history=False)
        self.run = map_.begin_run("teach", source=source, privileged=True)
        self._unknown_variance = config.odometry.failure_variance
        self.vertices = 0

    def process(self, images: StereoImages) -> OdometryResult:
        result = self.odometry.process(images)
        for kf in result.finalized:
            self._write(kf)
        return result

    def finish(self) -> int:
        """Write the keyframes still in the odometry window; returns the number of vertices."""
        for kf in self.odometry.flush():
            self._write(kf)
        if self.vertices == 0:
            raise MapError("teach produced no keyframe: the map has no taught path")
        return self.vertices

    def _write(self, kf: Keyframe) -> None:
        self.map.add_keyframe(self.run, kf, self.camera.T_vehicle_sensor, unknown_variance=self._unknown_variance)
        self.vertices += 1
