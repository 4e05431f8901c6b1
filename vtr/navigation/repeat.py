"""Repeat on top of odometry, the map and the localization chain.

* ``Repeat``: a program feeds frames one by one; odometry runs on the new run (stored in the same
  map as a repeat run), and every new keyframe (leaf) is localized against the taught path
  through the ``LocalizationChain``. ``latest`` is the latest localization.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..geometry import inv_T
from ..map import Map, VertexRecord
from ..types import Features, Keyframe, OdometryResult, StereoFrame, StereoImages
from ..vo.odometry import StereoOdometry
from .localization import Localization, LocalizationChain, Localizer, landmark_record
from .teach import usable_covariance


def frame_of_vertex(v: VertexRecord) -> StereoFrame:
    """The stereo frame a map vertex stores (features, stereo measurements, landmarks)."""
    feats = Features(v.uv, v.octave, np.zeros(len(v.uv)), v.descriptors)
    return StereoFrame(v.t_ns, v.frame_index, feats, v.u_right, v.points)


@dataclass(frozen=True)
class RepeatStep:
    """What one repeat frame produced: its odometry result, and a localization when it became a vertex.

    ``T_teach_frame`` is the frame's camera pose in the teach run's first camera frame, as the
    chain estimates it (odometry from the last localization).
    """

    odometry: OdometryResult
    localization: Localization | None
    vertex_id: int
    T_teach_frame: np.ndarray


class Repeat:
    """Repeat pipeline: feed frames with ``process``; ``latest`` holds the latest localization."""

    def __init__(self, map_: Map, config: Config, source: str = "", start_index: int = 0):
        config.validate()
        self.map = map_
        self.camera = map_.camera
        self.config = config
        ids, T = map_.privileged_poses()
        self.chain = LocalizationChain(ids, T, config.localization, start_index)
        self.localizer = Localizer(self.camera, config.localization, config.odometry, config.stereo.pixel_sigma)
        self.odometry = StereoOdometry(self.camera, config, keep_history=False)
        self.timer = self.odometry.timer          # odometry stages plus "map_write" and "localization"
        self.run = map_.begin_run("repeat", source=source, privileged=False)
        self.latest: Localization | None = None
        self.last_localization_seconds = 0.0     # time the latest frame spent localizing (0 if none)
        self._leaf: tuple[int, np.ndarray] | None = None   # (map id, T_world_leaf) of the previous vertex
        self._attempts = 0

    def process(self, images: StereoImages) -> RepeatStep:
        """Odometry on the frame; localize it when it becomes a new vertex."""
        result = self.odometry.process(images)
        loc = None
        vid = self._leaf[0] if self._leaf else -1
        if result.new_keyframe is not None:
            kf = result.new_keyframe
            edge = None
            if self._leaf is not None:
                edge = (inv_T(self._leaf[1]) @ kf.T_world_kf, usable_covariance(result.covariance), result.inliers)
            with self.timer("map_write"):
                v = self.map.add_vertex(self.run, kf.t_ns, kf.T_world_kf, kf.frame, self.camera.T_vehicle_sensor,
                                        edge)
            self._leaf = (v.id, kf.T_world_kf)
            vid = v.id
            t0 = time.perf_counter()
            with self.timer("localization"):
                loc = self._localize(v.id, kf)
            self.last_localization_seconds = time.perf_counter() - t0
            self.latest = loc
        else:
            self.last_localization_seconds = 0.0
        return RepeatStep(result, loc, vid, self.T_teach(result.T_world_frame))

    def T_teach(self, T_world_frame: np.ndarray) -> np.ndarray:
        """A repeat camera pose (repeat run's world) in the teach run's first camera frame, via the chain."""
        c = self.chain
        T_teach_branch = c.T_priv[c.branch]
        return T_teach_branch @ inv_T(c.T_twig_branch) @ inv_T(c.T_world_twig) @ T_world_frame

    def _localize(self, leaf_id: int, kf: Keyframe) -> Localization:
        c = self.chain
        twig, branch = c.twig_id, (int(c.ids[c.branch]) if c.localized else -1)
        trunk, T_prior = c.prior(kf.T_world_kf)
        trunk_vertex = self.map.vertex(int(c.ids[trunk]))
        trunk_frame = frame_of_vertex(trunk_vertex)
        self._attempts += 1
        T, cov, n_matches, matched, inlier = self.localizer.localize(
            kf.frame, trunk_frame, T_prior, seed=self.config.odometry.seed + self._attempts,
            trusted_prior=c.localized, consecutive_failures=c.consecutive_failures)
        success = T is not None
        if success:
            self.map.add_edge(leaf_id, trunk_vertex.id, T, usable_covariance(cov), "spatial", int(inlier.sum()))
        c.update(leaf_id, kf.T_world_kf, trunk, T)
        T_used = T if success else T_prior
        record = landmark_record(trunk_frame, T_used, self.camera, matched, inlier)
        return Localization(kf.t_ns, leaf_id, trunk_vertex.id, twig, branch, success, n_matches,
                            int(inlier.sum()) if success else 0, T_used,
                            cov if success else np.full((6, 6), np.nan), c.consecutive_failures,
                            c.distance_since_success, record)
