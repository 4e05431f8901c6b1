"""Localization of one repeat keyframe (leaf) against a taught submap: matching, robust estimation and the
checks an estimate must pass before it may count (docs/localization.md). The chain that decides which taught
vertex a leaf is localized against, and what a localization is worth, is :mod:`vtr.navigation.chain`.

Poses are of the left rectified camera; ``T_leaf_trunk`` maps trunk-camera coordinates into the leaf camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from perception_model.angles import parallax_angle, view_angle
from perception_model.landmarks_file import Observations
from perception_model.records import short_repr

from ..camera import MIN_DEPTH_M, StereoCamera
from ..config import EstimationConfig, LocalizationConfig
from ..geometry import inv_T
from ..map.records import RUN_SHIFT
from ..timing import StageTimer
from ..types import StereoFrame
from ..vo.estimation import odometry_row_weights, ransac_pnp
from ..vo.features import match_all
from ..vo.matching import match_landmarks
from .leaf_adjustment import LeafAdjustment, adjust_leaf, leaf_pose_jackknife


class LocalizationStatus(StrEnum):
    """Outcome of one localization attempt, as ``localization.csv``'s ``status`` column says it."""

    LOCALIZED = "localized"  # a success: consistent, and (when searching) confirmed
    UNCONFIRMED = "unconfirmed"  # verified against a place candidate, waiting for the next keyframe
    NO_CANDIDATES = "no_candidates"  # place recognition found no taught vertex that verified
    TOO_FEW_MATCHES = "too_few_matches"  # fewer candidate matches than localization.min_matches
    TOO_FEW_INLIERS = "too_few_inliers"  # fewer inliers than localization.min_inliers (or _unlocalized)
    LOW_INLIER_RATIO = "low_inlier_ratio"  # inliers / matches below localization.min_inlier_ratio
    RESIDUALS = "residuals_inconsistent"  # inlier residuals do not fit the pixel noise model
    INCONSISTENT = "inconsistent_with_odometry"  # outside the innovation gate of the odometry-propagated prior
    OFF_ROUTE = "off_route"  # beyond either end of the taught route


@dataclass(frozen=True)
class Localization:
    """One localization attempt of leaf ``leaf_id`` against trunk ``trunk_id``.

    ``T_leaf_trunk`` maps trunk-camera coordinates into the leaf camera (the prior on failure) and
    ``covariance`` is its 6x6 covariance ([rot, trans]). ``twig_id``/``branch_id`` are the chain's
    twig and branch *before* this attempt (-1 before the first success). ``landmarks`` holds the
    taught landmarks in the leaf's view as the ``landmarks.csv`` record (``perception_model``'s
    ``Observations``: one row per landmark, angles in radians), written as is by ``vtr repeat``.
    ``status`` says why an attempt failed; ``direction`` is the chain's direction of travel along the
    taught path after this attempt; ``experiences`` the earlier repeats whose landmarks gave a success inliers
    besides the teach's (docs/map.md, "Experiences").
    """

    t_ns: int
    leaf_id: int
    trunk_id: int
    twig_id: int
    branch_id: int
    success: bool
    matches: int
    inliers: int
    T_leaf_trunk: np.ndarray
    covariance: np.ndarray
    consecutive_failures: int
    distance_since_success_m: float
    landmarks: Observations | None = None
    status: LocalizationStatus = LocalizationStatus.LOCALIZED
    direction: int = 1  # +1 the route travelled as taught, -1 backward, 0 not yet decided
    experiences: tuple[int, ...] = ()  # the experiences (repeat runs) that gave this success inliers
    # the part of ``covariance`` that is the map's own placement (taught vertices, experiences): shared by the
    # leaves localized against the same vertices, not independent between them (LocalizationEstimate)
    frame_covariance: np.ndarray | None = None

    __repr__ = short_repr  # arrays by shape: print(repeat.latest) stays short


#: a stored landmark whose depth differs from its own triangulation by more than this disparity was refined
REFINED_DISPARITY_TOLERANCE_PX = 1e-6


