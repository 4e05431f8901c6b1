"""Synthetic stereo generator: determinism, exact geometry, stereo consistency, KITTI output, features."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vtr.geometry import check_se3, inv_T, transform_points
from vtr.io.kitti import KittiSource
from vtr.sim import synthetic as syn

SEED = 7
#: Small atlas for tests that do not look at features (fast to generate).
SMALL_TEXTURE = 512


@pytest.fixture(scope="module")
def zed():
    return syn.zed_camera()


@pytest.fixture(scope="module")
def aerial_scene():
    return syn.aerial_scene(SEED)


@pytest.fixture(scope="module")
def aerial_poses():
    return syn.aerial_route(60.0, 5.0)


@pytest.fixture(scope="module")
def aerial_pair(aerial_scene, zed, aerial_poses):
    return syn.render_stereo(aerial_scene, zed, aerial_poses[4], return_depth=True)


def _ray_ground_hits(camera, T_world_cam, u, v):
    """Independent ground-plane intersection of left-camera pixel rays: camera depth and world points."""
    d_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], axis=1)
    d_world = d_cam @ T_world_cam[:3, :3].T
    t = -T_world_cam[2, 3] / d_world[:, 2]
    return t, T_world_cam[:3, 3] + t[:, None] * d_world


def test_same_seed_same_images_different_seed_different(zed, aerial_poses):
    syn.make_texture_atlas.cache_clear()
    a = syn.make_scene(3, texture_size=SMALL_TEXTURE)
    syn.make_texture_atlas.cache_clear()  # regenerate the atlas from scratch
    b = syn.make_scene(3, texture_size=SMALL_TEXTURE)
    c = syn.make_scene(4, texture_size=SMALL_TEXTURE)
    assert a.boxes == b.boxes and a.trees == b.trees
    T = aerial_poses[2]
    ra = syn.render_stereo(a, zed, T, noise_sigma=2.0, noise_seed=5)
    rb = syn.render_stereo(b, zed, T, noise_sigma=2.0, noise_seed=5)
    np.testing.assert_array_equal(ra.left, rb.left)
    np.testing.assert_array_equal(ra.right, rb.right)
    rc = syn.render_stereo(c, zed, T, noise_sigma=2.0, noise_seed=5)
    assert np.mean(ra.left != rc.left) > 0.5
    rn = syn.render_stereo(a, zed, T, noise_sigma=2.0, noise_seed=6)
    assert not np.array_equal(ra.left, rn.left)  # noise follows its seed


def test_atlas_is_tileable_and_pyramid_consistent():
    atlas = syn.make_texture_atlas(SEED, SMALL_TEXTURE)
    lv0 = atlas.level(0).astype(float)
    assert atlas.packed.dtype == np.uint8 and lv0.shape == (SMALL_TEXTURE, SMALL_TEXTURE)
    assert lv0.std() > 40  # contrast-stretched
    # wrap seam is no stronger than an ordinary neighbouring-column step
    seam = np.abs(lv0[:, 0] - lv0[:, -1]).mean()
    inner = np.abs(np.diff(lv0, axis=1)).mean()
    assert seam < 2 * inner
    assert atlas.level(atlas.n_levels - 1).shape == (1, 1)
    assert abs(float(atlas.level(3).mean()) - lv0.mean()) < 3


def test_ground_depth_is_exact(zed):
    scene = syn.Scene(seed=SEED, texture_size=SMALL_TEXTURE)  # bare ground
    T = syn.aerial_route(10.0, 1.0, heading_rad=0.7)[3]
    img, depth = syn.render(scene, zed, T, return_depth=True)
    assert img.shape == (zed.height, zed.width) and img.dtype == np.uint8
    rng = np.random.default_rng(0)
    u = rng.integers(0, zed.width, 200).astype(float)
    v = rng.integers(0, zed.height, 200).astype(float)
    t, p_world = _ray_ground_hits(zed, T, u, v)
    assert np.all(t > 0)  # a 50 deg pitched camera sees only ground
    np.testing.assert_allclose(depth[v.astype(int), u.astype(int)], t, rtol=1e-5)
    # the ground point projects back to the pixel it was rendered at, with matching depth
    p_cam = transform_points(inv_T(T), p_world)
    uvr = zed.project(p_cam)
    np.testing.assert_allclose(uvr[:, 0], u, atol=1e-6)
    np.testing.assert_allclose(uvr[:, 1], v, atol=1e-6)
    np.testing.assert_allclose(p_cam[:, 2], depth[v.astype(int), u.astype(int)], rtol=1e-5)
    back = syn.backproject(zed, T, depth, u.astype(int), v.astype(int))
    np.testing.assert_allclose(back[:, 2], 0.0, atol=1e-3)


def test_box_and_tree_geometry(zed):
    box = syn.Box(-2.0, -3.0, 2.0, 3.0, height=4.0)
    tree = syn.Tree(0.0, 8.0, trunk_radius=0.3, trunk_height=2.0, crown_radius=1.5, crown_height=4.0)
    scene = syn.Scene(seed=SEED, boxes=(box,), trees=(tree,), texture_size=SMALL_TEXTURE)
    # camera south of the box at x=-12, looking east and 20 deg down
    T = syn.camera_pose((-12.0, 0.0, 6.0), heading_rad=0.0, pitch_down_rad=math.radians(20))
    img, depth = syn.render(scene, zed, T, return_depth=True)
    vv, uu = np.mgrid[0 : zed.height, 0 : zed.width]
    p = syn.backproject(zed, T, depth, uu.ravel(), vv.ravel())
    finite = np.isfinite(p).all(axis=1)
    on_roof = finite & (np.abs(p[:, 2] - box.height) < 1e-3)
    on_wall = finite & (np.abs(p[:, 0] - box.x_min) < 1e-3) & (p[:, 2] > 1e-2)
    assert on_roof.sum() > 500 and on_wall.sum() > 5000
    # every roof / wall pixel lies within the face's rectangle
    assert np.all((p[on_roof, 0] >= box.x_min - 1e-3) & (p[on_roof, 0] <= box.x_max + 1e-3))
    assert np.all((p[on_wall, 1] >= box.y_min - 1e-3) & (p[on_wall, 1] <= box.y_max + 1e-3))
    assert np.all(p[on_wall, 2] <= box.height + 1e-3)
    # every hit point lies on the ground, the box or the tree's surfaces
    on_ground = np.abs(p[finite, 2]) < 1e-3
    in_box = (
        (p[finite, 0] >= box.x_min - 1e-3)
        & (p[finite, 0] <= box.x_max + 1e-3)
        & (np.abs(p[finite, 1]) <= box.y_max + 1e-3)
        & (p[finite, 2] <= box.height + 1e-3)
    )
    rho = np.hypot(p[finite, 0] - tree.x, p[finite, 1] - tree.y)
    z = p[finite, 2]
    on_trunk = (np.abs(rho - tree.trunk_radius) < 1e-3) & (z <= tree.trunk_height + 1e-3)
    crown_r = tree.crown_radius * (1 - (z - tree.trunk_height) / tree.crown_height)
    on_crown = (z >= tree.trunk_height - 1e-3) & (np.abs(rho - np.clip(crown_r, 0, None)) < 2e-3)
    on_crown_base = (np.abs(z - tree.trunk_height) < 1e-3) & (rho <= tree.crown_radius + 1e-3)
    assert np.all(on_ground | in_box | on_trunk | on_crown | on_crown_base)
    assert on_crown.sum() > 200 and on_trunk.sum() > 20
    # walls are shaded differently from the roof so box edges are visible
    roof_mean = img.ravel()[on_roof].mean()
    wall_mean = img.ravel()[on_wall].mean()
    assert abs(roof_mean - wall_mean) > 10


def test_left_right_depth_maps_agree(aerial_pair, zed):
    """A left pixel's 3-D point, seen in the right image at u - fb/z, has the same depth there."""
    H, W = aerial_pair.depth_left.shape
    vv, uu = np.mgrid[0:H:5, 0:W:5]
    z = aerial_pair.depth_left[vv, uu]
    ur = uu - zed.fb / z
    ok = np.isfinite(z) & (ur > 1) & (ur < W - 2)
    zr = cv2.remap(
        aerial_pair.depth_right, ur[ok].astype(np.float32)[None], vv[ok].astype(np.float32)[None], cv2.INTER_LINEAR
    )[0]
    rel = np.abs(zr - z[ok]) / z[ok]
    assert np.mean(rel < 1e-3) > 0.98  # the rest straddle depth edges


