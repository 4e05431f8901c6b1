"""Named constants of the synthetic worlds: clipping, texture atlas, shading, sky, default flight and
vehicle poses, and the seed streams that keep one user seed's random numbers independent."""

from __future__ import annotations

import math

import numpy as np

#: Near clipping distance (m, camera z): hits closer than this are ignored.
NEAR_M = 0.05
#: Side of the square texture atlas in texels (power of two); with GROUND_TEXEL_M the ground
#: texture repeats every 4096 * 0.05 = 204.8 m.
DEFAULT_TEXTURE_SIZE = 4096
#: Ground texture resolution at mip level 0 (m per texel).
GROUND_TEXEL_M = 0.05
#: Box / tree texture resolution at mip level 0 (m per texel).
STRUCTURE_TEXEL_M = 0.04
#: Shortest / longest noise wavelength of the atlas (texels) and the amplitude exponent per
#: octave (amplitude ~ wavelength ** exponent; > 0 makes coarse detail stronger).
NOISE_MIN_WAVELENGTH = 2
NOISE_MAX_WAVELENGTH_FRACTION = 16
NOISE_AMPLITUDE_EXPONENT = 0.1
#: Random flat shapes drawn into the atlas per million texels, their size range (texels) and grey
#: level range (in units of the noise standard deviation).
SHAPES_PER_MEGATEXEL = 1200
SHAPE_SIZE_RANGE_TEXELS = (2.0, 160.0)
SHAPE_LEVEL_RANGE = 2.0
SHAPE_EDGE_BLUR_TEXELS = 0.6
#: Percentiles mapped to grey 0 and 255 when the atlas is quantized.
ATLAS_STRETCH_PERCENTILES = (0.5, 99.5)
#: Texels of wrap-around padding around each packed mip level (bilinear reads one past the end).
ATLAS_PAD = 2
#: Added to every mip level (log2 texels); > 0 blurs more, < 0 sharpens (and aliases).
MIP_BIAS = 0.0
#: Smallest |cos(incidence)| used for the footprint (grazing rays pick the coarsest levels).
MIN_COS_INCIDENCE = 1e-3

#: Mid grey of the 8-bit atlas; contrast scales the texture about it.
MID_GREY = 127.5
#: Lambertian shading: intensity factor = AMBIENT + DIFFUSE * max(0, n . sun).
AMBIENT = 0.45
DIFFUSE = 0.55
#: Unit sun direction in the world (ENU), about 55 deg elevation from the south-east.
SUN_DIRECTION_WORLD = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])
#: Sky grey at the horizon and at the zenith (a smooth featureless gradient).
SKY_GREY_HORIZON = 215.0
SKY_GREY_ZENITH = 185.0
#: Samples of a backdrop's height profile around its circle.
BACKDROP_PROFILE_SAMPLES = 720

#: Default aerial configuration (thesis simulation: multirotor, camera pitched 50 deg down).
DEFAULT_ALTITUDE_M = 12.0
DEFAULT_AERIAL_PITCH_RAD = math.radians(50.0)
#: Default ground-vehicle camera height (m).
DEFAULT_GROUND_CAMERA_HEIGHT_M = 1.5

#: Seed streams, so the texture, the structures, the surface texture offsets and the image noise
#: draw independent random numbers from one user seed.
_STREAM_TEXTURE = 1
_STREAM_LAYOUT = 2
_STREAM_SURFACES = 3
_STREAM_NOISE = 4
