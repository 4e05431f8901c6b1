"""Every section of the configuration, each default with its domain and its comment (units, what was measured):
``vtr config`` prints these comments. Defaults follow the open-source VT&R3 stack (docs/README.md); benchmarks
decide changes (docs/configuration.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from perception_model.settings import THESIS_C_BAR, THESIS_L_MIN

from .domains import Choice, Range, Section, setting

DESCRIPTOR_DISTANCE = Range(0, 256, integer=True)  # Hamming distance between 256-bit ORB descriptors
RADIUS_PX = Range(0.0, 10_000.0, lo_open=True)


MAX_PYRAMID_SCALE = 64.0  # largest scale_factor ** (n_levels - 1) (FeatureConfig.rules)


@dataclass(frozen=True)
class FeatureConfig(Section):
    """Detection and description (left and right images)."""

    SECTION: ClassVar[str] = "features"

    # features kept per image after grid bucketing; on the KITTI clip 2000 gave t_err 0.64-0.74 % over
    # five parameter variants against 0.74-0.90 % for 1500, for ~10 % more time per frame
    n_features: int = setting(2000, Range(1, 100_000, integer=True))
    detect_factor: float = setting(1.5, Range(1.0, 10.0))  # ORB detects this many times n_features before bucketing
    grid_rows: int = setting(8, Range(1, 256, integer=True))  # bucketing grid (cells keep their strongest features)
    grid_cols: int = setting(16, Range(1, 256, integer=True))
    scale_factor: float = setting(1.2, Range(1.0, 4.0, lo_open=True))  # ORB pyramid scale step
    # ORB pyramid levels (scale range 1.7: consecutive keyframes, repeats)
    n_levels: int = setting(4, Range(1, 16, integer=True))
    fast_threshold: int = setting(20, Range(1, 255, integer=True))  # FAST corner threshold (grey levels)
    edge_threshold: int = setting(19, Range(1, 127, integer=True))  # ORB border (px); also the patch half-size bound
    # ranking of FAST corners before bucketing: "fast" (FAST score, as ORB-SLAM's extractor) or "harris"
    # (OpenCV ORB's default). On the KITTI clip Harris ranking gave t_err 1.05-1.8 % over five parameter
    # variants against 0.67-0.90 % for the FAST score, which is also ~2 ms cheaper per image
    corner_score: str = setting("fast", Choice("fast", "harris"))
    # threads for one run's per-frame work (allowed: 0..1024; 0 = every core the process may use): with 2 or
    # more, a background thread decodes the frames and that many workers extract features and match stereo on
    # whole frames ahead of the tracking thread (vtr/vo/stereo.py, vtr/parallel.py; a repeat localizes on a thread
    # of its own with any value: localization.thread; docs/architecture.md "Threads inside one run"); a single
    # frame given to StereoProcessor.process has its left and right images' features extracted concurrently.
    # Results are bit-identical for every value (tests/vo/test_threads.py). KITTI 1226x370 odometry on 2 cores with 2
    # threads: 1.8-1.9x the frames/s of 1 thread (tools/bench_odometry.py). OpenCV's own pool
    # (cv2.setNumThreads) is left alone: ORB extraction runs serially inside OpenCV, and 1 or 2 OpenCV threads
    # measured the same; batch workers set it to this value
    threads: int = setting(0, Range(0, 1024, integer=True))
    # scheduling priority of those feature/stereo workers below the tracking thread's and the decoding reader's
    # (Linux niceness 0..19; ignored elsewhere): when every core is busy the frame being tracked goes first, the
    # workers' frames ahead after. KITTI odometry, 2 threads on 2 cores, best of 3, three rounds: niceness 0
    # 60.0-61.8 frames/s; 10 64.7-66.7 (the reader niced too: 63.3-65.7); 19 65.7-66.4
    worker_niceness: int = setting(10, Range(0, 19, integer=True))

    def rules(self) -> list[tuple[bool, str]]:
        # the top pyramid level is the image shrunk by scale_factor ** (n_levels - 1): beyond 64 it is a few
        # pixels of a KITTI image and OpenCV fails to build it (4 ** 5 = 1024: a raw cv2.error)
        top = self.scale_factor ** (self.n_levels - 1)
        return [
            (
                top <= MAX_PYRAMID_SCALE,
                f"features.scale_factor ** (features.n_levels - 1) = {self.scale_factor:g} ** {self.n_levels - 1} = "
                f"{top:.4g} must be at most {MAX_PYRAMID_SCALE} (the top pyramid level would be smaller than a few "
                f"pixels)",
            )
        ]


@dataclass(frozen=True)
class StereoConfig(Section):
    """Left-right matching on epipolar rows and triangulation."""

    SECTION: ClassVar[str] = "stereo"

    # |v_l - v_r| allowed at pyramid level 0 (scales with level)
    max_row_diff_px: float = setting(1.5, Range(0.0, 100.0))
    # smaller disparities are treated as unmatched (points at infinity)
    min_disparity_px: float = setting(0.5, Range(0.0, 10_000.0, lo_open=True))
    max_disparity_px: float = setting(160.0, Range(0.0, 10_000.0, lo_open=True))
    max_descriptor_distance: int = setting(64, DESCRIPTOR_DISTANCE)  # Hamming distance accepted between left and right
    refine_half_window: int = setting(5, Range(1, 32, integer=True))  # subpixel refinement: SAD patch half-size (px)
    # subpixel refinement: search +- this many px along the row
    refine_search_px: int = setting(3, Range(1, 64, integer=True))
    # measurement noise on u_l, v, u_r (px) used for covariances
    pixel_sigma: float = setting(1.0, Range(0.0, 100.0, lo_open=True))

    def rules(self) -> list[tuple[bool, str]]:
        return [
            (
                self.min_disparity_px < self.max_disparity_px,
                "stereo.min_disparity_px must be below stereo.max_disparity_px",
            )
        ]


@dataclass(frozen=True)
class OdometryConfig(Section):
    """Frame-to-keyframe odometry: matching, RANSAC and the window, the keyframe test (the estimation settings it
    shares with localization are in ``estimation``)."""

    SECTION: ClassVar[str] = "odometry"

    match_radius_px: float = setting(20.0, RADIUS_PX)  # search radius around the predicted projection
    match_radius_no_prior_px: float = setting(200.0, RADIUS_PX)  # radius when the motion prior is not trusted
    max_descriptor_distance: int = setting(64, DESCRIPTOR_DISTANCE)
    ransac_iterations: int = setting(2000, Range(1, 1_000_000, integer=True))
    ransac_threshold_px: float = setting(5.0, Range(0.0, 1000.0, lo_open=True))
    min_inliers: int = setting(15, Range(3, 100_000, integer=True))  # fewer: FAILURE
    # rounds of re-choosing a tracked frame's inliers among all its matches at the refined pose, then refining again
    # (stops early when the set is unchanged; each round starts where the last left the landmarks). 1: RANSAC's
    # inliers only, which on kitti00_ramp_clip held 0-9 of a frame's 3-15 matched near landmarks (the scale's anchors)
    # and depended on RANSAC's sample; with 4, t_err over clean + 16 noise seeds has a standard deviation of 0.14
    # points instead of 0.44, at 1.04-1.14x (kitti06) and 1.20-1.27x (the ramp) the odometry frame's cost
    # (docs/odometry_stability.md)
    inlier_rounds: int = setting(4, Range(1, 100, integer=True))
    # a far landmark whose rays across the window span at least this angle starts the windowed bundle
    # adjustment where they meet (its depth from parallax, not from one small disparity); on kitti00_ramp_clip
    # 0.5 deg gave t_err 0.9-1.6 % over four feature variants, 1 deg 1.1-2.3 %, none 1.4-2.0 %
    far_min_parallax_deg: float = setting(0.5, Range(0.0, 180.0))
    keyframe_translation_m: float = setting(0.3, Range(0.0, 1000.0))  # new vertex when translation exceeds this
    keyframe_rotation_deg: float = setting(3.0, Range(0.0, 180.0))  # ... or rotation exceeds this
    keyframe_min_inliers: int = setting(50, Range(0, 100_000, integer=True))  # ... or inliers fall below this
    # implausible motion is a FAILURE. VT&R3 bounds a step at 2 m / 20 deg; bounded here as rates so that
    # subsampled runs (KITTI at stride 3 moves 3.6 m between frames) are judged by speed, not by step
    max_speed_mps: float = setting(40.0, Range(0.0, 10_000.0, lo_open=True))
    max_rotation_rate_dps: float = setting(200.0, Range(0.0, 100_000.0, lo_open=True))
    # online self-calibration of the stereo pair's disparity offset (vtr.vo.disparity_offset): "online" fits
    # measured = slope * implied + offset over the window's landmarks at each keyframe (implied: the disparity their
    # parallax depth gives) and removes the offset from every disparity; "off" trusts the calibration
    disparity_offset: str = setting("online", Choice("online", "off"))
    # samples (keyframe observations of landmarks triangulated by parallax) before an offset is removed
    disparity_offset_min_samples: int = setting(200, Range(1, 10_000_000, integer=True))
    # a sample's rays must span this angle: with less, the parallax depth's own error flattens the fitted line and
    # pulls the offset towards 0 (kitti00_ramp_clip: 0.5 deg -0.69 px, 1 deg -0.69, 2 deg -1.24, 3 deg -1.20;
    # scale_check against ground truth -1.16)
    disparity_offset_min_parallax_deg: float = setting(2.0, Range(0.0, 180.0, lo_open=True))
    # the fit keeps the latest keyframes' samples, at least this many (bounded cost on a long route; the ramp's 26
    # frames give about 800, kitti06's 51 frames 4 700)
    disparity_offset_max_samples: int = setting(20_000, Range(1, 100_000_000, integer=True))
    # the removed offset is the fitted one shrunk towards 0 by this many of its standard errors (evidence within
    # them leaves 0)
    disparity_offset_shrink_sigmas: float = setting(3.0, Range(0.0, 100.0))
    # an offset below this stays unremoved: the calibration's scale (baseline, focal length), which motion cannot
    # observe, is not known better than this offset's effect on near depth. kitti06_clip's -0.2 px (its ground truth
    # shows a +0.3 % scale error that the offset hides at near disparities: removed, t_err 0.61 -> 0.85 %) stays,
    # kitti00_ramp_clip's -1.0..-1.2 px (path x1.010-1.014 long) goes
    disparity_offset_min_px: float = setting(0.5, Range(0.0, 1000.0))
    # keyframes in the local map matched and refined together
    window_keyframes: int = setting(5, Range(1, 1000, integer=True))
    # landmarks in the windowed bundle adjustment (near ones first, then the longest tracks); on kitti00_ramp_clip
    # 800 gave t_err 1.4-2.0 % over four feature variants against 1.9-5.0 % for 400
    window_max_landmarks: int = setting(800, Range(1, 1_000_000, integer=True))
    # Levenberg-Marquardt iterations of the windowed bundle adjustment
    window_iterations: int = setting(4, Range(1, 1000, integer=True))
    # a step below this (and still_rotation_deg) is DO_NOTHING
    still_translation_m: float = setting(1e-3, Range(0.0, 1000.0))
    still_rotation_deg: float = setting(0.01, Range(0.0, 180.0))
    # variance put on an edge carried by the motion prior alone
    failure_variance: float = setting(100.0, Range(0.0, 1e12, lo_open=True))
    # a teach whose odometry fails (FAILURE: the pose carried by the motion prior) on more than this fraction of
    # its frames ends failed: its run aborted with the count, not finished, since such a map is no route.
    # 0.5: "most frames" (1 never fails a teach)
    teach_max_failed_fraction: float = setting(0.5, Range(0.0, 1.0))

    def rules(self) -> list[tuple[bool, str]]:
        return [
            (
                self.keyframe_min_inliers >= self.min_inliers,
                "odometry.keyframe_min_inliers must be >= odometry.min_inliers",
            ),
            (
                self.match_radius_no_prior_px >= self.match_radius_px,
                "odometry.match_radius_no_prior_px must be >= odometry.match_radius_px",
            ),
            (
                self.disparity_offset_max_samples >= self.disparity_offset_min_samples,
                "odometry.disparity_offset_max_samples must be >= odometry.disparity_offset_min_samples",
            ),
        ]


@dataclass(frozen=True)
class EstimationConfig(Section):
    """Robust pose estimation that odometry and localization share: the ratio test, RANSAC's confidence, the
    refinement and the near/far weighting of stereo rows (docs/configuration.md)."""

    SECTION: ClassVar[str] = "estimation"

    # best/second-best Hamming ratio of a descriptor match (odometry's temporal matches, localization's matches)
    ratio_test: float = setting(0.9, Range(0.0, 1.0, lo_open=True))
    # RANSAC's confidence (odometry's P3P against the local map, localization's against a taught submap)
    ransac_confidence: float = setting(0.999, Range(0.0, 1.0, lo_open=True, hi_open=True))
    # Gauss-Newton iterations refining a pose on its inliers (odometry's tracked frame, a localization)
    refine_iterations: int = setting(10, Range(1, 1000, integer=True))
    # Huber kernel width (px) of every refinement: odometry's tracked frame and window, a localization
    huber_px: float = setting(1.5, Range(0.0, 1000.0, lo_open=True))
    # landmarks beyond this many baselines are "far": their disparity row keeps only far_disparity_weight,
    # so they fix rotation (and their own depth by parallax) while the scale comes from near landmarks.
    # 15 baselines = disparity f/15 (48 px on KITTI), where a systematic disparity error of 1 px (measured on
    # kitti00_ramp_clip, docs/far_structure.md) is about 2 % of depth
    far_point_baselines: float = setting(15.0, Range(0.0, 1e6, lo_open=True))
    # weight of a far landmark's disparity row (1 = full, 0 = ignored): small enough to leave the scale to
    # near landmarks
    far_disparity_weight: float = setting(1e-4, Range(0.0, 1.0))
    # a problem (a tracked frame, the window, a localization) with fewer near observations than this weighs every
    # disparity fully: with nothing near (a camera high above flat ground) the scale can only come from far
    # structure. 1: on the synthetic aerial repeats at 8 m lateral offset the largest error was 11 cm (36 cm when
    # the 60 largest disparities counted instead) and on kitti00_ramp_clip t_err 0.8-2.0 % (1.0-2.5 %)
    min_near_observations: int = setting(1, Range(0, 100_000, integer=True))


@dataclass(frozen=True)
class RunConfig(Section):
    """The run as a whole."""

    SECTION: ClassVar[str] = "run"

    # seed of a run's random choices (runs are reproducible): the place vocabulary's training, and odometry's RANSAC
    # (0 keeps the matching order, another shuffles the correspondences by (seed, frame index) before OpenCV's
    # solvePnPRansac, whose own generator has a fixed seed that cv2.setRNGSeed does not reach:
    # docs/odometry_stability.md)
    seed: int = setting(0, Range(0, 2**31 - 1, integer=True))


@dataclass(frozen=True)
class LocalizationConfig(Section):
    """Repeat: localizing the leaf against the taught (privileged) path."""

    SECTION: ClassVar[str] = "localization"

    ransac_iterations: int = setting(6000, Range(1, 1_000_000, integer=True))
    ransac_threshold_px: float = setting(10.0, Range(0.0, 1000.0, lo_open=True))
    # fewer inliers: not a success. 30 is the perception constraint's L_min (thesis §7.4): a success the
    # controller counts on has at least the inliers the controller plans for
    min_inliers: int = setting(30, Range(3, 100_000, integer=True))
    # searching (the start of a repeat, after a loss: unguided matches against a place candidate) demand this many
    min_inliers_unlocalized: int = setting(60, Range(3, 100_000, integer=True))
    min_matches: int = setting(30, Range(3, 1_000_000, integer=True))  # fewer candidate matches: do not try
    # fewer inliers per match: a chance alignment, reported as failure
    min_inlier_ratio: float = setting(0.4, Range(0.0, 1.0))
    # median reprojection error of the inliers (px, the worse of the taught and the leaf view) above this does not
    # fit the pixel noise: a chance alignment spreads its inliers up to the RANSAC threshold
    max_median_residual_px: float = setting(2.5, Range(0.0, 1000.0, lo_open=True))
    # the bundle adjustment's covariance, with the pixel noise its residuals estimate, times this (1: as estimated).
    # What the adjustment holds fixed (the taught vertices' placement) is added from the teach's temporal edges
    # (vtr.navigation.experiences.taught_covariance), not by a scale: a fixed 9 was conservative on kitti06 and the
    # synthetic aerial routes (position NEES 0.9 / 0.4) and overconfident on kitti00_ramp_clip (3.4-4.5)
    covariance_scale: float = setting(1.0, Range(0.0, 1e6, lo_open=True))
    # the pixel part of a localization's covariance: the delete-one-block jackknife over this many cells per side of
    # the leaf's image (features in one cell share their errors); 0, or fewer than covariance_min_blocks cells with
    # inliers: the adjustment's inverse Hessian times its variance factor (docs/localization.md)
    covariance_blocks: int = setting(8, Range(0, 1000, integer=True))
    covariance_min_blocks: int = setting(16, Range(7, 1_000_000, integer=True))
    # chi-square gate (6 dof) on the innovation of a localization against the odometry-propagated prior, and
    # between two keyframes' place candidates before the first success: 22.46 = 99.9 %
    innovation_gate: float = setting(22.46, Range(0.0, 1e9, lo_open=True))
    # floor of the prior's standard deviation (model errors odometry's covariance leaves out)
    prior_floor_translation_m: float = setting(0.05, Range(0.0, 1000.0))
    prior_floor_rotation_deg: float = setting(0.5, Range(0.0, 180.0))
    # odometry's scale error along its motion (1 sigma, share of the motion since the last localization) in the
    # prior: the newest keyframe, right after its window adjustment, is short or long along its motion far more
    # than it drifts sideways. Measured against ground truth on kitti00_ramp_clip (far structure): 2-12 % at 2 m per
    # keyframe, 12-22 % at 4 m, 27 % on the first step of a run under gamma 2.0; kitti06_clip within 2.2 %. 2 % per
    # metre of drift alone refused correct localizations with 1 200 inliers (5.6 sigma); 0.05 still refused the
    # gamma 2.0 run's first confirmation (docs/localization.md, tools/availability.py)
    odometry_scale_sigma: float = setting(0.1, Range(0.0, 10.0))
    # the chain is lost (place recognition again) after this many failures in a row, or this far since the last
    # success, or at once when odometry failed in between
    lost_after_failures: int = setting(3, Range(1, 1_000_000, integer=True))
    lost_after_distance_m: float = setting(10.0, Range(0.0, 1e6, lo_open=True))
    # a pose further than this beyond either end of the taught route is off the route: not localized
    off_route_distance_m: float = setting(3.0, Range(0.0, 1e6))
    # along-track motion between successive localizations that decides the direction of travel
    direction_min_step_m: float = setting(0.2, Range(0.0, 1e6))
    # while localized, every this many keyframes place recognition checks that no other place fits better
    place_check_every: int = setting(10, Range(1, 1_000_000, integer=True))
    match_radius_px: float = setting(30.0, RADIUS_PX)  # search radius around the prior's prediction
    # ... around the chain's own prior while tracking (odometry since the last success): on every availability case
    # (748 tracked leaves) 0.02 % of the inliers lie further than 15 px from it (docs/localization.md, "Cost")
    tracking_match_radius_px: float = setting(15.0, RADIUS_PX)
    # ... times this per consecutive failure (the prior grows uncertain)
    match_radius_growth: float = setting(2.0, Range(1.0, 100.0))
    max_match_radius_px: float = setting(240.0, RADIUS_PX)
    max_descriptor_distance: int = setting(64, DESCRIPTOR_DISTANCE)
    # trunk search window along the privileged path
    trunk_window_back: int = setting(10, Range(0, 1_000_000, integer=True))
    trunk_window_forward: int = setting(20, Range(0, 1_000_000, integer=True))
    rotation_weight: float = setting(7.0, Range(0.0, 1e6))  # trunk search metric ||rho|| + w ||phi||
    # taught vertices on each side of the trunk whose (window-refined) landmarks the leaf is matched against;
    # teach even / repeat odd on kitti00_ramp_clip, T_leaf_trunk median over four feature variants:
    # 0 -> 21-54 mm, 1 -> 20-40 mm, 2 -> 20-43 mm; kitti06_clip 10-13 mm for each
    neighbour_vertices: int = setting(1, Range(0, 50, integer=True))
    # where Repeat.steps (vtr repeat) localizes each new vertex: "own" on a localizer thread beside the frame loop,
    # in order, for every features.threads (the localization of one vertex overlaps the next frames' extraction and
    # odometry, as the map writes do on their writer thread); "caller" on the thread that runs the frames (with
    # features.threads 1 all per-frame computation but the map writes on one thread: the repeat's frames/s 0.85 of
    # the odometry's on kitti06 instead of 1.02, tools/bench_repeat.py; "caller" costs less CPU, so it suits a
    # process that shares its cores). Results are identical either way (docs/localization.md, "Cost")
    thread: str = setting("own", Choice("own", "caller"))

    def rules(self) -> list[tuple[bool, str]]:
        return [
            (self.min_matches >= self.min_inliers, "localization.min_matches must be >= localization.min_inliers"),
            (
                self.max_match_radius_px >= self.match_radius_px,
                "localization.max_match_radius_px must be >= localization.match_radius_px",
            ),
            (
                self.max_match_radius_px >= self.tracking_match_radius_px,
                "localization.max_match_radius_px must be >= localization.tracking_match_radius_px",
            ),
        ]


@dataclass(frozen=True)
class PlaceConfig(Section):
    """Place recognition over the taught vertices (vtr/navigation/place.py): a bag of binary ORB words."""

    SECTION: ClassVar[str] = "place"

    # vocabulary: a two-level tree of k-majority clusters, this many nodes per level (branching^2 words)
    branching: int = setting(32, Range(2, 256, integer=True))
    # taught descriptors sampled to learn the vocabulary (spread evenly over the vertices), clustering iterations
    training_descriptors: int = setting(50_000, Range(2, 100_000_000, integer=True))
    training_iterations: int = setting(6, Range(0, 1000, integer=True))
    candidates: int = setting(3, Range(1, 1000, integer=True))  # best-scoring vertices verified geometrically
    # a route of more vertices than ``shortlist`` is queried in two passes: an inverted file of each vertex's
    # ``vertex_words`` heaviest words, looked up with the query's ``query_words`` heaviest, shortlists this many
    # vertices, and only they are scored exactly (the others score 0); up to ``shortlist`` vertices every one is
    # scored. On a synthetic 50 000-vertex route (tools/bench_place.py, 200 queries) 200 / 128 / 128 found the
    # place as often as scoring every vertex (99.5 %), the same best vertex for every query, in 2.4-2.9 ms of CPU
    # against 59 ms (shortlist / vertex_words / query_words: 200 / 64 / 64 found 97.5 %, 100 / 32 / 64 86.5 %)
    shortlist: int = setting(200, Range(1, 10_000_000, integer=True))
    vertex_words: int = setting(128, Range(1, 1_000_000, integer=True))
    query_words: int = setting(128, Range(1, 1_000_000, integer=True))


@dataclass(frozen=True)
class SmoothingConfig(Section):
    """Continuous-time WNOA smoother."""

    SECTION: ClassVar[str] = "smoothing"

    # power spectral density of the white-noise acceleration, m^2/s^3
    qc_translation: float = setting(1.0, Range(0.0, 1e6, lo_open=True))
    qc_rotation: float = setting(0.1, Range(0.0, 1e6, lo_open=True))  # rad^2/s^3
    lag_s: float = setting(5.0, Range(0.0, 3600.0, lo_open=True))  # fixed-lag window (s)
    rate_hz: float = setting(50.0, Range(0.0, 1000.0, lo_open=True))  # default output rate of state.csv
    # odometry's own covariance (fixed landmarks) ignores drift; the smoother adds this much per metre
    # travelled between vertices, so that localizations against the taught path are not outvoted
    odometry_translation_sigma_per_m: float = setting(0.02, Range(0.0, 10.0))  # m per m (2 % drift)
    odometry_rotation_sigma_per_m: float = setting(0.0005, Range(0.0, 10.0))  # rad per m
    # state_at answers at most this long after the newest knot (a controller's query beyond it is an error:
    # the WNOA prior alone would extrapolate without bound)
    max_extrapolation_s: float = setting(1.0, Range(0.0, 3600.0))
    # the controller state's acceleration: a kernel-weighted local linear fit of the knots' velocities within this
    # half-width (s; continuous in time, the noise of each knot's velocity averaged); 0: the derivative of the
    # WNOA mean (discontinuous at every knot, as noisy as the knots' velocities differ)
    acceleration_window_s: float = setting(1.0, Range(0.0, 60.0))
    # the repeat's Qc from its own motion (vtr.state.wnoa.MotionPsd, docs/smoother.md "Qc"): per axis, the second
    # differences of the odometry's mean twists over spans of 1 and qc_long_steps keyframe steps (which tell the
    # motion from odometry's noise), forgotten over qc_window_s seconds; qc_window_s 0 keeps qc_* fixed. qc_* are
    # used until the forgetting-weighted count of long-span samples reaches qc_min_samples, and the estimate is held
    # above qc_floor_share of them
    qc_window_s: float = setting(10.0, Range(0.0, 3600.0))
    qc_long_steps: int = setting(4, Range(2, 1000, integer=True))
    qc_min_samples: float = setting(5.0, Range(1.0, 1e6))
    qc_floor_share: float = setting(1e-3, Range(0.0, 1.0))


@dataclass(frozen=True)
class ControlConfig(Section):
    """Perception-aware flatness-based MPC (``vtr.control.mpc``; thesis §7.4 settings)."""

    SECTION: ClassVar[str] = "control"

    dt_s: float = setting(0.1, Range(0.0, 10.0, lo_open=True))  # MPC discretization (10 Hz)
    horizon: int = setting(15, Range(1, 1000, integer=True))  # prediction steps N (1.5 s)
    # outer loop: one QP (one SQP iteration) per tick
    rate_hz: float = setting(50.0, Range(0.0, 10_000.0, lo_open=True))
    speed_mps: float = setting(10.0, Range(0.0, 1000.0, lo_open=True))  # desired speed along the taught path
    l_min: float = setting(THESIS_L_MIN, Range(0.0, 1e6))  # minimum inlier count
    c_bar: float = setting(THESIS_C_BAR, Range(0.0, 100.0))  # normal quantile of the chance constraint (3 sigma)
    # linearized mu - c sigma - L_min >= this (inliers; absorbs one SQP step's error). 1.5 keeps the thesis
    # experiment guaranteed forward and back at 10 and 12 m/s (docs/perception_aware_mpc); 6 (the old default)
    # made P-A slower than a fixed 1 m bound, 0.5 missed by 0.2 flown back
    perception_margin: float = setting(1.5, Range(0.0, 1e6))
    # speed governor: a tick whose plan cannot keep the constraint (governor_check) multiplies the reference's
    # speed by this (1: off); it recovers at accel_max_mps2. 0.8 measured (0.5: P-A slower than the fixed 1 m
    # bound at 12 m/s; off: the mount-camera return of tests/control fell to 9.1), docs/perception_aware_mpc
    speed_governor: float = setting(0.8, Range(0.0, 1.0, lo_open=True))
    # "plan": the true constraint along the new plan falls below 0 at a step, or its rows need more slack than
    # perception_margin; "slack": the latter only
    governor_check: str = setting("plan", Choice("plan", "slack"))
    # the chance constraint the perception rows linearize: "normal" mu - c_bar sigma (thesis eq. 7.7) or
    # "conservative" mu - c_bar sqrt(mu) (eq. 7.8, sigma^2 <= mu)
    constraint_form: str = setting("normal", Choice("normal", "conservative"))
    # between the 10 Hz grid points: "velocity" asks the perception row for |grad g| dt/2 |v| more (measured:
    # slower, not needed with the governor), "none" constrains the grid points only (the thesis' row)
    intersample: str = setting("none", Choice("none", "velocity"))
    # yaw reference: "along_travel" (the heading of the path in the direction of travel) or "as_taught" (the
    # taught vehicle's yaw: a camera on its mount looks where it looked when taught, also flown backward)
    yaw_reference: str = setting("along_travel", Choice("along_travel", "as_taught"))
    # a field step farther than this from the taught path (m) is OFF_ROUTE (the aerial demo's localization
    # envelope ends 7-17 m from the path: beyond it nothing taught supports the model)
    off_route_distance_m: float = setting(10.0, Range(0.0, 1e6, lo_open=True))
    # ... or more than this past either end of the route (m, along its first/last segment)
    off_route_past_end_m: float = setting(3.0, Range(0.0, 1e6))
    q_position: float = setting(1.0, Range(0.0, 1e9))  # tracking weight on position error (1/m^2)
    q_yaw: float = setting(10.0, Range(0.0, 1e9))  # tracking weight on yaw error (1/rad^2)
    r_jerk: float = setting(1e-3, Range(0.0, 1e9, lo_open=True))  # input weight on jerk ((s^3/m)^2)
    r_yaw_rate: float = setting(0.1, Range(0.0, 1e9, lo_open=True))  # input weight on yaw rate ((s/rad)^2)
    speed_max_mps: float = setting(12.0, Range(0.0, 1000.0, lo_open=True))  # per-axis velocity bound
    # per-axis acceleration bound (tilt, see flat_model.attitude_from_flat)
    accel_max_mps2: float = setting(8.0, Range(0.0, 1000.0, lo_open=True))
    jerk_max_mps3: float = setting(40.0, Range(0.0, 100_000.0, lo_open=True))  # per-axis jerk bound
    yaw_rate_max_rps: float = setting(1.5, Range(0.0, 100.0, lo_open=True))  # yaw-rate bound (rad/s)
    # L1 penalty of the softened path/perception rows (exact penalty)
    slack_weight: float = setting(1e3, Range(0.0, 1e12, lo_open=True))
    # quadratic penalty on the same slacks (conditioning)
    slack_quadratic_weight: float = setting(10.0, Range(0.0, 1e12))
    # terminal set: "hover" (v_N = a_N = 0, recursive feasibility) or "free" (no terminal constraint)
    terminal_set: str = setting("hover", Choice("hover", "free"))
    osqp_eps: float = setting(1e-4, Range(0.0, 1.0, lo_open=True))  # OSQP absolute/relative tolerance
    osqp_max_iter: int = setting(4000, Range(1, 10_000_000, integer=True))
    # OSQP solution polishing (no measured gain on the thesis experiment); not on/off: YAML reads those as booleans
    osqp_polishing: str = setting("disabled", Choice("disabled", "enabled"))


@dataclass(frozen=True)
class ExperienceConfig(Section):
    """Multi-experience localization (docs/map.md, "Experiences"): earlier repeats matched besides the teach."""

    SECTION: ClassVar[str] = "experiences"

    # experiences (earlier finished repeats) whose landmarks a keyframe is matched against besides the teach's, at
    # most; 0 localizes against the teach alone (single experience). Bounds the matching cost per keyframe
    max_per_keyframe: int = setting(3, Range(0, 100, integer=True))
    # a repeat is an experience only when at least this share of its keyframes localized (and it finished)
    min_localized_share: float = setting(0.5, Range(0.0, 1.0))
    # the recommender ranks experiences first by the inliers they gave the localizations of this many last keyframes
    history_keyframes: int = setting(5, Range(1, 1_000_000, integer=True))
    # `vtr map prune`: keep the newest this many experiences localized at each taught vertex ...
    keep_last: int = setting(5, Range(0, 1_000_000, integer=True))
    # ... plus this many most used ones (keyframes of later repeats they gave inliers to)
    keep_most_used: int = setting(5, Range(0, 1_000_000, integer=True))


@dataclass(frozen=True)
class MapConfig(Section):
    """On-disk map."""

    SECTION: ClassVar[str] = "map"

    # zlib level of array blobs: 1 packs a kitti06 vertex 0.8 % larger than 3 in 85 % of the time (docs/map.md)
    compress_level: int = setting(1, Range(0, 9, integer=True))