def test_orb_stereo_disparities_match_depth(aerial_pair, zed):
    orb = cv2.ORB_create(nfeatures=1000)
    kl, dl = orb.detectAndCompute(aerial_pair.left, None)
    kr, dr = orb.detectAndCompute(aerial_pair.right, None)
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    ul = np.array([kl[m.queryIdx].pt for m in matches])
    ur = np.array([kr[m.trainIdx].pt for m in matches])
    disp = ul[:, 0] - ur[:, 0]
    same_row = (np.abs(ul[:, 1] - ur[:, 1]) <= 1.0) & (disp > 0)
    assert same_row.sum() > 300
    ui = np.round(ul[same_row]).astype(int)
    z = aerial_pair.depth_left[ui[:, 1], ui[:, 0]]
    err = disp[same_row] - zed.fb / z
    assert abs(np.median(err)) < 0.2  # unbiased
    assert np.median(np.abs(err)) < 0.6
    assert np.mean(np.abs(err) < 1.5) > 0.9


def test_aerial_frame_has_many_well_spread_orb_features(aerial_pair, zed):
    kps = cv2.ORB_create(nfeatures=1000).detect(aerial_pair.left, None)
    assert len(kps) >= 500
    pts = np.array([k.pt for k in kps])
    cells = np.zeros((4, 4), int)
    np.add.at(cells, ((pts[:, 1] * 4 / zed.height).astype(int), (pts[:, 0] * 4 / zed.width).astype(int)), 1)
    assert np.mean(cells > 0) >= 0.7


