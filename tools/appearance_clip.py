"""A KITTI-layout clip copied with a photometric change applied to both images of every frame: the lighting
cases localization must keep working under (docs/localization.md, "Availability").

Changes (``--change``):

* ``gamma`` (``--gamma``, e.g. 0.5 brighter, 2.0 darker): ``255 (I/255)^gamma``;
* ``dusk``: darker and flatter (``DUSK_GAIN`` times the image plus ``DUSK_OFFSET``) with a little sensor noise
  (``DUSK_NOISE`` gray levels, ``--seed``);
* ``shadows``: moving cloud shadows, a few smooth low-frequency dark blobs (``SHADOW_BLOBS``, up to
  ``SHADOW_DEPTH`` darker at their centres, ``SHADOW_SIZE`` of the image width across) that drift
  ``SHADOW_DRIFT`` of the image width per frame (``--seed`` places them; the same field on both cameras);
* ``noise``: Gaussian noise of ``--sigma`` gray levels (default 1: imperceptible), ``--seed``.

calib.txt, times.txt and poses.txt are copied as they are: ground truth holds for the changed copy.

usage: python tools/appearance_clip.py SRC DST --change gamma --gamma 0.5
       python tools/appearance_clip.py SRC DST --change shadows --seed 3
"""

from __future__ import annotations

import argparse
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

CHANGES = ("gamma", "dusk", "shadows", "noise")
GRAY_MAX = 255.0
DUSK_GAIN = 0.45  # dusk: the image at this share of its brightness ...
DUSK_OFFSET = 12.0  # ... plus this floor (gray levels): darker and lower contrast
DUSK_NOISE = 1.5  # ... with this much sensor noise (gray levels, 1 sigma)
SHADOW_BLOBS = 4  # cloud shadows in view
SHADOW_DEPTH = 0.55  # a shadow's centre keeps 1 - this of the light
SHADOW_SIZE = 0.25  # a shadow's 1-sigma radius, share of the image width
SHADOW_DRIFT = 0.02  # a shadow's motion per frame, share of the image width


def _gray(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, GRAY_MAX).astype(np.uint8)


def gamma(img: np.ndarray, g: float) -> np.ndarray:
    return _gray(GRAY_MAX * (img.astype(np.float64) / GRAY_MAX) ** g)


def dusk(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return _gray(DUSK_GAIN * img.astype(np.float64) + DUSK_OFFSET + rng.normal(0.0, DUSK_NOISE, img.shape))


def noise(img: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    return _gray(img.astype(np.float64) + rng.normal(0.0, sigma, img.shape))


def shadow_field(shape: tuple[int, int], frame: int, seed: int) -> np.ndarray:
    """Light multiplier (H, W) in (1 - SHADOW_DEPTH, 1] of frame ``frame``: blobs placed by ``seed`` that drift
    with the frame index (one wind direction per blob)."""
    h, w = shape
    rng = np.random.default_rng(seed)
    centre = rng.uniform([0.0, 0.0], [w, h], (SHADOW_BLOBS, 2))
    heading = rng.uniform(0.0, 2 * np.pi, SHADOW_BLOBS)
    centre = centre + frame * SHADOW_DRIFT * w * np.c_[np.cos(heading), np.sin(heading)]
    sigma = SHADOW_SIZE * w
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    dark = np.zeros(shape)
    for cx, cy in centre:
        dark = np.maximum(dark, np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma**2)))
    return 1.0 - SHADOW_DEPTH * dark


def transform(
    change: str, *, g: float = 1.0, seed: int = 0, sigma: float = 1.0
) -> Callable[[np.ndarray, int], np.ndarray]:
    """The change as a function of (image, frame index) -> image (uint8 grayscale in, uint8 out)."""
    if change not in CHANGES:
        raise ValueError(f"change: {change!r} is not one of {', '.join(CHANGES)}")
    rng = np.random.default_rng(seed)
    if change == "gamma":
        return lambda img, _k: gamma(img, g)
    if change == "dusk":
        return lambda img, _k: dusk(img, rng)
    if change == "noise":
        return lambda img, _k: noise(img, rng, sigma)
    return lambda img, k: _gray(img.astype(np.float64) * shadow_field(img.shape[:2], k, seed))


def appearance_clip(
    src: str | Path, dst: str | Path, change: str, *, g: float = 1.0, seed: int = 0, sigma: float = 1.0
) -> Path:
    """Copy clip ``src`` (KITTI layout: image_0, image_1, calib.txt, times.txt, poses.txt) to ``dst`` with
    ``change`` applied to both images of every frame; returns ``dst``."""
    import cv2

    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise FileExistsError(f"dst: {dst} exists")
    f = transform(change, g=g, seed=seed, sigma=sigma)
    for side in ("image_0", "image_1"):
        (dst / side).mkdir(parents=True)
        for k, path in enumerate(sorted((src / side).glob("*.png"))):
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise ValueError(f"image: {path} is not a readable PNG")
            cv2.imwrite(str(dst / side / path.name), f(img, k))
    for name in ("calib.txt", "times.txt", "poses.txt"):
        if (src / name).exists():
            shutil.copy(src / name, dst / name)
    return dst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--change", choices=CHANGES, required=True)
    ap.add_argument("--gamma", type=float, default=1.0, help="exponent of the gamma change")
    ap.add_argument("--seed", type=int, default=0, help="noise and shadow placement")
    ap.add_argument("--sigma", type=float, default=1.0, help="noise: gray levels, 1 sigma")
    args = ap.parse_args()
    print(appearance_clip(args.src, args.dst, args.change, g=args.gamma, seed=args.seed, sigma=args.sigma))


if __name__ == "__main__":
    main()
