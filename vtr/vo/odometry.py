"""Keyframe stereo visual odometry (the teach front end).

Per frame: stereo features of the new frame are matched to the landmarks of a local map (the
last few keyframes) around where a constant-velocity prior predicts them; P3P RANSAC rejects
outliers; the pose is refined on stereo reprojection errors; the keyframe test (VT&R3's vertex
test) decides whether the frame becomes a new vertex. Each new keyframe triggers a windowed
bundle adjustment over the last ``window_keyframes`` keyframes and their landmarks (VT&R3's
default), stereo reprojection errors in both images, landmarks free along their rays. Far
landmarks (beyond ``far_point_baselines`` baselines) keep only a token weight on their disparity,
so they constrain rotation, while the scale comes from near landmarks and multi-view parallax.

Frames: every pose is of the left rectified camera. ``T_world_frame`` is expressed in the first
camera frame of the run (world = camera 0), as KITTI ground truth is.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass
from typing import cast

import numpy as np

from ..camera import StereoCamera
from ..config import Config, EstimationConfig, FeatureConfig, OdometryConfig, StereoConfig
from ..errors import ConfigError, EstimationError
from ..geometry import exp_se3, inv_T, log_se3, rotation_angle, usable_covariance
from ..timing import StageTimer
from ..types import FrameKind, Keyframe, OdometryResult, StereoFrame, StereoImages
from .disparity_offset import DisparityOffsetEstimator, corrected
from .estimation import bundle_adjust, odometry_row_weights, ransac_pnp, triangulate_bearings
from .matching import MIN_DEPTH_M, match_landmarks
from .stereo import StereoProcessor

MIN_FRAME_INTERVAL_S = 1e-3  # frames closer in time are judged as if this far apart


@dataclass
class _WindowKeyframe:
    """A keyframe inside the local map; pose and landmarks still being refined."""

    id: int
    frame: StereoFrame  # as measured, less the current disparity offset estimate
    T_cam_world: np.ndarray
    landmark_ids: np.ndarray  # (N,) landmark of each feature, -1 if none
    edge_covariance: np.ndarray
    edge_inliers: int
    raw: StereoFrame  # as measured


@dataclass(frozen=True)
class _Track:
    """A frame tracked against the local map: its ``T_cam_world`` with 6x6 covariance, the inlier landmark
    ids with the frame's features that observe them, and the number of candidate matches."""

    T_cam_world: np.ndarray
    covariance: np.ndarray
    landmarks: np.ndarray
    features: np.ndarray
    matches: int