def refined_landmarks(z: np.ndarray, depth_m: np.ndarray, camera: StereoCamera) -> np.ndarray:
    """Which landmarks of a stored or keyframe stereo frame sit where odometry's window put them: their depth is
    not their own triangulation ``fb / (u_l - u_r)`` (measurements ``z`` (N, 3), depths (N,))."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(z[:, 0] - z[:, 2] - camera.fb / depth_m) > REFINED_DISPARITY_TOLERANCE_PX


@dataclass(frozen=True)
class TaughtSubmap:
    """The landmarks a leaf is localized against: the trunk's and those of its taught neighbours.

    VT&R3 localizes against a window of taught vertices rather than one stereo frame, so a leaf's
    pose does not inherit one stereo pair's depth errors. Vertex ``s`` (of ``vertex_ids``) sits at
    ``T_vertex_trunk[s]`` along the privileged path; ``trunk_slot`` is the trunk's slot. Per landmark
    (arrays of equal length): its position in the trunk camera frame (as the teach's windowed bundle
    adjustment left it), descriptor, the slot of the vertex that observed it, that vertex's stereo
    measurement (u_l, v, u_r) and the feature index in that vertex.
    """

    vertex_ids: np.ndarray
    T_vertex_trunk: np.ndarray
    trunk_slot: int
    points_trunk: np.ndarray
    descriptors: np.ndarray
    slot: np.ndarray
    z: np.ndarray
    feature: np.ndarray
    depth_m: np.ndarray
    refined: np.ndarray

    @classmethod
    def build(
        cls,
        frames: list[StereoFrame],
        vertex_ids: np.ndarray,
        T_vertex_trunk: np.ndarray,
        trunk_slot: int,
        camera: StereoCamera,
    ) -> TaughtSubmap:
        """From the vertices' stereo frames (landmarks with depth) and their poses relative to the trunk.

        A vertex stores each landmark where odometry's windowed bundle adjustment left it, or, when the
        window did not refine it, its own triangulation (depth exactly fb / disparity): ``refined`` tells
        them apart and ``depth_m`` is the stored depth in the observing vertex.
        """
        feats = [np.flatnonzero(f.has_depth) for f in frames]
        T_trunk_vertex = inv_T(np.asarray(T_vertex_trunk))
        points = np.concatenate(
            [f.points[i] @ T[:3, :3].T + T[:3, 3] for f, i, T in zip(frames, feats, T_trunk_vertex, strict=True)]
        )
        z = np.concatenate([f.stereo_measurements[i] for f, i in zip(frames, feats, strict=True)])
        depth = np.concatenate([f.points[i, 2] for f, i in zip(frames, feats, strict=True)])
        refined = refined_landmarks(z, depth, camera)
        return cls(
            np.asarray(vertex_ids),
            np.asarray(T_vertex_trunk),
            trunk_slot,
            points,
            np.concatenate([f.features.descriptors[i] for f, i in zip(frames, feats, strict=True)]),
            np.concatenate([np.full(len(i), s) for s, i in enumerate(feats)]),
            z,
            np.concatenate(feats),
            depth,
            refined,
        )

    @classmethod
    def of_frame(cls, frame: StereoFrame, camera: StereoCamera, vertex_id: int = 0) -> TaughtSubmap:
        """A submap of one stereo frame (a single taught view)."""
        return cls.build([frame], np.array([vertex_id]), np.eye(4)[None], 0, camera)

    @property
    def experience(self) -> np.ndarray:
        """(M,) int64: per landmark the map run (experience) of the vertex that observed it: the teach run for
        taught landmarks, a repeat run for an experience's (:mod:`vtr.navigation.experiences`)."""
        return np.asarray(self.vertex_ids, np.int64)[self.slot] >> RUN_SHIFT

    def trunk_features(self, landmarks: np.ndarray) -> np.ndarray:
        """Feature indices in the trunk vertex of those of ``landmarks`` that the trunk observed."""
        landmarks = np.asarray(landmarks, int)
        return self.feature[landmarks[self.slot[landmarks] == self.trunk_slot]]