def test_turning_route_texture_is_mostly_beyond_40_baselines(zed):
    T = syn.turning_route(0.5, straight_before_m=8.0, turn_radius_m=6.0, straight_after_m=8.0)
    scene = syn.far_structure_scene(SEED, route_xy=T[:, :2, 3], centre_xy=(8.0, 6.0))
    mid = len(T) // 2
    img, depth = syn.render(scene, zed, T[mid], return_depth=True)
    kps = cv2.ORB_create(nfeatures=1000).detect(img, None)
    assert len(kps) > 300
    pts = np.round([k.pt for k in kps]).astype(int)
    z = depth[pts[:, 1], pts[:, 0]]
    assert np.mean(z > 40 * zed.baseline) > 0.8


def test_routes_geometry():
    T = syn.aerial_route(20.0, 2.0, heading_rad=0.5)
    R = syn.aerial_route(20.0, 2.0, heading_rad=0.5, lateral_offset_m=3.0, vertical_offset_m=-1.0)
    assert len(T) == 11 and T.shape == R.shape
    for Ti in T:
        check_se3(Ti)
    np.testing.assert_allclose(T[:, 2, 3], syn.DEFAULT_ALTITUDE_M)
    np.testing.assert_allclose(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1), 2.0)
    # optical axis 50 deg below the horizon, along the heading; image x horizontal
    z_axis = T[0, :3, 2]
    assert math.isclose(math.asin(-z_axis[2]), math.radians(50), abs_tol=1e-9)
    assert math.isclose(math.atan2(z_axis[1], z_axis[0]), 0.5, abs_tol=1e-9)
    assert abs(T[0, 2, 0]) < 1e-12
    left = np.array([-math.sin(0.5), math.cos(0.5), 0.0])
    np.testing.assert_allclose(R[:, :3, 3] - T[:, :3, 3], np.tile(3.0 * left - [0, 0, 1.0], (len(T), 1)), atol=1e-9)
    # turning route: heading changes by the turn angle, camera height constant, forward looking
    G = syn.turning_route(0.25, turn_angle_rad=math.pi / 2, turn_radius_m=5.0)
    h0 = math.atan2(G[0, 1, 2], G[0, 0, 2])
    h1 = math.atan2(G[-1, 1, 2], G[-1, 0, 2])
    assert math.isclose(h1 - h0, math.pi / 2, abs_tol=1e-9)
    np.testing.assert_allclose(G[:, 2, 3], syn.DEFAULT_GROUND_CAMERA_HEIGHT_M)
    np.testing.assert_allclose(np.linalg.norm(np.diff(G[:, :2, 3], axis=0), axis=1), 0.25, rtol=1e-3)
    t = syn.route_times(G, speed_mps=2.0)
    assert t.dtype == np.int64 and t[0] == 0 and np.all(np.diff(t) > 0)
    assert abs(t[1] - 125_000_000) < 1_000_000


def test_write_sequence_reads_back_as_kitti(tmp_path, zed, aerial_scene):
    T = syn.aerial_route(6.0, 2.0, lateral_offset_m=1.0, heading_rad=0.3)
    t_ns = syn.route_times(T, speed_mps=4.0, start_ns=1_700_000_000_000_000_000)
    out = syn.write_sequence(tmp_path / "seq", aerial_scene, zed, T, t_ns, noise_sigma=1.0, write_depth=True)
    src = KittiSource(out)
    assert len(src) == len(T)
    assert src.camera.matches(zed)
    np.testing.assert_array_equal(src.timestamps(), t_ns)
    gt = src.ground_truth()
    assert gt is not None
    np.testing.assert_allclose(gt.T_world_cam, inv_T(T[0]) @ T, atol=1e-8)
    np.testing.assert_allclose(gt.T_world_cam[0], np.eye(4), atol=1e-12)
    ref = syn.render_stereo(aerial_scene, zed, T[1], noise_sigma=1.0, noise_seed=1)
    frame = src[1]
    np.testing.assert_array_equal(frame.left, ref.left)
    np.testing.assert_array_equal(frame.right, ref.right)
    depth = np.load(out / "depth_0" / "000001.npy")
    assert depth.shape == (zed.height, zed.width)
    assert (out / "poses_world.txt").is_file() and (out / "synthetic.json").is_file()


def test_supersampled_render_matches_shape_and_geometry(zed, aerial_scene, aerial_poses):
    img1, d1 = syn.render(aerial_scene, zed, aerial_poses[1], return_depth=True)
    img2, d2 = syn.render(aerial_scene, zed, aerial_poses[1], supersample=2, return_depth=True)
    assert img2.shape == img1.shape
    np.testing.assert_array_equal(d1, d2)
    assert np.median(np.abs(img1.astype(int) - img2.astype(int))) <= 4
