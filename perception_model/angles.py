"""Parallax and view angles of trunk landmarks (thesis §7.3.1, eqs. 7.3-7.4), in radians: ``alpha_i`` at the landmark
between the rays to the taught camera ``s`` and to the current camera, ``theta_i`` between the current optical axis
``z`` and the ray to the landmark, for ``p_is`` (taught camera to landmark) and ``p_ao`` (current camera offset) in the
gravity-aligned frame ``o`` at the taught camera, broadcast with numpy rules; ``optical_axis(yaw, pitch_down)`` gives
``z``. Degenerate input, accuracy and the axis convention: docs/perception_model.md, "In code"."""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError
from .settings import THESIS_PITCH_DOWN_RAD  # the camera pitch of the thesis simulations

Degenerate = Literal["nan", "raise"]

_VECTOR_DIM = 3


def _as_vectors(x: ArrayLike, name: str) -> NDArray[np.float64]:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim == 0 or arr.shape[-1] != _VECTOR_DIM:
        raise GeometryError(f"{name} must have shape (..., 3), got {arr.shape}")
    return arr


def angle_between(u: ArrayLike, v: ArrayLike, *, on_degenerate: Degenerate = "nan") -> NDArray[np.float64]:
    """Angle in [0, pi] between 3-vectors ``u`` and ``v`` (shapes ``(..., 3)``, broadcast).

    Computed as ``atan2(|u x v|, u . v)`` after scaling each vector to unit length. Entries where
    either vector has zero length (or is non-finite) are NaN, or raise ``GeometryError`` when
    ``on_degenerate="raise"``.
    """
    a = _as_vectors(u, "u")
    b = _as_vectors(v, "v")
    na = np.linalg.norm(a, axis=-1, keepdims=True)
    nb = np.linalg.norm(b, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = a / na
        ub = b / nb
        cross = np.linalg.norm(np.cross(ua, ub), axis=-1)
        dot = np.sum(ua * ub, axis=-1)
        ang = np.arctan2(cross, dot)
    bad = ~(np.isfinite(ang) & (na[..., 0] > 0) & (nb[..., 0] > 0))
    bad = np.broadcast_to(bad, ang.shape)
    if np.any(bad):
        if on_degenerate == "raise":
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise GeometryError(f"angle undefined at index {idx}: zero-length or non-finite vector")
        ang = np.where(bad, np.nan, ang)
    return ang


def parallax_angle(p_is: ArrayLike, p_ao: ArrayLike, *, on_degenerate: Degenerate = "nan") -> NDArray[np.float64]:
    """Parallax angle ``alpha = angle(-p_is, -p_is + p_ao)`` in radians, in [0, pi].

    ``p_is`` (taught camera -> landmark) and ``p_ao`` (taught camera -> current camera) are
    ``(..., 3)`` arrays in frame ``o``, broadcast together. ``alpha = 0`` when the current camera
    is at the taught camera (or anywhere on the ray from the landmark through it). Undefined (NaN)
    when the landmark coincides with either camera.
    """
    p = _as_vectors(p_is, "p_is")
    a = _as_vectors(p_ao, "p_ao")
    return angle_between(-p, a - p, on_degenerate=on_degenerate)


def view_angle(
    p_is: ArrayLike, p_ao: ArrayLike, z: ArrayLike, *, on_degenerate: Degenerate = "nan"
) -> NDArray[np.float64]:
    """View angle ``theta = angle(z, p_is - p_ao)`` in radians, in [0, pi].

    ``z`` is the current optical axis in frame ``o`` (only its direction matters). Broadcasts
    ``p_is``, ``p_ao`` and ``z`` (all ``(..., 3)``). Undefined (NaN) when the current camera is at
    the landmark or ``z`` is zero.
    """
    p = _as_vectors(p_is, "p_is")
    a = _as_vectors(p_ao, "p_ao")
    axis = _as_vectors(z, "z")
    return angle_between(axis, p - a, on_degenerate=on_degenerate)


def optical_axis(yaw: ArrayLike, pitch_down: float = THESIS_PITCH_DOWN_RAD) -> NDArray[np.float64]:
    """Unit optical axis ``[cos(yaw) cos(b), sin(yaw) cos(b), -sin(b)]`` in frame ``o`` (ENU-like).

    ``yaw`` (radians, any shape ``S``) is the heading of the optical axis counter-clockwise from
    the x axis; ``pitch_down`` (radians) is the camera's fixed pitch below the horizon. Returns
    shape ``S + (3,)``.
    """
    psi = np.asarray(yaw, dtype=np.float64)
    cb, sb = np.cos(pitch_down), np.sin(pitch_down)
    return np.stack([np.cos(psi) * cb, np.sin(psi) * cb, np.full_like(psi, -sb)], axis=-1)


def optical_axis_yaw_derivative(yaw: ArrayLike, pitch_down: float = THESIS_PITCH_DOWN_RAD) -> NDArray[np.float64]:
    """Derivative ``dz/dyaw = [-sin(yaw) cos(b), cos(yaw) cos(b), 0]`` of ``optical_axis``."""
    psi = np.asarray(yaw, dtype=np.float64)
    cb = np.cos(pitch_down)
    return np.stack([-np.sin(psi) * cb, np.cos(psi) * cb, np.zeros_like(psi)], axis=-1)


def angle_gradient(u: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
    """Gradient of ``angle_between(u, v)`` with respect to ``v`` (``u`` held fixed), ``(..., 3)``.

    Equals ``-w / |v|`` where ``w`` is the unit component of ``u`` perpendicular to ``v``
    (computed as ``v^ x (u^ x v^) / |u^ x v^|``). At angle 0 or pi the angle is not differentiable
    (a cone point); there the zero vector is returned (the minimum-norm subgradient at 0).
    Zero-length input gives NaN.
    """
    a = _as_vectors(u, "u")
    b = _as_vectors(v, "v")
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = a / np.linalg.norm(a, axis=-1, keepdims=True)
        nb = np.linalg.norm(b, axis=-1, keepdims=True)
        ub = b / nb
        c = np.cross(ua, ub)
        s = np.linalg.norm(c, axis=-1, keepdims=True)
        perp = np.cross(ub, c)
        grad = np.where(s > 0, -perp / (s * nb), 0.0)
    return np.where(np.isfinite(ub) & np.isfinite(ua), grad, np.nan)
