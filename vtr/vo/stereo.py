"""Stereo processing of one rectified pair: left-right matching on epipolar rows, subpixel
disparity, triangulation into 3-D landmarks (left rectified camera frame) with covariance.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..camera import StereoCamera
from ..config import FeatureConfig, StereoConfig
from ..errors import DataError
from ..parallel import background_thread, lookahead_frames, prefetch, resolve_threads
from ..timing import StageTimer
from ..types import Features, StereoFrame, StereoImages
from .features import FeatureExtractor, descriptor_words
from .kernels import matching as km
from .kernels import stereo as ks

MAX_OCTAVE_GAP = 1  # left/right features more pyramid levels apart are not the same corner


def refine_disparity(
    left: np.ndarray, right: np.ndarray, u_l: np.ndarray, v_l: np.ndarray, u_r: np.ndarray, half: int, search: int
) -> tuple[np.ndarray, np.ndarray]:
    """Subpixel right-image columns by mean-removed SSD block matching along the row around ``u_r``.

    Left patches are centred on the rounded left keypoints; the returned left columns are those
    rounded positions. Returns (u_left_px, u_right_px), with NaN right columns where the SSD
    minimum sits on the search border (no reliable match).
    """
    ul = np.rint(u_l).astype(np.int64)
    vl = np.rint(v_l).astype(np.int64)
    ur = np.rint(u_r).astype(np.int64)
    out = ks.refine_rows(np.ascontiguousarray(left), np.ascontiguousarray(right), ul, vl, ur, int(half), int(search))
    return ul.astype(float), out


def check_stereo_images(images: StereoImages, camera: StereoCamera) -> None:
    """``DataError`` unless both images are 2-D uint8 greyscale arrays of the camera's size and the
    time is an integer (ns): what every source yields, checked again for library callers."""
    if not isinstance(images, StereoImages):
        raise DataError(f"expected StereoImages, got {type(images).__name__}")
    if isinstance(images.t_ns, bool) or not isinstance(images.t_ns, int | np.integer):
        raise DataError(f"frame {images.index}: t_ns must be an integer time in ns, got {images.t_ns!r}")
    w, h = camera.size
    for side in ("left", "right"):
        img = getattr(images, side)
        where = f"frame {images.index} ({images.t_ns} ns) {side} image"
        if not isinstance(img, np.ndarray):
            raise DataError(f"{where}: expected a numpy array, got {type(img).__name__}")
        if img.ndim != 2:
            raise DataError(
                f"{where}: expected a 2-D greyscale image, got shape {img.shape} (convert colour with cv2.cvtColor)"
            )
        if img.dtype != np.uint8:
            raise DataError(f"{where}: expected uint8 pixels, got {img.dtype} (scale to 0..255 and cast first)")
        if img.shape != (h, w):
            raise DataError(f"{where}: is {img.shape[1]}x{img.shape[0]} but the camera is {w}x{h}")


def _both(extractor: FeatureExtractor) -> Callable[[StereoImages], tuple[Features, Features]]:
    """Left then right image's features, with one extractor on the calling thread."""
    return lambda images: (extractor.extract(images.left), extractor.extract(images.right))


