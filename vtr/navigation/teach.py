"""Teach: odometry over a run, each keyframe written to the map (as its pose becomes final in the
odometry window) with a temporal edge to the previous one: the privileged path.

Lifecycle: ``finish`` writes the keyframes still in the window and marks the run finished (a
complete route), unless odometry failed on more than ``odometry.teach_max_failed_fraction`` of the
frames (``TeachFailedError``: the caller aborts the run with it); ``abort(exc)`` (on an error,
Ctrl-C, SIGTERM, full disk) writes them too, as far as it can, and marks the run aborted with the
reason, so a repeat does not take it for complete.
"""

from __future__ import annotations

from ..camera import StereoCamera
from ..config import Config
from ..errors import MapError, TeachFailedError
from ..map import Map
from ..map.store import abort_reason
from ..types import FrameKind, Keyframe, OdometryResult, StereoFrame, StereoImages
from ..vo.odometry import OdometrySettings, StereoOdometry
from .place import route_place_index


class Teach:
    """Builds the privileged path of a map from a stereo run."""

    def __init__(self, map_: Map, camera: StereoCamera, config: Config, source: str = ""):
        """``config``: a run-level root, it hands each part its sections (the odometry ``OdometrySettings.of``,
        the place index ``place`` and ``run.seed``) and keeps ``odometry.teach_max_failed_fraction``
        (docs/configuration.md)."""
        self.map = map_
        self.camera = camera
        self.odometry = StereoOdometry(camera, OdometrySettings.of(config), keep_history=False)
        self.run = map_.begin_run("teach", source=source, privileged=True)
        self._place = config.place
        self._seed = config.run.seed
        self._max_failed = config.odometry.teach_max_failed_fraction
        self.vertices = 0
        self.frames = 0  # frames through odometry
        self.failures = 0  # ... of which odometry failed on (FAILURE)

    def process(self, images: StereoImages) -> OdometryResult:
        """Stereo-process a rectified pair, then :meth:`process_frame`."""
        return self.process_frame(self.odometry.stereo.process(images))

    def process_frame(self, frame: StereoFrame) -> OdometryResult:
        """Odometry on one stereo frame; keyframes leaving the odometry window are written to the map."""
        result = self.odometry.process_frame(frame)
        self.frames += 1
        self.failures += result.kind == FrameKind.FAILURE
        for kf in result.finalized:
            self._write(kf)
        return result

    def finish(self) -> int:
        """Write the keyframes still in the odometry window and finish the run; returns the number of
        vertices. ``TeachFailedError`` when odometry failed on more than ``odometry.teach_max_failed_fraction``
        of the frames, ``MapError`` when the teach produced no keyframe (the run left open for ``abort``)."""
        if self.frames and self.failures > self._max_failed * self.frames:
            raise TeachFailedError(
                f"teach failed: odometry failed on {self.failures} of {self.frames} frames (more than "
                f"odometry.teach_max_failed_fraction = {self._max_failed:g} of them), so the map is no route; "
                "check the images, the calibration and the frame range"
            )
        self._flush()
        if self.vertices == 0:
            raise MapError("teach produced no keyframe: the map has no taught path")
        self.map.finish_run()
        try:
            route_place_index(self.map, self._place, self._seed)  # where-am-I index of the route, stored in the map
        except MapError:
            pass  # derived data (e.g. no room to store it): the first repeat builds it from the vertices
        return self.vertices

    def abort(self, exc: BaseException) -> int:
        """End the run as aborted because of ``exc``: the keyframes still in the odometry window are
        written first (as far as the map can take them), then the reason. Never raises (``exc`` is
        the error to report); returns the number of vertices written."""
        try:
            self._flush()
        except Exception:  # noqa: BLE001, S110 - e.g. the disk is full: keep what was written
            pass
        try:
            self.map.abort_run(abort_reason(exc))
        except Exception:  # noqa: BLE001, S110 - cannot write at all: the run reads as interrupted
            pass
        return self.vertices

    def _flush(self) -> None:
        for kf in self.odometry.flush():
            self._write(kf)

    def _write(self, kf: Keyframe) -> None:
        self.map.add_keyframe(self.run, kf, self.camera.T_vehicle_sensor)
        self.vertices += 1
