"""One typed configuration for the whole pipeline, with every default documented here.

Defaults follow the open-source VT&R3 stack (DESIGN.md §4); benchmarks decide changes. A config
loads from YAML (or TOML) holding any subset of the sections below; unknown keys are errors.
Dump the resolved defaults with ``vtr config``.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .errors import ConfigError


@dataclass
class FeatureConfig:
    """Detection and description (left and right images)."""

    # features kept per image after grid bucketing; on the KITTI clip 2000 gave t_err 0.64-0.74 % over
    # five parameter variants against 0.74-0.90 % for 1500, for ~10 % more time per frame
    n_features: int = 2000
    detect_factor: float = 1.5      # ORB detects this many times n_features before bucketing
    grid_rows: int = 8              # bucketing grid (cells keep their strongest features)
    grid_cols: int = 16
    scale_factor: float = 1.2       # ORB pyramid scale step
    n_levels: int = 4               # ORB pyramid levels (scale range 1.7: consecutive keyframes, repeats)
    fast_threshold: int = 20        # FAST corner threshold (grey levels)
    edge_threshold: int = 19        # ORB border (px); also the patch half-size bound
    # ranking of FAST corners before bucketing: "fast" (FAST score, as ORB-SLAM's extractor) or "harris"
    # (OpenCV ORB's default). On the KITTI clip Harris ranking gave t_err 1.05-1.8 % over five parameter
    # variants against 0.67-0.90 % for the FAST score, which is also ~2 ms cheaper per image
    corner_score: str = "fast"
    # threads for one run's per-frame work (allowed: 0..1024; 0 = every core the process may use): with 2 or
    # more the left and right images' features are extracted concurrently and the next frames are decoded in
    # the background (vtr/parallel.py). Results are bit-identical for every value (tests/vo/test_threads.py).
    # KITTI 1226x370 odometry on a shared 2-core machine: 2 threads 1.10-1.52x the frames/s of 1 thread
    # (tools/bench_odometry.py). OpenCV's own pool (cv2.setNumThreads) is left alone: ORB extraction runs
    # serially inside OpenCV, and 1 or 2 OpenCV threads measured the same; batch workers set it to this value
    threads: int = 0


@dataclass
class StereoConfig:
    """Left-right matching on epipolar rows and triangulation."""

    max_row_diff_px: float = 1.5    # |v_l - v_r| allowed at pyramid level 0 (scales with level)
    min_disparity_px: float = 0.5   # smaller disparities are treated as unmatched (points at infinity)
    max_disparity_px: float = 160.0
    max_descriptor_distance: int = 64   # Hamming distance accepted between left and right
    refine_half_window: int = 5     # subpixel refinement: SAD patch half-size (px)
    refine_search_px: int = 3       # subpixel refinement: search +- this many px along the row
    pixel_sigma: float = 1.0        # measurement noise on u_l, v, u_r (px) used for covariances


@dataclass
class OdometryConfig:
    """Frame-to-keyframe odometry, its robust estimation and the keyframe test."""

    match_radius_px: float = 20.0         # search radius around the predicted projection
    match_radius_no_prior_px: float = 200.0   # radius when the motion prior is not trusted
    max_descriptor_distance: int = 64
    ratio_test: float = 0.9               # best/second-best Hamming ratio for temporal matches
    ransac_iterations: int = 2000
    ransac_threshold_px: float = 5.0
    ransac_confidence: float = 0.999
    min_inliers: int = 15                 # fewer: FAILURE
    refine_iterations: int = 10           # Gauss-Newton iterations of the two-view stereo bundle adjustment
    huber_px: float = 1.5                 # robust kernel width in the refinement
    far_point_baselines: float = 40.0     # points beyond this many baselines constrain rotation only
    far_disparity_weight: float = 0.01    # weight of a far point's disparity row (1 = full, 0 = ignored)
    keyframe_translation_m: float = 0.3   # new vertex when translation exceeds this
    keyframe_rotation_deg: float = 3.0    # ... or rotation exceeds this
    keyframe_min_inliers: int = 50        # ... or inliers fall below this
    # implausible motion is a FAILURE. VT&R3 bounds a step at 2 m / 20 deg; bounded here as rates so that
    # subsampled runs (KITTI at stride 3 moves 3.6 m between frames) are judged by speed, not by step
    max_speed_mps: float = 40.0
    max_rotation_rate_dps: float = 200.0
    window_keyframes: int = 5             # keyframes in the local map matched and refined together
    window_max_landmarks: int = 400       # landmarks in the windowed bundle adjustment (longest tracks first)
    window_iterations: int = 4            # Levenberg-Marquardt iterations of the windowed bundle adjustment
    still_translation_m: float = 1e-3     # a step below this (and still_rotation_deg) is DO_NOTHING
    still_rotation_deg: float = 0.01
    failure_variance: float = 100.0       # variance put on an edge carried by the motion prior alone
    seed: int = 0                         # RANSAC seed (runs are reproducible)


@dataclass
class LocalizationConfig:
    """Repeat: localizing the leaf against the taught (privileged) path."""

    ransac_iterations: int = 6000
    ransac_threshold_px: float = 10.0
    min_inliers: int = 6                  # fewer: localization failure
    min_inliers_unlocalized: int = 20     # before the first success (no trusted prior) demand this many
    min_matches: int = 20                 # fewer candidate matches: do not try
    min_inlier_ratio: float = 0.4         # fewer inliers per match: a chance alignment, reported as failure
    match_radius_px: float = 30.0         # search radius around the prior's prediction
    match_radius_growth: float = 2.0      # ... times this per consecutive failure (the prior grows uncertain)
    max_match_radius_px: float = 240.0
    max_descriptor_distance: int = 64
    trunk_window_back: int = 10           # trunk search window along the privileged path
    trunk_window_forward: int = 20
    rotation_weight: float = 7.0          # trunk search metric ||rho|| + w ||phi||
    neighbour_vertices: int = 3           # taught vertices around the trunk whose landmarks are matched


@dataclass
class SmoothingConfig:
    """Continuous-time WNOA smoother."""

    qc_translation: float = 1.0           # power spectral density of the white-noise acceleration, m^2/s^3
    qc_rotation: float = 0.1              # rad^2/s^3
    lag_s: float = 5.0                    # fixed-lag window (s)
    rate_hz: float = 50.0                 # default output rate of state.csv
    # odometry's own covariance (fixed landmarks) ignores drift; the smoother adds this much per metre
    # travelled between vertices, so that localizations against the taught path are not outvoted
    odometry_translation_sigma_per_m: float = 0.02   # m per m (2 % drift)
    odometry_rotation_sigma_per_m: float = 0.0005    # rad per m


@dataclass
class MapConfig:
    """On-disk map."""

    compress_level: int = 3               # zlib level of array blobs


@dataclass
class Config:
    """The whole pipeline configuration."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    localization: LocalizationConfig = field(default_factory=LocalizationConfig)
    smoothing: SmoothingConfig = field(default_factory=SmoothingConfig)
    map: MapConfig = field(default_factory=MapConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "config") -> Config:
        cfg = cls()
        if not isinstance(data, dict):
            raise ConfigError(f"{where}: expected a mapping of sections")
        for section, values in data.items():
            if section not in {f.name for f in dataclasses.fields(cls)}:
                raise ConfigError(f"{where}: unknown section {section!r}")
            target = getattr(cfg, section)
            if not isinstance(values, dict):
                raise ConfigError(f"{where}: section {section!r} must be a mapping")
            known = {f.name: f for f in dataclasses.fields(target)}
            for key, value in values.items():
                if key not in known:
                    raise ConfigError(f"{where}: unknown key {section}.{key}")
                default = getattr(target, key)
                try:
                    value = type(default)(value)
                except (TypeError, ValueError) as err:
                    raise ConfigError(f"{where}: {section}.{key}={value!r} is not a {type(default).__name__}") from err
                setattr(target, key, value)
        cfg.validate(where)
        return cfg

    @classmethod
    def load(cls, path: str | Path) -> Config:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: no such config file")
        try:
            if path.suffix == ".toml":
                data = tomllib.loads(path.read_text())
            else:
                data = yaml.safe_load(path.read_text()) or {}
        except (yaml.YAMLError, tomllib.TOMLDecodeError) as err:
            raise ConfigError(f"{path}: cannot parse ({err})") from err
        return cls.from_dict(data, str(path))

    def validate(self, where: str = "config") -> None:
        """Cross-field checks."""
        o, s, loc = self.odometry, self.stereo, self.localization
        checks = [
            (self.features.n_features > 0, "features.n_features must be positive"),
            (self.features.corner_score in ("fast", "harris"), "features.corner_score must be 'fast' or 'harris'"),
            (0 < s.min_disparity_px < s.max_disparity_px, "stereo disparity limits must satisfy 0 < min < max"),
            (o.min_inliers >= 3, "odometry.min_inliers must be at least 3"),
            (o.keyframe_min_inliers >= o.min_inliers, "odometry.keyframe_min_inliers must be >= min_inliers"),
            (o.ransac_iterations > 0 and o.ransac_threshold_px > 0, "odometry RANSAC settings must be positive"),
            (loc.min_matches >= loc.min_inliers >= 3, "localization needs min_matches >= min_inliers >= 3"),
            (self.smoothing.qc_translation > 0 and self.smoothing.qc_rotation > 0, "smoothing Qc must be positive"),
            (0 < o.ratio_test <= 1, "odometry.ratio_test must be in (0, 1]"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ConfigError(f"{where}: {msg}")