class StereoProcessor:
    """Turns a rectified stereo pair into a ``StereoFrame``.

    With ``features.threads`` resolving to 2 or more, :meth:`process` extracts the right image's
    features on a thread of the processor's own while the left image's are extracted on the caller's
    (OpenCV releases the GIL), and :meth:`frames` processes several frames at once on a pool of
    that many threads. Every thread has its own extractor, so results equal the one-thread run bit for bit.
    """

    def __init__(
        self, camera: StereoCamera, features: FeatureConfig, stereo: StereoConfig, timer: StageTimer | None = None
    ):
        self.camera = camera
        self.timer = timer or StageTimer()
        self.cfg = stereo
        self.features_config = features
        self.extractor = FeatureExtractor(features, camera.size)
        self.scales = self.extractor.level_scales
        self.threads = resolve_threads(features.threads)
        self._local = threading.local()  # a frames() worker's own extractor
        self._right_extractor = self.extractor
        self._pool: ThreadPoolExecutor | None = None
        if self.threads > 1:
            self._right_extractor = FeatureExtractor(features, camera.size)
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="vtr-features")
            weakref.finalize(self, self._pool.shutdown, wait=False)

    def frames(self, images: Iterable[StereoImages]) -> Iterator[StereoFrame]:
        """``images`` as stereo frames, in order.

        With 2 or more threads, a background thread pulls (decodes) the images and hands each frame
        whole to a pool of ``threads`` workers, up to :func:`~vtr.parallel.lookahead_frames` frames ahead
        of the caller, who meanwhile tracks and localizes the frames already done: decoding, features and
        stereo of later frames overlap this one's tracking. Each frame is processed as :meth:`process` would,
        so results equal the one-thread run bit for bit; an error is raised at the frame it belongs to.
        """
        if self.threads <= 1:
            return map(self.process, images)
        return self._frames_on_pool(images)

    def _frames_on_pool(self, images: Iterable[StereoImages]) -> Iterator[StereoFrame]:
        niceness = self.features_config.worker_niceness
        with ThreadPoolExecutor(
            self.threads, thread_name_prefix="vtr-stereo", initializer=background_thread, initargs=(niceness,)
        ) as pool:
            # the reader (decoding, a serial stage that feeds every worker) keeps the normal priority
            pending = prefetch(
                (pool.submit(self._process_on_worker, im) for im in images), lookahead_frames(self.threads)
            )
            try:
                for future in pending:
                    yield future.result()
            finally:
                pending.close()  # stops the reader before the pool is shut down
                pool.shutdown(wait=True, cancel_futures=True)

    def process(self, images: StereoImages) -> StereoFrame:
        """Features on both images, stereo matches, subpixel disparity, triangulation."""
        return self._process(images, self._extract_split if self._pool is not None else _both(self.extractor))

    def _extract_split(self, images: StereoImages) -> tuple[Features, Features]:
        assert self._pool is not None
        right = self._pool.submit(self._right_extractor.extract, images.right)
        return self.extractor.extract(images.left), right.result()

    def _process_on_worker(self, images: StereoImages) -> StereoFrame:
        extractor = getattr(self._local, "extractor", None)
        if extractor is None:
            extractor = self._local.extractor = FeatureExtractor(self.features_config, self.camera.size)
        return self._process(images, _both(extractor))

    def _process(
        self, images: StereoImages, extract: Callable[[StereoImages], tuple[Features, Features]]
    ) -> StereoFrame:
        check_stereo_images(images, self.camera)
        with self.timer("features"):
            left, right = extract(images)
        with self.timer("stereo"):
            return self._triangulate(images, left, right)

    def match(self, left: Features, right: Features) -> tuple[np.ndarray, np.ndarray]:
        """Left/right matches on epipolar rows: (left indices, right indices)."""
        c = self.cfg
        qi, tj, _ = km.row_band_match(
            np.ascontiguousarray(left.uv),
            left.octave.astype(np.int64),
            descriptor_words(left.descriptors),
            np.ascontiguousarray(right.uv),
            right.octave.astype(np.int64),
            descriptor_words(right.descriptors),
            c.max_row_diff_px * self.scales,
            c.min_disparity_px - c.refine_search_px,
            c.max_disparity_px,
            MAX_OCTAVE_GAP,
            c.max_descriptor_distance,
        )
        return qi, tj

    def _triangulate(self, images: StereoImages, left: Features, right: Features) -> StereoFrame:
        qi, tj = self.match(left, right)
        c = self.cfg
        ul, ur = refine_disparity(
            images.left,
            images.right,
            left.uv[qi, 0],
            left.uv[qi, 1],
            right.uv[tj, 0],
            c.refine_half_window,
            c.refine_search_px,
        )
        disp = ul - ur
        good = np.isfinite(ur) & (disp >= c.min_disparity_px) & (disp <= c.max_disparity_px)
        qi, ul, ur = qi[good], ul[good], ur[good]
        uv = left.uv.copy()
        uv[qi, 0] = ul
        uv[qi, 1] = np.rint(uv[qi, 1])
        feats = Features(uv, left.octave, left.response, left.descriptors)
        u_right = np.full(len(uv), np.nan)
        u_right[qi] = ur
        points = np.full((len(uv), 3), np.nan)
        points[qi] = self.camera.triangulate(uv[qi, 0], uv[qi, 1], ul - ur)
        return StereoFrame(images.t_ns, images.index, feats, u_right, points)