@dataclass(frozen=True)
class LocalizationEstimate:
    """What the localizer found: ``T_leaf_trunk`` (None on failure) with its 6x6 covariance, the number of
    candidate matches, the matched submap landmarks and which of them are inliers."""

    T_leaf_trunk: np.ndarray | None
    covariance: np.ndarray
    matches: int
    matched: np.ndarray
    inlier: np.ndarray
    status: LocalizationStatus = LocalizationStatus.LOCALIZED
    median_residual_px: float = float("nan")  # median reprojection error of the inliers (worse of the two views)
    # the part of ``covariance`` the map's own placement adds (vtr.navigation.experiences.taught_covariance and
    # experience_covariance): an error of the frame the leaf is localized in, which consecutive leaves localized
    # against the same vertices share; None: none added
    frame_covariance: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.T_leaf_trunk is not None

    @property
    def inliers(self) -> int:
        return int(self.inlier.sum())

    @classmethod
    def failed(
        cls,
        matched: np.ndarray,
        status: LocalizationStatus,
        inlier: np.ndarray | None = None,
        median_residual_px: float = float("nan"),
    ) -> LocalizationEstimate:
        return cls(
            None,
            np.full((6, 6), np.nan),
            len(matched),
            matched,
            np.zeros(len(matched), bool) if inlier is None else inlier,
            status,
            median_residual_px,
        )


