"""Ray casting: the nearest surface hit of every pixel (depth, texture coordinates, mip footprint,
gain and bias) against the ground, the backdrop, box faces and tree frusta of a compiled scene."""

from __future__ import annotations

import functools
import math

import numpy as np

from ...camera import StereoCamera
from .constants import (
    AMBIENT,
    DIFFUSE,
    MID_GREY,
    MIN_COS_INCIDENCE,
    NEAR_M,
    SUN_DIRECTION_WORLD,
)
from .scene import Scene


@functools.lru_cache(maxsize=8)
def _ray_grid(fx: float, fy: float, cx: float, cy: float, width: int, height: int):
    """Camera-frame ray directions d = (xn, yn, 1) per pixel centre: xn (1, W), yn (H, 1), 1/|d| (H, W)."""
    xn = ((np.arange(width, dtype=np.float64) - cx) / fx).astype(np.float32)[None, :]
    yn = ((np.arange(height, dtype=np.float64) - cy) / fy).astype(np.float32)[:, None]
    inv_norm = (1.0 / np.sqrt(1.0 + xn**2 + yn**2)).astype(np.float32)
    for a in (xn, yn, inv_norm):
        a.setflags(write=False)
    return xn, yn, inv_norm


#: Hull edges of a rectangle's 4 corners (in order) and of a cuboid's 8 corners indexed
#: 4 * ix + 2 * iy + iz (edges join corners differing in one index).
_QUAD_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
_CUBOID_EDGES = np.array([[i, i ^ bit] for i in range(8) for bit in (1, 2, 4) if i < i ^ bit])


