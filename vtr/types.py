"""The stage-boundary records: what one stage hands the next (frozen dataclasses, no behaviour beyond
small views of their own fields).

``StereoImages`` (frame sources) -> ``Features`` / ``StereoFrame`` (stereo processing) -> ``OdometryResult``,
``Keyframe``, ``FrameKind``, ``FrameRecord`` (odometry) -> teach, repeat, map.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from perception_model.records import short_repr


@dataclass(frozen=True)
class StereoImages:
    """One rectified stereo pair: ``t_ns`` is the left image's time, ``index`` its position in the source."""

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    t_ns: int
    index: int
    left: np.ndarray
    right: np.ndarray


@dataclass(frozen=True)
class Features:
    """Keypoints of one image: ``uv`` (N, 2) px, ``octave`` (N,), ``response`` (N,), ``descriptors`` (N, 32)."""

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    uv: np.ndarray
    octave: np.ndarray
    response: np.ndarray
    descriptors: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, idx: np.ndarray) -> Features:
        return Features(self.uv[idx], self.octave[idx], self.response[idx], self.descriptors[idx])


@dataclass(frozen=True)
class StereoFrame:
    """Features of the left image with their stereo measurements.

    ``u_right`` (N,) is the matched right-image column (NaN when unmatched); ``points`` (N, 3) the
    triangulated landmark in the left camera frame (NaN rows when unmatched), metres.
    """

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    t_ns: int
    index: int
    features: Features
    u_right: np.ndarray
    points: np.ndarray

    @property
    def has_depth(self) -> np.ndarray:
        return np.isfinite(self.u_right)

    @property
    def stereo_measurements(self) -> np.ndarray:
        """(N, 3) measurements u_l, v, u_r (u_r NaN when unmatched)."""
        return np.column_stack([self.features.uv, self.u_right])


class FrameKind(StrEnum):
    """What odometry did with a frame (VT&R3's vertex-test results)."""

    CREATE_VERTEX = "CREATE_VERTEX"  # the frame became a new keyframe
    CREATE_CANDIDATE = "CREATE_CANDIDATE"  # tracked; not far enough for a new keyframe
    DO_NOTHING = "DO_NOTHING"  # tracked; the vehicle did not move measurably
    FAILURE = "FAILURE"  # not tracked; pose carried by the motion prior


@dataclass(frozen=True)
class Keyframe:
    """A keyframe from odometry: its stereo frame, camera pose in the run's world and what odometry measured.

    ``edge_covariance`` (6x6, [rot, trans], GTSAM tangent order) and ``edge_inliers`` describe the
    odometry estimate of this keyframe's pose (the covariance already usable: an estimate without
    information is ``odometry.failure_variance * I``); the map's temporal edge from the run's previous vertex
    (:meth:`vtr.map.Map.add_keyframe`, the one way a keyframe reaches the map) takes them, with the
    relative transform from the two stored poses.
    """

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    id: int
    frame: StereoFrame
    T_world_kf: np.ndarray
    edge_covariance: np.ndarray
    edge_inliers: int

    @property
    def t_ns(self) -> int:
        return self.frame.t_ns


@dataclass(frozen=True)
class OdometryResult:
    """Outcome of one frame. ``T_keyframe_frame`` maps the frame into the keyframe it was matched to."""

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    t_ns: int
    index: int
    kind: FrameKind
    matches: int
    inliers: int
    keyframe_id: int
    T_keyframe_frame: np.ndarray
    T_world_frame: np.ndarray
    covariance: np.ndarray
    new_keyframe: Keyframe | None = None
    finalized: tuple[Keyframe, ...] = ()

    @property
    def vertex_id(self) -> int:
        """The keyframe this frame belongs to: its own new vertex, else the reference keyframe."""
        return self.new_keyframe.id if self.new_keyframe is not None else self.keyframe_id

    def record(self) -> FrameRecord:
        """The few numbers a run log keeps per frame (no images, features or landmarks)."""
        return FrameRecord(
            self.t_ns, self.kind, self.matches, self.inliers, self.vertex_id, self.new_keyframe is not None
        )


@dataclass(frozen=True)
class FrameRecord:
    """What a long run keeps of each frame: its result, match counts and the vertex it belongs to."""

    __repr__ = short_repr  # arrays by shape: print(record) stays short

    t_ns: int
    kind: FrameKind
    matches: int
    inliers: int
    vertex_id: int
    new_vertex: bool
