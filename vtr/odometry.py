"""Keyframe stereo visual odometry (the teach front end).

Per frame (VT&R3's "petiole" scheme): stereo features of the new frame are matched to the
landmarks of the last keyframe around where a constant-velocity prior predicts them, P3P RANSAC
rejects outliers, a two-view stereo bundle adjustment refines ``T_frame_keyframe`` (and the
landmarks), and the keyframe test decides whether the frame becomes a new vertex.

Frames: every pose is of the left rectified camera. ``T_world_frame`` is expressed in the first
camera frame of the run (world = camera 0), as KITTI ground truth is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from .camera import StereoCamera
from .config import Config, OdometryConfig
from .estimation import ransac_pnp, refine_two_view
from .features import best_matches, hamming_pairs, radius_pairs
from .geometry import exp_se3, inv_T, log_se3, rotation_angle
from .io.base import StereoImages
from .stereo import StereoFrame, StereoProcessor


class FrameKind(StrEnum):
    """What odometry did with a frame (VT&R3's vertex-test results)."""

    CREATE_VERTEX = "CREATE_VERTEX"        # the frame became a new keyframe
    CREATE_CANDIDATE = "CREATE_CANDIDATE"  # tracked; not far enough for a new keyframe
    DO_NOTHING = "DO_NOTHING"              # tracked; the vehicle did not move measurably
    FAILURE = "FAILURE"                    # not tracked; pose carried by the motion prior


@dataclass(frozen=True)
class Keyframe:
    """A vertex of the teach path: its stereo frame, pose and the edge from the previous keyframe.

    ``T_prev_kf`` maps this keyframe's camera coordinates into the previous keyframe's camera;
    ``edge_covariance`` is its 6x6 covariance ([rot, trans], GTSAM tangent order).
    """

    id: int
    frame: StereoFrame
    T_world_kf: np.ndarray
    T_prev_kf: np.ndarray
    edge_covariance: np.ndarray
    edge_inliers: int

    @property
    def t_ns(self) -> int:
        return self.frame.t_ns


@dataclass(frozen=True)
class OdometryResult:
    """Outcome of one frame. ``T_keyframe_frame`` maps the frame into the keyframe it was matched to."""

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
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class _Track:
    """Mutable state carried between frames."""

    keyframe: Keyframe
    T_frame_kf: np.ndarray            # last frame relative to the keyframe
    t_ns: int
    velocity: np.ndarray | None       # twist per second of T_frame_prev ([rot, trans])
    failures: int = 0


class StereoOdometry:
    """Keyframe stereo visual odometry; feed frames in time order with ``process``."""

    def __init__(self, camera: StereoCamera, config: Config | None = None):
        self.config = config or Config()
        self.camera = camera
        self.stereo = StereoProcessor(camera, self.config.features, self.config.stereo)
        self._track: _Track | None = None
        self._next_id = 0

    @property
    def keyframe(self) -> Keyframe | None:
        return self._track.keyframe if self._track else None

    def process(self, images: StereoImages) -> OdometryResult:
        """Stereo-process a rectified pair, then track it (``process_frame``)."""
        return self.process_frame(self.stereo.process(images))

    def process_frame(self, frame: StereoFrame) -> OdometryResult:
        """Track one stereo frame against the last keyframe."""
        cfg = self.config.odometry
        if self._track is None:
            return self._start(frame)
        tr = self._track
        kf = tr.keyframe
        dt = (frame.t_ns - tr.t_ns) * 1e-9
        T_pred = tr.T_frame_kf if tr.velocity is None else exp_se3(tr.velocity * dt) @ tr.T_frame_kf
        radius = cfg.match_radius_px if tr.velocity is not None else cfg.match_radius_no_prior_px
        est = self._estimate(kf.frame, frame, T_pred, radius)
        if est is None and radius < cfg.match_radius_no_prior_px:
            est = self._estimate(kf.frame, frame, T_pred, cfg.match_radius_no_prior_px)
        if est is not None and not self._plausible(est[0], tr.T_frame_kf):
            est = None
        if est is None:
            return self._fail(frame, T_pred)
        T_frame_kf, cov, n_matches, n_inliers = est
        T_step = T_frame_kf @ inv_T(tr.T_frame_kf)
        velocity = log_se3(T_step) / dt if dt > 0 else tr.velocity
        T_kf_frame = inv_T(T_frame_kf)
        T_world_frame = kf.T_world_kf @ T_kf_frame
        trans = np.linalg.norm(T_kf_frame[:3, 3])
        rot = np.degrees(rotation_angle(T_kf_frame[:3, :3]))
        if trans > cfg.keyframe_translation_m or rot > cfg.keyframe_rotation_deg \
                or n_inliers < cfg.keyframe_min_inliers:
            new_kf = Keyframe(self._take_id(), frame, T_world_frame, T_kf_frame, cov, n_inliers)
            self._track = _Track(new_kf, np.eye(4), frame.t_ns, velocity)
            kind = FrameKind.CREATE_VERTEX
        else:
            new_kf = None
            moved = np.linalg.norm(T_step[:3, 3]) > 1e-3 or rotation_angle(T_step[:3, :3]) > 1e-4
            self._track = _Track(kf, T_frame_kf, frame.t_ns, velocity)
            kind = FrameKind.CREATE_CANDIDATE if moved else FrameKind.DO_NOTHING
        return OdometryResult(frame.t_ns, frame.index, kind, n_matches, n_inliers, kf.id, T_kf_frame,
                              T_world_frame, cov, new_kf)

    def final_poses(self, results: list[OdometryResult]) -> np.ndarray:
        """Poses (N, 4, 4) of the processed frames in the first camera frame, as finally estimated."""
        return np.array([r.T_world_frame for r in results]).reshape(-1, 4, 4)

    def _take_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    def _start(self, frame: StereoFrame) -> OdometryResult:
        kf = Keyframe(self._take_id(), frame, np.eye(4), np.eye(4), np.zeros((6, 6)), 0)
        self._track = _Track(kf, np.eye(4), frame.t_ns, None)
        return OdometryResult(frame.t_ns, frame.index, FrameKind.CREATE_VERTEX, 0, 0, kf.id, np.eye(4),
                              np.eye(4), np.zeros((6, 6)), kf)

    def _plausible(self, T_frame_kf: np.ndarray, T_prev_frame_kf: np.ndarray) -> bool:
        cfg = self.config.odometry
        step = T_frame_kf @ inv_T(T_prev_frame_kf)
        return bool(np.linalg.norm(step[:3, 3]) <= cfg.max_step_translation_m
                    and np.degrees(rotation_angle(step[:3, :3])) <= cfg.max_step_rotation_deg)

    def _fail(self, frame: StereoFrame, T_pred: np.ndarray) -> OdometryResult:
        """No reliable estimate: carry the pose by the motion prior; restart from this frame."""
        tr = self._track
        kf = tr.keyframe
        T_kf_frame = inv_T(T_pred)
        T_world_frame = kf.T_world_kf @ T_kf_frame
        # the frame becomes the new reference so tracking can resume; its edge is the prior (unknown covariance)
        big = np.diag([1e2] * 6)
        new_kf = Keyframe(self._take_id(), frame, T_world_frame, T_kf_frame, big, 0)
        self._track = _Track(new_kf, np.eye(4), frame.t_ns, tr.velocity, tr.failures + 1)
        return OdometryResult(frame.t_ns, frame.index, FrameKind.FAILURE, 0, 0, kf.id, T_kf_frame,
                              T_world_frame, big, new_kf)

    def _estimate(self, ref: StereoFrame, cur: StereoFrame, T_pred: np.ndarray, radius: float):
        """Match, RANSAC and refine ``T_cur_ref``; None when too few inliers."""
        cfg: OdometryConfig = self.config.odometry
        ia, jb = match_to_landmarks(ref, cur, T_pred, self.camera, radius, cfg.max_descriptor_distance,
                                    cfg.ratio_test)
        if len(ia) < cfg.min_inliers:
            return None
        rs = ransac_pnp(ref.points[ia], cur.features.uv[jb], self.camera, cfg.ransac_iterations,
                        cfg.ransac_threshold_px, cfg.ransac_confidence, cfg.seed)
        if rs is None or len(rs.inliers) < cfg.min_inliers:
            return None
        ia_in, jb_in = ia[rs.inliers], jb[rs.inliers]
        ref_z = ref.stereo_measurements[ia_in]
        cur_z = cur.stereo_measurements[jb_in]
        # far landmarks: their disparity is too small to trust for depth, so they constrain rotation only
        far = ref.points[ia_in, 2] > cfg.far_point_baselines * self.camera.baseline
        ref_z[far, 2] = np.nan
        cur_z[far, 2] = np.nan
        rf = refine_two_view(rs.T_q_r, ref.points[ia_in], ref_z, cur_z, self.camera,
                             self.config.stereo.pixel_sigma, cfg.huber_px, cfg.refine_iterations,
                             cfg.ransac_threshold_px)
        n_in = int(rf.inlier.sum())
        if n_in < cfg.min_inliers:
            return None
        return rf.T_q_r, rf.covariance, len(ia), n_in


def match_to_landmarks(ref: StereoFrame, cur: StereoFrame, T_cur_ref: np.ndarray, camera: StereoCamera,
                       radius: float, max_distance: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Match reference landmarks (with depth) to current features near their predicted projection.

    Returns (reference indices, current indices).
    """
    ref_idx = np.flatnonzero(ref.has_depth)
    P = ref.points[ref_idx] @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
    front = P[:, 2] > 0.1
    ref_idx, P = ref_idx[front], P[front]
    pred = camera.project(P)[:, :2]
    inside = (pred[:, 0] >= -radius) & (pred[:, 0] < camera.width + radius) \
        & (pred[:, 1] >= -radius) & (pred[:, 1] < camera.height + radius)
    ref_idx, pred = ref_idx[inside], pred[inside]
    pi, cj = radius_pairs(pred, cur.features.uv, radius)
    ia = ref_idx[pi]
    dist = hamming_pairs(ref.features.descriptors, cur.features.descriptors, ia, cj)
    qi, tj, _ = best_matches(dist, ia, cj, max_distance, ratio=ratio, mutual=True)
    return qi, tj