class _Frame:
    """Per-image ray-casting state: world ray directions and the nearest-hit buffers (flat, H*W)."""

    def __init__(self, camera: StereoCamera, T_world_cam: np.ndarray, scale: int):
        fx, fy = camera.fx * scale, camera.fy * scale
        cx, cy = (camera.cx + 0.5) * scale - 0.5, (camera.cy + 0.5) * scale - 0.5
        self.W, self.H = camera.width * scale, camera.height * scale
        self.fx, self.fy, self.cx, self.cy = fx, fy, cx, cy
        self.f = math.sqrt(fx * fy)
        xn, yn, inv_norm = _ray_grid(fx, fy, cx, cy, self.W, self.H)
        T = np.asarray(T_world_cam, float)
        self.R = T[:3, :3]
        self.C = T[:3, 3].copy()
        R32 = self.R.astype(np.float32)
        # world direction of the ray whose camera-frame z component is 1, so the hit parameter is depth
        self.d = np.empty((3, self.H * self.W), np.float32)
        for i in range(3):
            self.d[i].reshape(self.H, self.W)[...] = R32[i, 0] * xn + R32[i, 1] * yn + R32[i, 2]
        self.inv_norm = inv_norm.reshape(-1)
        n = self.H * self.W
        self.depth = np.full(n, np.inf, np.float32)
        self.tex_u = np.zeros(n, np.float32)
        self.tex_v = np.zeros(n, np.float32)
        self.footprint = np.ones(n, np.float32)  # level-0 texels per pixel
        self.gain = np.zeros(n, np.float32)
        self.bias = np.zeros(n, np.float32)

    def write(self, pix, t, u, v, fp, gain, bias) -> None:
        """Store surface attributes at flat pixel indices ``pix`` (depth already resolved or set here)."""
        for buf, val in (
            (self.depth, t),
            (self.tex_u, u),
            (self.tex_v, v),
            (self.footprint, fp),
            (self.gain, gain),
            (self.bias, bias),
        ):
            buf[pix] = val

    def resolve(self, pix: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Depth-test candidate hits (flat pixel, depth), possibly several per pixel: lower the depth
        buffer to the nearest and return the indices of the candidates that won their pixel."""
        closer = np.flatnonzero(t < self.depth[pix])
        pix, t = pix[closer], t[closer]
        np.minimum.at(self.depth, pix, t)
        return closer[t == self.depth[pix]]

    def candidates(self, corners_world: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels to test for convex primitives bounded by the convex hull of world corners (P, K, 3)
        with hull edges ``edges`` (E, 2) (corner index pairs): returns (primitive index, flat pixel index)
        for every pixel of each primitive's projected bounding rectangle, after clipping it to the near
        plane. Primitives entirely behind the near plane or off the image give none."""
        P = len(corners_world)
        if P == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        pc = (corners_world - self.C) @ self.R  # camera frame
        z = pc[..., 2]
        # near-plane clipping: the clipped hull is spanned by the corners in front of the plane and
        # the points where hull edges cross it
        pa, pb = pc[:, edges[:, 0]], pc[:, edges[:, 1]]
        za, zb = pa[..., 2], pb[..., 2]
        crosses = (za - NEAR_M) * (zb - NEAR_M) < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            w_edge = np.where(crosses, (NEAR_M - za) / (zb - za), 0.0)
        pts = np.concatenate([pc, pa + w_edge[..., None] * (pb - pa)], axis=1)
        valid = np.concatenate([z > NEAR_M, crosses], axis=1)
        zz = np.where(valid, np.maximum(pts[..., 2], NEAR_M), 1.0)
        u = self.fx * pts[..., 0] / zz + self.cx
        v = self.fy * pts[..., 1] / zz + self.cy
        u0 = np.clip(np.floor(np.where(valid, u, np.inf).min(axis=1)), 0, self.W)
        u1 = np.clip(np.ceil(np.where(valid, u, -np.inf).max(axis=1)) + 1, 0, self.W)
        v0 = np.clip(np.floor(np.where(valid, v, np.inf).min(axis=1)), 0, self.H)
        v1 = np.clip(np.ceil(np.where(valid, v, -np.inf).max(axis=1)) + 1, 0, self.H)
        u0, u1, v0, v1 = (a.astype(np.int64) for a in (u0, u1, v0, v1))
        w, h = u1 - u0, v1 - v0
        counts = np.where(valid.any(axis=1) & (w > 0) & (h > 0), w * h, 0)
        total = int(counts.sum())
        prim = np.repeat(np.arange(P), counts)
        local = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
        wp = w[prim]
        pix = (v0[prim] + local // wp) * self.W + u0[prim] + local % wp
        return prim, pix


def _cast_ground(fr: _Frame, scene: Scene) -> None:
    cz = fr.C[2]
    if cz <= 0:
        return
    off_u, off_v, inv_tex, gain, bias = scene._compiled.ground_tex
    dx, dy, dz = fr.d
    with np.errstate(divide="ignore"):
        t = np.float32(-cz) / dz  # negative or inf for rays that do not go down
    mask = (t > NEAR_M) & (t < np.inf)
    t[~mask] = 0.0
    # hit offsets from the camera (float32 precision independent of the distance from the origin)
    hx = t * dx
    hy = t * dy
    g = scene.ground
    if math.isfinite(g.half_extent_m):
        mask &= np.abs(hx - np.float32(g.centre_xy[0] - fr.C[0])) <= g.half_extent_m
        mask &= np.abs(hy - np.float32(g.centre_xy[1] - fr.C[1])) <= g.half_extent_m
    cos_inc = np.maximum(np.abs(dz) * fr.inv_norm, np.float32(MIN_COS_INCIDENCE))
    fp = t * np.float32(inv_tex / fr.f) / cos_inc
    size = scene.texture_size
    hx *= np.float32(inv_tex)
    hx += np.float32((fr.C[0] * inv_tex + off_u) % size)
    hy *= np.float32(inv_tex)
    hy += np.float32((fr.C[1] * inv_tex + off_v) % size)
    for buf, val in (
        (fr.depth, t),
        (fr.tex_u, hx),
        (fr.tex_v, hy),
        (fr.footprint, fp),
        (fr.gain, np.float32(gain)),
        (fr.bias, np.float32(bias)),
    ):
        np.copyto(buf, val, where=mask)


def _cast_backdrop(fr: _Frame, scene: Scene) -> None:
    bd = scene.backdrop
    comp = scene._compiled
    if bd is None or comp.backdrop_tex is None or comp.backdrop_heights is None:
        return
    _, off_v, inv_tex, gain, bias = comp.backdrop_tex
    ox, oy = fr.C[0] - bd.centre_xy[0], fr.C[1] - bd.centre_xy[1]
    dist = math.hypot(ox, oy)
    # from inside, the wall is at least (radius - dist) m away along any ray: only pixels whose
    # current depth is beyond that can see it
    min_depth = (bd.radius - dist) * float(np.min(fr.inv_norm)) if dist < bd.radius else 0.0
    pix = np.flatnonzero(fr.depth > min_depth)
    dx, dy, dz = fr.d[0][pix], fr.d[1][pix], fr.d[2][pix]
    ox32, oy32 = np.float32(ox), np.float32(oy)
    a = dx * dx + dy * dy
    b = ox32 * dx + oy32 * dy  # half of the linear coefficient
    c = np.float32(ox * ox + oy * oy - bd.radius**2)
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        t_far = (-b + sq) / a
        t_near = (-b - sq) / a
    # inside the cylinder only the far root is ahead; from outside the near root is the visible side
    t = np.where(t_near > NEAR_M, t_near, t_far) if c > 0 else t_far
    hz = np.float32(fr.C[2]) + t * dz
    heights = comp.backdrop_heights
    keep = np.flatnonzero((disc >= 0) & (t > NEAR_M) & (t < fr.depth[pix]) & (hz >= 0) & (hz <= heights.max()))
    pix, t, hz, dx, dy = pix[keep], t[keep], hz[keep], dx[keep], dy[keep]
    hx = ox32 + t * dx
    hy = oy32 + t * dy
    phi = np.arctan2(hy, hx)
    n = len(heights)
    pos = (phi + np.float32(np.pi)) * np.float32(n / (2 * np.pi))
    i0 = np.floor(pos)
    frac = pos - i0
    i0 = i0.astype(np.int64) % n
    h = heights[i0] * (1 - frac) + heights[(i0 + 1) % n] * frac
    k = np.flatnonzero(hz <= h)
    pix, t, hz, hx, hy, dx, dy, pos = pix[k], t[k], hz[k], hx[k], hy[k], dx[k], dy[k], pos[k]
    cos_inc = np.maximum(
        np.abs(hx * dx + hy * dy) * np.float32(1.0 / bd.radius) * fr.inv_norm[pix], np.float32(MIN_COS_INCIDENCE)
    )
    fp = t * np.float32(inv_tex / fr.f) / cos_inc
    u = pos * np.float32(scene.texture_size / n)  # one atlas period around the circle: seamless
    v = hz * np.float32(inv_tex) + np.float32(off_v)
    fr.write(pix, t, u, v, fp, np.float32(gain), np.float32(bias))


def _cast_rects(fr: _Frame, scene: Scene) -> None:
    comp = scene._compiled
    if len(comp.rect_axis) == 0:
        return
    # back-face culling: the camera must be on the normal's side of the face
    idx = np.flatnonzero(comp.rect_sign * (fr.C[comp.rect_axis] - comp.rect_c) > 0)
    prim, pix = fr.candidates(comp.rect_corners[idx], _QUAD_EDGES)
    if len(pix) == 0:
        return
    prim = idx[prim]
    axis, s_ax, t_ax = comp.rect_axes[:, prim]
    # per-face constants relative to the camera centre
    dc = (comp.rect_c - fr.C[comp.rect_axis]).astype(np.float32)
    rel = (comp.rect_bounds - fr.C[comp.rect_axes[1:]].T.repeat(2, axis=1)).astype(np.float32)
    t = dc[prim] / fr.d[axis, pix]
    ps = t * fr.d[s_ax, pix]
    pt = t * fr.d[t_ax, pix]
    r = rel[prim]
    hit = np.flatnonzero((t > NEAR_M) & (ps >= r[:, 0]) & (ps <= r[:, 1]) & (pt >= r[:, 2]) & (pt <= r[:, 3]))
    win = hit[fr.resolve(pix[hit], t[hit])]
    prim, pix, t, ps, pt, axis, s_ax, t_ax = (a[win] for a in (prim, pix, t, ps, pt, axis, s_ax, t_ax))
    # texture origin of each face relative to the camera, reduced modulo the atlas in float64
    tex = comp.rect_tex.astype(float)
    size = scene.texture_size
    base_u = ((fr.C[comp.rect_axes[1]] * tex[:, 2] + tex[:, 0]) % size).astype(np.float32)
    base_v = ((fr.C[comp.rect_axes[2]] * tex[:, 2] + tex[:, 1]) % size).astype(np.float32)
    _, _, inv_tex, gain, bias = comp.rect_tex[prim].T
    cos_inc = np.maximum(np.abs(fr.d[axis, pix]) * fr.inv_norm[pix], np.float32(MIN_COS_INCIDENCE))
    fp = t * inv_tex * np.float32(1.0 / fr.f) / cos_inc
    fr.write(pix, t, ps * inv_tex + base_u[prim], pt * inv_tex + base_v[prim], fp, gain, bias)


def _cast_frusta(fr: _Frame, scene: Scene) -> None:
    comp = scene._compiled
    if len(comp.frusta) == 0:
        return
    prim, pix = fr.candidates(comp.frustum_corners, _CUBOID_EDGES)
    if len(pix) == 0:
        return
    F = comp.frusta
    cz = fr.C[2]
    k_all = (F[:, 5] - F[:, 4]) / (F[:, 3] - F[:, 2])  # radius slope dr/dz
    # per-primitive constants (camera relative): ox, oy, a0 = radius at camera height, k, z0, z1
    consts = np.stack(
        [fr.C[0] - F[:, 0], fr.C[1] - F[:, 1], F[:, 4] + k_all * (cz - F[:, 2]), k_all, F[:, 2] - cz, F[:, 3] - cz],
        axis=1,
    ).astype(np.float32)
    ox, oy, a0, k, z0, z1 = consts[prim].T
    dx, dy, dz = fr.d[0][pix], fr.d[1][pix], fr.d[2][pix]
    qa = dx * dx + dy * dy - k * k * dz * dz
    qb = ox * dx + oy * dy - a0 * k * dz  # half of the linear coefficient
    qc = ox * ox + oy * oy - a0 * a0
    disc = qb * qb - qa * qc
    best = np.full(len(pix), np.inf, np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        ra, rb = (-qb - sq) / qa, (-qb + sq) / qa
        for root in (np.maximum(ra, rb), np.minimum(ra, rb)):  # the nearer valid root wins
            hz = root * dz
            ok = (root > NEAR_M) & (hz >= z0) & (hz <= z1)
            best = np.where(ok, root, best)
    cap = np.zeros(len(pix), np.int8)  # 0 lateral, -1 bottom disc, +1 top disc
    # caps: bottom disc (facing down) seen from below, top disc (facing up) seen from above
    for col_z, col_r, side in ((2, 4, -1), (3, 5, 1)):
        vis = (F[:, col_r] > 0) & (side * (cz - F[:, col_z]) > 0)
        if not vis.any():
            continue
        sel = np.flatnonzero(vis[prim])
        zc = (F[:, col_z] - cz).astype(np.float32)[prim[sel]]
        rc2 = (F[:, col_r] ** 2).astype(np.float32)[prim[sel]]
        tc = zc / dz[sel]
        px, py = ox[sel] + tc * dx[sel], oy[sel] + tc * dy[sel]
        ok = (tc > NEAR_M) & (px * px + py * py <= rc2) & (tc < best[sel])
        best[sel[ok]] = tc[ok]
        cap[sel[ok]] = side
    hit = np.flatnonzero(np.isfinite(best))
    win = hit[fr.resolve(pix[hit], best[hit])]
    prim, pix, t, cap, ox, oy, k, dx, dy, dz = (a[win] for a in (prim, pix, best, cap, ox, oy, k, dx, dy, dz))
    px = ox + t * dx
    py = oy + t * dy
    pz = np.float32(cz) + t * dz
    rho = np.maximum(np.sqrt(px * px + py * py), np.float32(1e-6))
    lateral = cap == 0
    # unit outward normal: lateral (px/rho, py/rho, -k)/sqrt(1+k^2); caps -z / +z
    inv_len = 1.0 / np.sqrt(1.0 + k * k)
    nx = np.where(lateral, px / rho * inv_len, np.float32(0.0))
    ny = np.where(lateral, py / rho * inv_len, np.float32(0.0))
    nz = np.where(lateral, -k * inv_len, cap.astype(np.float32))
    sun = SUN_DIRECTION_WORLD.astype(np.float32)
    shade = np.float32(AMBIENT) + np.float32(DIFFUSE) * np.maximum(nx * sun[0] + ny * sun[1] + nz * sun[2], 0)
    cos_inc = np.maximum(np.abs(nx * dx + ny * dy + nz * dz) * fr.inv_norm[pix], np.float32(MIN_COS_INCIDENCE))
    off_u, off_v, inv_tex, albedo, contrast = comp.frustum_tex[prim].T
    r_ref = np.maximum(F[:, 4], F[:, 5]).astype(np.float32)[prim]
    # lateral texture: (azimuth * r_ref, z); caps: (x, y). Near a cone apex the azimuthal mapping
    # squeezes texels by r / r_ref: the footprint accounts for it.
    u = np.where(lateral, np.arctan2(py, px) * r_ref, px) * inv_tex + off_u
    v = np.where(lateral, pz, py) * inv_tex + off_v
    squeeze = np.where(lateral, np.maximum(r_ref / rho, np.float32(1.0)), np.float32(1.0))
    fp = t * inv_tex * np.float32(1.0 / fr.f) / cos_inc * squeeze
    k_gain = shade * albedo
    fr.write(pix, t, u, v, fp, k_gain * contrast, k_gain * np.float32(MID_GREY) * (1 - contrast))


def _cast(scene: Scene, camera: StereoCamera, T_world_view: np.ndarray, scale: int) -> _Frame:
    fr = _Frame(camera, T_world_view, scale)
    _cast_ground(fr, scene)
    _cast_backdrop(fr, scene)
    _cast_rects(fr, scene)
    _cast_frusta(fr, scene)
    return fr