class Localizer:
    """Matches a leaf's features to a taught submap's landmarks and estimates ``T_leaf_trunk``."""

    def __init__(
        self,
        camera: StereoCamera,
        config: LocalizationConfig,
        estimation: EstimationConfig,
        pixel_sigma: float,
        timer: StageTimer | None = None,
    ):
        self.camera = camera
        self.config = config
        self.estimation = estimation
        self.pixel_sigma = pixel_sigma
        # seconds in "match", "ransac" and "refine" (Repeat adds its submap reads, landmark records and spatial
        # edges): the split tools/bench_repeat.py prints
        self.timer = timer or StageTimer()

    def localize(
        self,
        leaf: StereoFrame,
        submap: TaughtSubmap,
        T_prior: np.ndarray | None,
        seed: int = 0,
        trusted_prior: bool = True,
        consecutive_failures: int = 0,
    ) -> LocalizationEstimate:
        """Estimate ``T_leaf_trunk``; ``T_prior`` None means no usable prior (unguided matching).

        Without a trusted prior (searching: the start, after a loss) a localization needs
        ``min_inliers_unlocalized`` inliers: unguided matches are far more often wrong. The search
        radius around the prior's prediction (``tracking_match_radius_px`` around the chain's own, trusted prior,
        ``match_radius_px`` around a place candidate's) grows with the failures since the last success, as the
        prior (odometry since then) grows less certain. An estimate is refused (with its reason) unless
        it has enough inliers, enough inliers per match, and inlier residuals that fit the pixel noise
        (median at most ``max_median_residual_px``); its covariance is the measurements' (:meth:`_pixel_covariance`:
        the jackknife over cells of the leaf's image). What the taught map's own placement adds is
        :func:`vtr.navigation.experiences.taught_covariance` (docs/localization.md, "What the covariance holds").
        """
        c = self.config
        min_inliers = c.min_inliers if trusted_prior else c.min_inliers_unlocalized
        base = c.tracking_match_radius_px if trusted_prior else c.match_radius_px  # the chain's own prior is tighter
        radius = min(base * c.match_radius_growth**consecutive_failures, c.max_match_radius_px)
        with self.timer("match"):
            li, lj = self._match(leaf, submap, T_prior, radius)
        if len(li) < c.min_matches:
            return LocalizationEstimate.failed(li, LocalizationStatus.TOO_FEW_MATCHES)
        with self.timer("ransac"):
            rs = ransac_pnp(
                submap.points_trunk[li],
                leaf.features.uv[lj],
                self.camera,
                c.ransac_iterations,
                c.ransac_threshold_px,
                self.estimation.ransac_confidence,
                seed,
            )
        if rs is None or len(rs.inliers) < min_inliers:
            return LocalizationEstimate.failed(li, LocalizationStatus.TOO_FEW_INLIERS)
        sel = rs.inliers
        depth = submap.points_trunk[li[sel]] @ rs.T_q_r[2, :3] + rs.T_q_r[2, 3]
        sel = sel[depth > MIN_DEPTH_M]
        with self.timer("refine"):
            T, cov, ok, err_sq, factor = self._refine(submap, li[sel], leaf.stereo_measurements[lj[sel]], rs.T_q_r)
        inlier = np.zeros(len(li), bool)
        inlier[sel[ok]] = True
        n_in = int(inlier.sum())
        median_px = float(np.sqrt(np.median(err_sq[ok]))) if n_in else float("nan")
        if n_in < min_inliers:
            return LocalizationEstimate.failed(li, LocalizationStatus.TOO_FEW_INLIERS, inlier, median_px)
        if n_in < c.min_inlier_ratio * len(li):
            return LocalizationEstimate.failed(li, LocalizationStatus.LOW_INLIER_RATIO, inlier, median_px)
        if not median_px <= c.max_median_residual_px:
            return LocalizationEstimate.failed(li, LocalizationStatus.RESIDUALS, inlier, median_px)
        # the pixel part (the image-block jackknife, or the adjustment's with its variance factor), times the scale
        cov = cov * c.covariance_scale
        return LocalizationEstimate(T, cov, len(li), li, inlier, LocalizationStatus.LOCALIZED, median_px)

    def _refine(
        self, submap: TaughtSubmap, landmarks: np.ndarray, z_leaf: np.ndarray, T_leaf_trunk: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """Stereo bundle adjustment of ``T_leaf_trunk`` with the matched landmarks free, each observed by its
        taught vertex (held where the taught path puts it) and by the leaf. Returns (T_leaf_trunk,
        covariance, inlier mask).

        The taught disparity of a landmark the teach window refined is the one its refined depth implies,
        at full weight: the depth the teach established from several views, not from one stereo pair. The
        other rows are weighted by :func:`stereo_row_weights` (a far landmark's own disparity barely counts).
        Only the taught side is anchored so: anchoring the leaf's far landmarks on the repeat window's
        depths too would turn the two windows' scale difference, times the depth, into translation.
        """
        o = self.estimation
        n = len(landmarks)
        z_taught = submap.z[landmarks].copy()
        w = self._row_weights(np.concatenate([z_taught, z_leaf]))
        refined = submap.refined[landmarks]
        z_taught[refined, 2] = z_taught[refined, 0] - self.camera.fb / submap.depth_m[landmarks[refined]]
        w[np.flatnonzero(refined), 2] = 1.0  # taught rows come first
        z = np.nan_to_num(np.concatenate([z_taught, z_leaf]))
        res = adjust_leaf(  # bundle_adjust of this one shape, in one compiled kernel
            submap.T_vertex_trunk,
            submap.slot[landmarks],
            T_leaf_trunk,
            submap.points_trunk[landmarks],
            z,
            w,
            self.camera,
            self.pixel_sigma,
            o.huber_px,
            o.refine_iterations,
        )
        err_sq = np.maximum(res.error_sq[:n], res.error_sq[n:])
        inlier = err_sq <= self.config.ransac_threshold_px**2
        # the a-posteriori variance factor: the robust cost (in units of the modelled noise) per degree of freedom,
        # the measured rows counted by their weight (a row of weight w adds w times its noise to the cost: a far
        # landmark's disparity at far_disparity_weight adds almost nothing) less the parameters fitted to them (3 per
        # landmark, 6 for the leaf); counting such rows whole read the noise variance 0.6 of itself on the KITTI clips
        dof = float(w.sum()) - 3 * n - 6
        factor = res.cost / dof if dof > 0 else float("inf")
        cov = self._pixel_covariance(res, submap, landmarks, z, w, factor, inlier)
        return res.T_leaf_trunk, cov, inlier, err_sq, factor

    def _pixel_covariance(
        self,
        res: LeafAdjustment,
        submap: TaughtSubmap,
        landmarks: np.ndarray,
        z: np.ndarray,
        w: np.ndarray,
        factor: float,
        inlier: np.ndarray,
    ) -> np.ndarray:
        """The covariance of the leaf pose from the measurements (:meth:`_refine`'s adjustment ``res``): the
        delete-one-block jackknife over cells of the leaf's image (``covariance_blocks`` per side; features that
        share a cell share their errors, which the adjustment's inverse Hessian with independent pixel noise does
        not see), or, with fewer than ``covariance_min_blocks`` cells holding inliers, the adjustment's covariance
        times its variance factor (docs/localization.md, "What the covariance holds")."""
        c, cam, n = self.config, self.camera, len(landmarks)
        iid = res.covariance * factor
        sel = np.flatnonzero(inlier)
        if c.covariance_blocks == 0 or len(sel) == 0:
            return iid
        uv = z[n + sel, :2]
        cells = np.clip((uv / [cam.width, cam.height] * c.covariance_blocks).astype(int), 0, c.covariance_blocks - 1)
        rows = np.concatenate([sel, n + sel])  # the inliers' taught rows, then their leaf rows (adjust_leaf's layout)
        jk, blocks = leaf_pose_jackknife(
            submap.T_vertex_trunk,
            submap.slot[landmarks[sel]],
            res.T_leaf_trunk,
            res.points[sel],
            z[rows],
            w[rows],
            cells[:, 0] * c.covariance_blocks + cells[:, 1],
            cam,
            self.pixel_sigma,
            self.estimation.huber_px,
        )
        return jk if blocks >= c.covariance_min_blocks else iid

    def _row_weights(self, z: np.ndarray) -> np.ndarray:
        return odometry_row_weights(z, self.camera, self.estimation)

    def _match(
        self, leaf: StereoFrame, submap: TaughtSubmap, T_prior: np.ndarray | None, radius: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Candidate matches (submap landmarks, leaf features). The trunk's landmarks are matched first and the
        neighbours' only to the leaf features left over, so the trunk's matches (those ``landmarks.csv``
        records for the perception model) are the ones a localization against the trunk alone would find."""
        trunk = np.flatnonzero(submap.slot == submap.trunk_slot)
        others = np.flatnonzero(submap.slot != submap.trunk_slot)
        li, lj = self._match_subset(leaf, submap, trunk, T_prior, radius)
        if len(others):
            lo, jo = self._match_subset(leaf, submap, others, T_prior, radius)
            fresh = ~np.isin(jo, lj)
            li, lj = np.r_[li, lo[fresh]], np.r_[lj, jo[fresh]]
        return li, lj

    def _match_subset(
        self, leaf: StereoFrame, submap: TaughtSubmap, subset: np.ndarray, T_prior: np.ndarray | None, radius: float
    ) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        if T_prior is not None:
            li, lj = match_landmarks(
                submap.points_trunk[subset],
                submap.descriptors[subset],
                leaf,
                T_prior,
                self.camera,
                radius,
                c.max_descriptor_distance,
                self.estimation.ratio_test,
            )
            if len(li) >= c.min_matches:
                return subset[li], lj
        # unguided: every taught landmark against every leaf feature, ratio test
        li, lj = match_all(
            submap.descriptors[subset],
            leaf.features.descriptors,
            c.max_descriptor_distance,
            ratio=self.estimation.ratio_test,
        )
        return subset[li], lj


def landmark_record(
    trunk: StereoFrame,
    T_leaf_trunk: np.ndarray,
    camera: StereoCamera,
    matched: np.ndarray,
    inlier: np.ndarray,
    *,
    t_ns: int,
    leaf_id: int,
    trunk_id: int,
) -> Observations:
    """Angles of every trunk landmark inside the leaf's image, as ``landmarks.csv`` rows; ``matched`` and
    ``inlier`` are the feature indices of the trunk's matched / inlier landmarks.

    Angles do not depend on the frame they are computed in, so the trunk camera frame stands in
    for the gravity-aligned frame o: ``p_is`` = landmark in the trunk frame, ``p_ao`` = leaf camera
    centre in the trunk frame, ``z`` = leaf optical axis in the trunk frame. ``landmark_id`` is the
    feature index in the trunk vertex; ``matched``/``inlier`` say whether it was matched / a
    localization inlier; ``range_m`` is the distance from the leaf camera.
    """

    idx = np.flatnonzero(trunk.has_depth)
    P_leaf = trunk.points[idx] @ T_leaf_trunk[:3, :3].T + T_leaf_trunk[:3, 3]
    in_view = camera.in_view(P_leaf)
    idx, P_leaf = idx[in_view], P_leaf[in_view]
    T_trunk_leaf = inv_T(T_leaf_trunk)
    p_is = trunk.points[idx]
    p_ao = T_trunk_leaf[:3, 3]
    z = T_trunk_leaf[:3, 2]
    is_matched = np.isin(idx, matched)
    is_inlier = np.isin(idx, inlier)
    n = len(idx)
    return Observations(
        alpha=parallax_angle(p_is, p_ao),
        theta=view_angle(p_is, p_ao, z),
        inlier=is_inlier,
        t_ns=np.full(n, t_ns, np.int64),
        leaf_id=np.full(n, leaf_id, np.int64),
        trunk_id=np.full(n, trunk_id, np.int64),
        landmark_id=idx.astype(np.int64),
        range_m=np.linalg.norm(P_leaf, axis=1),
        matched=is_matched,
    )
