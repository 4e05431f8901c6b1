"""Synthetic rectified greyscale stereo sequences with exact ground truth: a seeded :class:`Scene` (textured ground,
boxes, trees, a distant backdrop) ray-cast per pixel by :func:`render_stereo`, camera routes (:func:`aerial_route`,
:func:`turning_route`) and KITTI-layout folders (:func:`write_sequence`). This package re-exports its modules' public
names. Scene, rendering, frames, routes and the modules' order: docs/synthetic.md."""

from __future__ import annotations

from .builders import aerial_scene, far_structure_scene, make_scene
from .cameras import T_left_right, kitti_like_camera, zed_camera
from .constants import AMBIENT as AMBIENT
from .constants import ATLAS_PAD as ATLAS_PAD
from .constants import ATLAS_STRETCH_PERCENTILES as ATLAS_STRETCH_PERCENTILES
from .constants import BACKDROP_PROFILE_SAMPLES as BACKDROP_PROFILE_SAMPLES
from .constants import DEFAULT_AERIAL_PITCH_RAD as DEFAULT_AERIAL_PITCH_RAD
from .constants import DEFAULT_ALTITUDE_M as DEFAULT_ALTITUDE_M
from .constants import DEFAULT_GROUND_CAMERA_HEIGHT_M as DEFAULT_GROUND_CAMERA_HEIGHT_M
from .constants import DEFAULT_TEXTURE_SIZE as DEFAULT_TEXTURE_SIZE
from .constants import DIFFUSE as DIFFUSE
from .constants import GROUND_TEXEL_M as GROUND_TEXEL_M
from .constants import MID_GREY as MID_GREY
from .constants import MIN_COS_INCIDENCE as MIN_COS_INCIDENCE
from .constants import MIP_BIAS as MIP_BIAS
from .constants import NEAR_M as NEAR_M
from .constants import NOISE_AMPLITUDE_EXPONENT as NOISE_AMPLITUDE_EXPONENT
from .constants import NOISE_MAX_WAVELENGTH_FRACTION as NOISE_MAX_WAVELENGTH_FRACTION
from .constants import NOISE_MIN_WAVELENGTH as NOISE_MIN_WAVELENGTH
from .constants import SHAPE_EDGE_BLUR_TEXELS as SHAPE_EDGE_BLUR_TEXELS
from .constants import SHAPE_LEVEL_RANGE as SHAPE_LEVEL_RANGE
from .constants import SHAPE_SIZE_RANGE_TEXELS as SHAPE_SIZE_RANGE_TEXELS
from .constants import SHAPES_PER_MEGATEXEL as SHAPES_PER_MEGATEXEL
from .constants import SKY_GREY_HORIZON as SKY_GREY_HORIZON
from .constants import SKY_GREY_ZENITH as SKY_GREY_ZENITH
from .constants import STRUCTURE_TEXEL_M as STRUCTURE_TEXEL_M
from .constants import SUN_DIRECTION_WORLD as SUN_DIRECTION_WORLD
from .render import StereoRender, backproject, render, render_stereo
from .routes import aerial_route, camera_pose, camera_rotation, route_times, turning_route
from .routes import drifting_aerial_route as drifting_aerial_route
from .routes import segmented_aerial_route as segmented_aerial_route
from .scene import Backdrop, Box, Ground, Scene, Tree
from .sequence import write_sequence
from .texture import TextureAtlas, make_texture_atlas

__all__ = [
    "Backdrop",
    "Box",
    "Ground",
    "Scene",
    "StereoRender",
    "TextureAtlas",
    "Tree",
    "T_left_right",
    "aerial_route",
    "aerial_scene",
    "backproject",
    "camera_pose",
    "camera_rotation",
    "far_structure_scene",
    "kitti_like_camera",
    "make_scene",
    "make_texture_atlas",
    "render",
    "render_stereo",
    "route_times",
    "turning_route",
    "write_sequence",
    "zed_camera",
]