class LocalMap:
    """The last keyframes and the landmarks they observe, positions in the world (first camera) frame."""

    def __init__(self, size: int):
        self.size = size
        self.keyframes: deque[_WindowKeyframe] = deque()
        self.positions = np.zeros((0, 3))
        self.descriptors = np.zeros((0, 32), np.uint8)
        self.refined = np.zeros(0, bool)  # position set by a windowed bundle adjustment (else triangulated)

    def add_landmarks(self, points_world: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
        ids = np.arange(len(self.positions), len(self.positions) + len(points_world))
        self.positions = np.concatenate([self.positions, points_world])
        self.descriptors = np.concatenate([self.descriptors, descriptors])
        self.refined = np.concatenate([self.refined, np.zeros(len(points_world), bool)])
        return ids

    def active(self) -> np.ndarray:
        """Ids of landmarks observed by a keyframe in the window."""
        if not self.keyframes:
            return np.zeros(0, int)
        ids = np.concatenate([kf.landmark_ids for kf in self.keyframes])
        return np.unique(ids[ids >= 0])

    def compact(self) -> None:
        """Drop landmarks no keyframe in the window observes (keeps memory flat)."""
        keep = self.active()
        remap = -np.ones(len(self.positions), int)
        remap[keep] = np.arange(len(keep))
        self.positions, self.descriptors = self.positions[keep], self.descriptors[keep]
        self.refined = self.refined[keep]
        for kf in self.keyframes:
            ok = kf.landmark_ids >= 0
            kf.landmark_ids[ok] = remap[kf.landmark_ids[ok]]


@dataclass(frozen=True)
class OdometrySettings:
    """What :class:`StereoOdometry` is built from: its sections of the configuration (each checked when built)
    and the run's RANSAC seed (``run.seed``)."""

    odometry: OdometryConfig = dataclasses.field(default_factory=OdometryConfig)
    features: FeatureConfig = dataclasses.field(default_factory=FeatureConfig)
    stereo: StereoConfig = dataclasses.field(default_factory=StereoConfig)
    estimation: EstimationConfig = dataclasses.field(default_factory=EstimationConfig)
    seed: int = 0

    @classmethod
    def of(cls, config: Config) -> OdometrySettings:
        """The odometry's sections of ``config``."""
        return cls(config.odometry, config.features, config.stereo, config.estimation, config.run.seed)


class StereoOdometry:
    """Keyframe stereo visual odometry; feed frames in time order with ``process``."""

    def __init__(self, camera: StereoCamera, settings: OdometrySettings | None = None, keep_history: bool = True):
        """``settings``: the odometry's sections (defaults without it; ``OdometrySettings.of(config)`` from a whole
        ``Config``). ``keep_history`` keeps every frame's place for :meth:`final_poses`; teach and repeat, which
        store keyframes as they are finalized, turn it off so memory does not grow with the route."""
        self.config = settings or OdometrySettings()
        self.keep_history = keep_history
        self.skipped_window_adjustments = 0  # window adjustments not run (a landmark behind a camera)
        self.camera = camera
        self.timer = StageTimer()
        self.stereo = StereoProcessor(camera, self.config.features, self.config.stereo, self.timer)
        self.map = LocalMap(self.config.odometry.window_keyframes)
        self._next_id = 0
        self._T_cw_last: np.ndarray | None = None  # last frame's T_cam_world
        self._t_last = 0
        self._velocity: np.ndarray | None = None  # twist per second of T_cur_prev ([rot, trans])
        self._keyframe_poses: dict[int, np.ndarray] = {}  # id -> T_world_kf (latest estimate)
        self._frame_refs: list[tuple[int, np.ndarray]] = []
        self.disparity_offset = (
            DisparityOffsetEstimator(camera, self.config.odometry, self.config.stereo.pixel_sigma)
            if self.config.odometry.disparity_offset == "online"
            else None
        )

    @property
    def disparity_offset_px(self) -> float:
        """The disparity offset removed from every measured disparity now (0 without the online estimate)."""
        return 0.0 if self.disparity_offset is None else self.disparity_offset.offset_px

    def _corrected(self, frame: StereoFrame) -> StereoFrame:
        return corrected(frame, self.camera, self.disparity_offset_px, self.config.stereo.min_disparity_px)

    def process(self, images: StereoImages) -> OdometryResult:
        """Stereo-process a rectified pair, then track it (``process_frame``)."""
        return self.process_frame(self.stereo.process(images))

    def process_frame(self, frame: StereoFrame) -> OdometryResult:
        """Track one stereo frame against the local map; returns what happened to it."""
        cfg = self.config.odometry
        raw, frame = frame, self._corrected(frame)
        if self._T_cw_last is None:
            return self._start(frame, raw)
        ref = self.map.keyframes[-1]
        dt = (frame.t_ns - self._t_last) * 1e-9
        T_pred = self._T_cw_last if self._velocity is None else exp_se3(self._velocity * dt) @ self._T_cw_last
        radius = cfg.match_radius_px if self._velocity is not None else cfg.match_radius_no_prior_px
        est = self._track(frame, T_pred, radius)
        if est is None and radius < cfg.match_radius_no_prior_px:
            est = self._track(frame, T_pred, cfg.match_radius_no_prior_px)
        if est is not None and not self._plausible(est.T_cam_world, dt):
            est = None
        if est is None:
            return self._fail(frame, raw, T_pred, ref)
        T_cw, cov, n_matches = est.T_cam_world, est.covariance, est.matches
        n_inliers = len(est.landmarks)
        T_step = T_cw @ inv_T(self._T_cw_last)
        if dt > 0:
            self._velocity = log_se3(T_step) / dt
        self._T_cw_last, self._t_last = T_cw, frame.t_ns
        T_world_frame = inv_T(T_cw)
        T_kf_frame = ref.T_cam_world @ T_world_frame
        trans = np.linalg.norm(T_kf_frame[:3, 3])
        rot = np.degrees(rotation_angle(T_kf_frame[:3, :3]))
        new_kf, finalized = None, ()
        if (
            trans > cfg.keyframe_translation_m
            or rot > cfg.keyframe_rotation_deg
            or n_inliers < cfg.keyframe_min_inliers
        ):
            new_kf, finalized = self._add_keyframe(frame, raw, T_cw, cov, n_inliers, est.landmarks, est.features)
            kind = FrameKind.CREATE_VERTEX
            T_world_frame = self._keyframe_poses[new_kf.id]
            T_kf_frame = ref.T_cam_world @ T_world_frame  # ref may have just left the window
        else:
            moved = (
                np.linalg.norm(T_step[:3, 3]) > cfg.still_translation_m
                or np.degrees(rotation_angle(T_step[:3, :3])) > cfg.still_rotation_deg
            )
            kind = FrameKind.CREATE_CANDIDATE if moved else FrameKind.DO_NOTHING
        self._remember(new_kf.id if new_kf else ref.id, np.eye(4) if new_kf else T_kf_frame)
        return OdometryResult(
            t_ns=frame.t_ns,
            index=frame.index,
            kind=kind,
            matches=n_matches,
            inliers=n_inliers,
            keyframe_id=ref.id,
            T_keyframe_frame=T_kf_frame,
            T_world_frame=T_world_frame,
            covariance=cov,
            new_keyframe=new_kf,
            finalized=finalized,
        )

    def window_poses(self) -> dict[int, np.ndarray]:
        """Current ``T_world_kf`` (copies) of the keyframes in the window, by keyframe id: later keyframes' bundle
        adjustments move them, so relative odometry between two window keyframes is read from here."""
        return {kf.id: self._keyframe_poses[kf.id].copy() for kf in self.map.keyframes}

    def flush(self) -> list[Keyframe]:
        """Finalize every keyframe still in the window (call at the end of a run)."""
        out = []
        while self.map.keyframes:
            out.append(self._finalize(self.map.keyframes.popleft()))
        return out

    def final_poses(self) -> np.ndarray:
        """Poses (N, 4, 4) of every frame processed (in order), in the first camera frame, with
        keyframes as refined by the windowed bundle adjustment."""
        if not self.keep_history:
            raise ConfigError("final_poses: this odometry was created with keep_history=False")
        return np.array([self._keyframe_poses[k] @ T for k, T in self._frame_refs]).reshape(-1, 4, 4)

    def _remember(self, keyframe_id: int, T_kf_frame: np.ndarray) -> None:
        if self.keep_history:
            self._frame_refs.append((keyframe_id, T_kf_frame))

    def _take_id(self) -> int:
        self._next_id += 1
        return self._next_id - 1

    def _start(
        self,
        frame: StereoFrame,
        raw: StereoFrame,
        T_cw: np.ndarray | None = None,
        covariance: np.ndarray | None = None,
    ) -> OdometryResult:
        T_cw = np.eye(4) if T_cw is None else T_cw
        kf = self._new_window_keyframe(
            frame,
            raw,
            T_cw,
            covariance if covariance is not None else np.zeros((6, 6)),
            0,
            np.zeros(0, int),
            np.zeros(0, int),
        )
        self._T_cw_last, self._t_last = T_cw, frame.t_ns
        self._remember(kf.id, np.eye(4))
        new = self._public(kf)
        return OdometryResult(
            t_ns=frame.t_ns,
            index=frame.index,
            kind=FrameKind.CREATE_VERTEX,
            matches=0,
            inliers=0,
            keyframe_id=kf.id,
            T_keyframe_frame=np.eye(4),
            T_world_frame=inv_T(T_cw),
            covariance=kf.edge_covariance,
            new_keyframe=new,
        )

    def _new_window_keyframe(
        self,
        frame: StereoFrame,
        raw: StereoFrame,
        T_cw: np.ndarray,
        cov: np.ndarray,
        inliers: int,
        lm_ids: np.ndarray,
        feat_idx: np.ndarray,
    ) -> _WindowKeyframe:
        """Register a keyframe: matched features keep their landmarks, other stereo features start new ones."""
        ids = -np.ones(len(frame.features), int)
        ids[feat_idx] = lm_ids
        self.map.descriptors[lm_ids] = frame.features.descriptors[feat_idx]
        fresh = np.flatnonzero((ids < 0) & frame.has_depth)
        T_wc = inv_T(T_cw)
        ids[fresh] = self.map.add_landmarks(
            frame.points[fresh] @ T_wc[:3, :3].T + T_wc[:3, 3], frame.features.descriptors[fresh]
        )
        kf = _WindowKeyframe(self._take_id(), frame, T_cw, ids, cov, inliers, raw)
        self.map.keyframes.append(kf)
        self._keyframe_poses[kf.id] = T_wc
        return kf

    def _add_keyframe(self, frame, raw, T_cw, cov, inliers, lm_ids, feat_idx):
        kf = self._new_window_keyframe(frame, raw, T_cw, cov, inliers, lm_ids, feat_idx)
        with self.timer("window_ba"):
            self._bundle_adjust()
        finalized = []
        while len(self.map.keyframes) > self.map.size:
            finalized.append(self._finalize(self.map.keyframes.popleft()))
        if finalized:
            self.map.compact()
        self._T_cw_last = kf.T_cam_world
        return self._public(kf), tuple(finalized)

    def _public(self, kf: _WindowKeyframe) -> Keyframe:
        """The keyframe as the map takes it: its edge covariance made usable (an estimate without
        information, e.g. the zeros of a run's first keyframe, becomes ``odometry.failure_variance * I``)."""
        C = usable_covariance(kf.edge_covariance, self.config.odometry.failure_variance)
        return Keyframe(kf.id, self._refined_frame(kf), self._keyframe_poses[kf.id], C, kf.edge_inliers)

    def _refined_frame(self, kf: _WindowKeyframe) -> StereoFrame:
        """The keyframe's stereo frame with its landmarks where the windowed bundle adjustment put them
        (a far landmark's depth then rests on the parallax of the window, not on one small disparity)."""
        f = np.flatnonzero((kf.landmark_ids >= 0) & kf.frame.has_depth)
        f = f[self.map.refined[kf.landmark_ids[f]]]
        if len(f) == 0:
            return kf.frame
        points = kf.frame.points.copy()
        points[f] = self.map.positions[kf.landmark_ids[f]] @ kf.T_cam_world[:3, :3].T + kf.T_cam_world[:3, 3]
        return dataclasses.replace(kf.frame, points=points)

    def _finalize(self, kf: _WindowKeyframe) -> Keyframe:
        """A keyframe leaving the window: its pose is final."""
        out = self._public(kf)
        if not self.keep_history:
            del self._keyframe_poses[kf.id]
        return out

    def _window_observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every landmark observation in the window: (pose slot, landmark id, feature index, z (M, 3))."""
        kfs = list(self.map.keyframes)
        feats = [np.flatnonzero(kf.landmark_ids >= 0) for kf in kfs]
        slot = np.concatenate([np.full(len(f), s) for s, f in enumerate(feats)])
        lm = np.concatenate([kf.landmark_ids[f] for kf, f in zip(kfs, feats, strict=True)])
        z = np.concatenate([kf.frame.stereo_measurements[f] for kf, f in zip(kfs, feats, strict=True)])
        return slot, lm, np.concatenate(feats), z

    def _row_weights(self, z: np.ndarray) -> np.ndarray:
        """Weights of (u_l, v, u_r): see :func:`stereo_row_weights` (far landmarks: rotation and parallax)."""
        return odometry_row_weights(z, self.camera, self.config.estimation)

    def _bundle_adjust(self) -> None:
        """Windowed bundle adjustment: oldest keyframe fixed, the others and their landmarks free.

        Landmarks seen by >= 2 window keyframes take part. A far one (no near observation) first moves
        to where the parallax of the window puts it, so the adjustment starts from the depth the
        images support rather than from one small disparity. At most ``window_max_landmarks`` are
        adjusted: first those with a near observation (they carry the scale), then the longest tracks.
        """
        cfg = self.config.odometry
        kfs = list(self.map.keyframes)
        if len(kfs) < 2:
            return
        slot, lm, feat, z = self._window_observations()
        seen = np.bincount(lm, minlength=len(self.map.positions))
        keep = seen[lm] >= 2
        slot, lm, feat, z = slot[keep], lm[keep], feat[keep], z[keep]
        if len(lm) == 0:
            return
        weights = self._row_weights(z)
        T = np.stack([kf.T_cam_world for kf in kfs])
        uniq, lm_local = np.unique(lm, return_inverse=True)
        near = np.zeros(len(uniq), bool)
        np.logical_or.at(near, lm_local, weights[:, 2] == 1.0)
        if len(uniq) > cfg.window_max_landmarks:
            # ties broken by id (deterministic)
            order = np.lexsort((uniq, -seen[uniq], ~near))[: cfg.window_max_landmarks]
            selected = np.zeros(len(uniq), bool)
            selected[order] = True
            keep = selected[lm_local]
            slot, lm, feat, z, weights = slot[keep], lm[keep], feat[keep], z[keep], weights[keep]
            near = near[selected]
            uniq, lm_local = np.unique(lm, return_inverse=True)
        self._place_far_by_parallax(T, slot, lm_local, z, uniq, near)
        fixed = np.zeros(len(kfs), bool)
        fixed[0] = True
        try:
            res = bundle_adjust(
                T,
                fixed,
                self.map.positions[uniq],
                slot,
                lm_local,
                np.nan_to_num(z),
                weights,
                self.camera,
                self.config.stereo.pixel_sigma,
                self.config.estimation.huber_px,
                cfg.window_iterations,
            )
        except EstimationError:  # a landmark behind a camera: the window keeps its tracked poses (counted)
            self.skipped_window_adjustments += 1
            return
        for s, kf in enumerate(kfs):
            kf.T_cam_world = res.T_cam_world[s]
            self._keyframe_poses[kf.id] = inv_T(kf.T_cam_world)
        self.map.positions[uniq] = res.points
        self.map.refined[uniq] = True
        # observations that no longer fit are detached from their landmark
        bad = res.error_sq > cfg.ransac_threshold_px**2
        for s in np.unique(slot[bad]):
            kfs[s].landmark_ids[feat[bad & (slot == s)]] = -1
        self._update_disparity_offset(res.T_cam_world, slot[~bad], lm_local[~bad], feat[~bad], len(uniq))

    def _update_disparity_offset(
        self, T_cam_world: np.ndarray, slot: np.ndarray, lm_local: np.ndarray, feat: np.ndarray, n_points: int
    ) -> None:
        """Feed the window's newest keyframe to the disparity offset estimate (raw measurements); when the offset to
        remove changes, the window's keyframes are measured again with it."""
        if self.disparity_offset is None:
            return
        kfs = list(self.map.keyframes)
        z_raw = np.concatenate([kfs[s].raw.stereo_measurements[feat[slot == s]] for s in range(len(kfs))])
        order = np.argsort(slot, kind="stable")  # z_raw is grouped by slot
        before = self.disparity_offset.offset_px
        z = np.empty_like(z_raw)
        z[order] = z_raw
        after = self.disparity_offset.add_window(T_cam_world, slot, lm_local, z, n_points)
        if after != before:
            for kf in kfs:
                kf.frame = self._corrected(kf.raw)

    def _place_far_by_parallax(
        self,
        T_cam_world: np.ndarray,
        slot: np.ndarray,
        lm_local: np.ndarray,
        z: np.ndarray,
        uniq: np.ndarray,
        near: np.ndarray,
    ) -> None:
        """Far landmarks ``uniq[~near]`` whose window rays span at least ``far_min_parallax_deg`` start at the
        point their left-image rays meet (when in front of every camera that saw them)."""
        tri, parallax = triangulate_bearings(T_cam_world, slot, lm_local, z[:, :2], self.camera, len(uniq))
        depth = np.einsum("mj,mj->m", T_cam_world[slot, 2, :3], np.nan_to_num(tri[lm_local])) + T_cam_world[slot, 2, 3]
        in_front = np.ones(len(uniq), bool)
        np.logical_and.at(in_front, lm_local, depth > MIN_DEPTH_M)
        use = (
            ~near
            & in_front
            & np.isfinite(tri).all(1)
            & (parallax >= np.radians(self.config.odometry.far_min_parallax_deg))
        )
        self.map.positions[uniq[use]] = tri[use]

    def _plausible(self, T_cw: np.ndarray, dt: float) -> bool:
        """Speed and rotation rate of the step since the last frame within the configured bounds."""
        cfg = self.config.odometry
        step = T_cw @ inv_T(cast(np.ndarray, self._T_cw_last))
        dt = max(dt, MIN_FRAME_INTERVAL_S)
        return bool(
            np.linalg.norm(step[:3, 3]) <= cfg.max_speed_mps * dt
            and np.degrees(rotation_angle(step[:3, :3])) <= cfg.max_rotation_rate_dps * dt
        )

    def _fail(self, frame: StereoFrame, raw: StereoFrame, T_pred: np.ndarray, ref: _WindowKeyframe) -> OdometryResult:
        """No reliable estimate: carry the pose by the motion prior and restart the local map here."""
        finalized = tuple(self.flush())
        self.map = LocalMap(self.config.odometry.window_keyframes)
        unknown = np.eye(6) * self.config.odometry.failure_variance
        res = self._start(frame, raw, T_pred, unknown)
        T_kf_frame = ref.T_cam_world @ inv_T(T_pred)
        return OdometryResult(
            t_ns=frame.t_ns,
            index=frame.index,
            kind=FrameKind.FAILURE,
            matches=0,
            inliers=0,
            keyframe_id=ref.id,
            T_keyframe_frame=T_kf_frame,
            T_world_frame=res.T_world_frame,
            covariance=unknown,
            new_keyframe=res.new_keyframe,
            finalized=finalized,
        )

    def _track(self, frame: StereoFrame, T_pred: np.ndarray, radius: float) -> _Track | None:
        """Match to the local map, RANSAC, refine ``T_cam_world``; None when too few inliers."""
        cfg: OdometryConfig = self.config.odometry
        with self.timer("matching"):
            active = self.map.active()
            lm, feat = match_landmarks(
                self.map.positions[active],
                self.map.descriptors[active],
                frame,
                T_pred,
                self.camera,
                radius,
                cfg.max_descriptor_distance,
                self.config.estimation.ratio_test,
            )
            lm = active[lm]
        if len(lm) < cfg.min_inliers:
            return None
        with self.timer("estimation"):
            return self._estimate(frame, lm, feat)

    def _estimate(self, frame: StereoFrame, lm: np.ndarray, feat: np.ndarray) -> _Track | None:
        """RANSAC then pose refinement on the matched landmarks (see ``_track``).

        RANSAC's model rests on its best minimal sample; on a scene of mostly far structure its translation can be
        off by decimetres (far landmarks barely constrain it), which puts the near landmarks, the ones that carry
        the scale, outside the threshold. So the inliers are chosen again among all matches at the refined pose,
        and the pose refined again, until the set no longer changes (at most ``odometry.inlier_rounds`` rounds):
        the inlier set is that of the refined pose, not of a random sample.
        """
        cfg = self.config.odometry
        order = self._ransac_order(len(lm), frame.index)
        rs = ransac_pnp(
            self.map.positions[lm[order]],
            frame.features.uv[feat[order]],
            self.camera,
            cfg.ransac_iterations,
            cfg.ransac_threshold_px,
            self.config.estimation.ransac_confidence,
            self.config.seed,
        )
        if rs is None or len(rs.inliers) < cfg.min_inliers:
            return None
        z = frame.stereo_measurements[feat]
        inlier = np.zeros(len(lm), bool)
        inlier[order[rs.inliers]] = True
        inlier &= self.map.positions[lm] @ rs.T_q_r[2, :3] + rs.T_q_r[2, 3] > MIN_DEPTH_M
        T_cw = rs.T_q_r
        points = self.map.positions[lm]
        for round_ in range(cfg.inlier_rounds):
            res, ok = self._refine_pose(T_cw, lm[inlier], z[inlier], points[inlier])
            T_cw = res.T_cam_world[-1]
            if round_ == cfg.inlier_rounds - 1:
                break
            points = points.copy()
            points[inlier] = res.points
            again = self._fits(T_cw, points, z) & (self.map.positions[lm] @ T_cw[2, :3] + T_cw[2, 3] > MIN_DEPTH_M)
            if np.array_equal(again, inlier) or again.sum() < cfg.min_inliers:
                break
            inlier = again
        if ok.sum() < cfg.min_inliers:
            return None
        lm_in, feat_in = lm[inlier][ok], feat[inlier][ok]
        return _Track(res.T_cam_world[-1], res.pose_covariance[-1], lm_in, feat_in, len(lm))

    def _ransac_order(self, n: int, frame_index: int) -> np.ndarray:
        """The order in which RANSAC sees a frame's ``n`` correspondences. OpenCV's RANSAC draws its samples from a
        generator of its own with a fixed seed (``cv2.setRNGSeed`` does not reach it), so its samples depend only on
        the correspondences and their order: ``run.seed`` 0 keeps the matching order, another seed shuffles it
        by (seed, frame index), so a run is reproducible from its seed and different seeds draw different samples."""
        seed = self.config.seed
        if seed == 0:
            return np.arange(n)
        return np.random.default_rng((seed, frame_index)).permutation(n)

    def _fits(self, T_cam_world: np.ndarray, points_world: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Which landmarks (world points) project at ``T_cam_world`` within the RANSAC threshold of their stereo
        measurements ``z`` (rows that were measured), in front of the camera."""
        P = points_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        in_front = P[:, 2] > MIN_DEPTH_M
        err = np.where(np.isfinite(z), self.camera.project(np.where(in_front[:, None], P, 1.0)) - z, 0.0)
        return in_front & ((err**2).sum(1) <= self.config.odometry.ransac_threshold_px**2)

    def _refine_pose(self, T_cam_world: np.ndarray, lm: np.ndarray, z: np.ndarray, points_world: np.ndarray):
        """Refine the new frame's ``T_cam_world`` from its measurements ``z`` of landmarks ``lm`` (starting at
        ``points_world``, where the map or the previous inlier round has them).

        The landmarks are not held fixed at their current estimate: they stay free, constrained by
        their observations in the window keyframes (poses held), so a far landmark's uncertain depth
        moves with the evidence instead of dragging the translation. Returns the bundle result (the
        new frame is the last pose) and the per-landmark inlier mask.
        """
        cfg = self.config.odometry
        kfs = list(self.map.keyframes)
        n = len(lm)
        slot, lm_obs, _, z_obs = self._window_observations()
        local = -np.ones(len(self.map.positions), int)
        local[lm] = np.arange(n)
        keep = local[lm_obs] >= 0
        K = len(kfs)
        obs_pose = np.r_[slot[keep], np.full(n, K)]
        obs_point = np.r_[local[lm_obs[keep]], np.arange(n)]
        z_all = np.concatenate([z_obs[keep], z])
        T = np.concatenate([np.stack([kf.T_cam_world for kf in kfs]), T_cam_world[None]])
        fixed = np.r_[np.ones(K, bool), False]
        res = bundle_adjust(
            T,
            fixed,
            points_world,
            obs_pose,
            obs_point,
            np.nan_to_num(z_all),
            self._row_weights(z_all),
            self.camera,
            self.config.stereo.pixel_sigma,
            self.config.estimation.huber_px,
            self.config.estimation.refine_iterations,
        )
        return res, res.error_sq[-n:] <= cfg.ransac_threshold_px**2
