"""The trunk rule, one owner: which taught vertex a pose is expressed against (thesis §6.3.2; VT&R3's trunk search).

The trunk of a pose is the taught vertex in a search window around the previous trunk that minimizes
``||rho|| + w ||phi||`` of the relative transform (translation m, rotation rad, ``w`` =
``localization.rotation_weight``). The window reaches ``back`` vertices behind the previous trunk and
``forward`` ahead of it *in the direction of travel*: a repeat that travels the route backward (the
return flight) searches the same distances, mirrored. The localization chain
(:class:`~vtr.navigation.chain.LocalizationChain`) and the controller's field
(:class:`~vtr.control.field.TaughtPathField`) both choose trunks with these functions.
"""

from __future__ import annotations

import numpy as np

from ..geometry import log_se3_batch

FORWARD, BACKWARD = 1, -1
#: a direction of travel not yet decided (a repeat's first leaves): trunk windows look forward
UNDECIDED = 0


def trunk_cost(T_pose_vertex: np.ndarray, rotation_weight: float) -> np.ndarray:
    """``||rho|| + w ||phi||`` (...,) of relative transforms ``T_pose_vertex`` (..., 4, 4)."""
    T = np.asarray(T_pose_vertex, float)
    xi = log_se3_batch(T.reshape(-1, 4, 4)).reshape(*T.shape[:-2], 6)
    return np.linalg.norm(xi[..., 3:], axis=-1) + rotation_weight * np.linalg.norm(xi[..., :3], axis=-1)


def trunk_window(previous: int, n_vertices: int, back: int, forward: int, direction: int = FORWARD) -> tuple[int, int]:
    """``(lo, hi)`` (hi exclusive) of the path indices searched around trunk ``previous``; ``direction``
    -1 mirrors the window (the route travelled backward)."""
    behind, ahead = (back, forward) if direction >= 0 else (forward, back)
    return max(0, int(previous) - int(behind)), min(int(n_vertices), int(previous) + int(ahead) + 1)


def select_trunk(T_pose_vertex: np.ndarray, lo: int, rotation_weight: float) -> int:
    """Path index of the trunk among candidates ``T_pose_vertex`` (K, 4, 4) = vertices ``lo .. lo+K-1``."""
    return int(lo + np.argmin(trunk_cost(T_pose_vertex, rotation_weight)))


__all__ = ["BACKWARD", "FORWARD", "UNDECIDED", "select_trunk", "trunk_cost", "trunk_window"]
