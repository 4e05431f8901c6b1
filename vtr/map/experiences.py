"""Experiences: the finished repeats of a map that later repeats may localize against besides the teach (docs/map.md,
"Experiences").

A repeat's vertices, landmarks and the spatial edges to the taught vertices it localized against are in the map
already; this module says which repeats are trustworthy experiences (:func:`experiences`), where their vertices
sit relative to the taught path (:func:`experience_links`, through the stored spatial edges), how much later
repeats used them (table ``experience_use``, written with each leaf by :meth:`vtr.map.Map.add_leaf`) and which
ones a retention rule keeps (:func:`retention`, :func:`prune`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..errors import MapError
from . import localizations
from .records import INDEX_MASK, RUN_FINISHED, RUN_SHIFT, blob_matrix
from .store import Map

#: the triggers that keep vertices, their data, checksums, edges and runs append-only; `prune` lifts them inside
#: its one transaction and puts them back before it commits
APPEND_ONLY_TRIGGERS = (
    "vertices_append_only_delete",
    "vertex_data_append_only_delete",
    "edges_append_only_delete",
    "runs_no_delete",
    "vertex_checksums_append_only_delete",
    "localizations_append_only_delete",
)


@dataclass(frozen=True)
class ExperienceInfo:
    """One repeat run seen as an experience: its lifecycle ``state``, vertices, how many of them localized against
    the taught path (a spatial edge to a taught vertex), whether it is ``trusted`` (else ``why_not`` says why), and
    its use: keyframes of later repeats it gave localization inliers to (``used_keyframes``), by ``used_by`` repeats."""

    run: int
    state: str
    n_vertices: int
    localized: int
    trusted: bool
    why_not: str
    used_keyframes: int
    used_by: int

    @property
    def localized_share(self) -> float:
        return self.localized / self.n_vertices if self.n_vertices else 0.0


@dataclass(frozen=True)
class ExperienceLinks:
    """Experience vertices placed on the taught path, one row per spatial edge (arrays of equal length):
    ``vertex_id`` (the experience's vertex), ``run``, ``taught_id`` (the taught vertex it localized against),
    ``T_vertex_taught`` (4x4: taught-vertex camera coordinates into the experience vertex's camera, the stored
    ``T_leaf_trunk``), its 6x6 ``covariance`` ([rot, trans], as stored) and ``inliers``."""

    vertex_id: np.ndarray
    run: np.ndarray
    taught_id: np.ndarray
    T_vertex_taught: np.ndarray
    covariance: np.ndarray
    inliers: np.ndarray

    def __len__(self) -> int:
        return len(self.vertex_id)


def _has_table(m: Map, name: str) -> bool:
    with m.file.connection() as conn:
        return (
            conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?", (name,)).fetchone()
            is not None
        )


def use_counts(m: Map) -> dict[int, tuple[int, int]]:
    """Per experience run: (keyframes of later repeats it gave inliers to, number of those repeats)."""
    if not _has_table(m, "experience_use"):
        return {}
    with m.file.connection() as conn:
        rows = conn.execute(
            "SELECT experience, SUM(keyframes), COUNT(*) FROM experience_use GROUP BY experience"
        ).fetchall()
    return {int(r[0]): (int(r[1]), int(r[2])) for r in rows}


def _localized_counts(m: Map) -> dict[int, int]:
    """Per run: its vertices with a spatial edge to a taught (privileged) vertex."""
    with m.file.connection() as conn:
        rows = conn.execute(
            "SELECT e.from_id >> 32, COUNT(DISTINCT e.from_id) FROM edges e JOIN runs t ON t.id = (e.to_id >> 32) "
            "WHERE e.kind = 'spatial' AND t.privileged = 1 GROUP BY e.from_id >> 32"
        ).fetchall()
    return {int(r[0]): int(r[1]) for r in rows}


def experiences(m: Map, min_localized_share: float, exclude: Iterable[int] = ()) -> list[ExperienceInfo]:
    """Every repeat run of the map (but ``exclude``, e.g. the repeat under way) as an experience, in run order.

    Trusted: finished (not aborted, interrupted or still running) with at least ``min_localized_share`` of its
    vertices localized against the taught path. Its vertices link to the taught path only through spatial
    edges, and a repeat writes one only for a localization every integrity gate accepted, so a refused one never
    brings an experience in.
    """
    skip = {int(r) for r in exclude}
    localized = _localized_counts(m)
    use = use_counts(m)
    out = []
    for r in m.runs():
        if r.privileged or r.kind != "repeat" or r.id in skip:
            continue
        n_loc = localized.get(r.id, 0)
        share = n_loc / r.n_vertices if r.n_vertices else 0.0
        why = ""
        if r.state != RUN_FINISHED:
            why = r.describe()
        elif share < min_localized_share:
            why = f"localized {n_loc} of {r.n_vertices} keyframes ({share:.0%} < {min_localized_share:.0%})"
        used = use.get(r.id, (0, 0))
        out.append(ExperienceInfo(r.id, r.state, r.n_vertices, n_loc, not why, why, used[0], used[1]))
    return out


def experience_links(m: Map, runs: Iterable[int]) -> ExperienceLinks:
    """The spatial edges from the vertices of ``runs`` to taught vertices, ordered by experience vertex."""
    runs = sorted({int(r) for r in runs})
    rows: list = []
    if runs:
        marks = ",".join("?" * len(runs))
        with m.file.connection() as conn:
            rows = conn.execute(
                "SELECT e.from_id, e.to_id, e.T_from_to, e.inliers, e.covariance FROM edges e "
                "JOIN runs t ON t.id = (e.to_id >> 32) "
                f"WHERE e.kind = 'spatial' AND t.privileged = 1 AND (e.from_id >> 32) IN ({marks}) "
                "ORDER BY e.from_id, e.to_id",
                runs,
            ).fetchall()
    vid = np.array([r[0] for r in rows], np.int64)
    T = np.stack([blob_matrix(r[2], (4, 4)) for r in rows]) if rows else np.zeros((0, 4, 4))
    C = np.stack([blob_matrix(r[4], (6, 6)) for r in rows]) if rows else np.zeros((0, 6, 6))
    return ExperienceLinks(
        vid, vid >> RUN_SHIFT, np.array([r[1] for r in rows], np.int64), T, C, np.array([r[3] for r in rows], np.int64)
    )


@dataclass(frozen=True)
class Retention:
    """What the retention rule keeps and removes (repeat run ids), and why each kept one is kept."""

    keep: dict[int, str]
    remove: list[int]


def retention(
    m: Map, keep_last: int, keep_most_used: int, min_localized_share: float, neighbours: int = 1
) -> Retention:
    """The retention rule: of the trusted experiences keep, at every taught vertex, the ``keep_last`` newest localized
    within ``neighbours`` taught vertices of it (the vertices whose experiences a submap there may use), plus the
    ``keep_most_used`` most used (ties: the newer); every other repeat run that is not running (older experiences,
    untrusted repeats: aborted, interrupted, localized too little) is removed."""
    infos = experiences(m, min_localized_share, exclude=[m.open_run] if m.open_run is not None else [])
    trusted = [e.run for e in infos if e.trusted]
    keep: dict[int, str] = {}
    links = experience_links(m, trusted)
    if keep_last > 0 and len(links):
        slot = np.searchsorted(m.taught_path().ids, links.taught_id)  # path index of each link's taught vertex
        near = np.concatenate([slot + d for d in range(-neighbours, neighbours + 1)])
        pairs = np.unique(np.stack([near, np.tile(links.run, 2 * neighbours + 1)], 1), axis=0)  # (vertex, run)
        pairs = pairs[np.lexsort((-pairs[:, 1], pairs[:, 0]))]  # by taught vertex, newest run first
        first = np.r_[0, np.flatnonzero(np.diff(pairs[:, 0])) + 1]
        rank = np.arange(len(pairs)) - np.repeat(first, np.diff(np.r_[first, len(pairs)]))
        for r in np.unique(pairs[rank < keep_last, 1]):
            keep[int(r)] = f"among the {keep_last} newest at a taught vertex"
    used = sorted((e for e in infos if e.trusted and e.used_keyframes > 0), key=lambda e: (-e.used_keyframes, -e.run))
    for e in used[:keep_most_used]:
        keep.setdefault(e.run, f"among the {keep_most_used} most used ({e.used_keyframes} keyframes)")
    remove = [e.run for e in infos if e.run not in keep and e.state != "running"]
    return Retention(keep, remove)


#: derived data of an experience (its vertices' place-recognition words), under ``experience_words/<run>/...``:
#: removed with the run (a later run may take its id)
WORDS_KEY = "experience_words"


def prune(m: Map, runs: Iterable[int]) -> int:
    """Remove repeat ``runs`` from a map opened for writing: their vertices, data, checksums, edges, localization
    records and use, in one transaction (the append-only triggers are lifted inside it and restored before it
    commits), then ``VACUUM`` to give the space back (the file shrinks when the map is closed, which folds the
    log). Returns the number of vertices removed. Refuses taught runs and the open run."""
    runs = sorted({int(r) for r in runs})
    if m.mode != "a":
        raise MapError(f"{m.path}: map opened read-only (open it with mode='a' to prune)")
    if not runs:
        return 0
    by_id = {r.id: r for r in m.runs()}
    for r in runs:
        info = by_id.get(r)
        if info is None:
            raise MapError(f"{m.path}: no run {r}")
        if info.privileged or info.kind != "repeat":
            raise MapError(f"{m.path}: run {r} is a taught run: prune removes repeats only")
        if r == m.open_run:
            raise MapError(f"{m.path}: run {r} is the open run")
    removed = sum(by_id[r].n_vertices for r in runs)
    with m.file.transaction() as conn:
        saved = conn.execute(
            f"SELECT name, sql FROM sqlite_master WHERE type = 'trigger' AND name IN "
            f"({','.join('?' * len(APPEND_ONLY_TRIGGERS))})",
            APPEND_ONLY_TRIGGERS,
        ).fetchall()
        for name, _ in saved:
            conn.execute(f"DROP TRIGGER {name}")
        has_sums = (
            conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'vertex_checksums'").fetchone()
            is not None
        )
        has_use = (
            conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'experience_use'").fetchone()
            is not None
        )
        has_derived = (
            conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'derived'").fetchone() is not None
        )
        has_records = localizations.has_table(conn)
        for r in runs:
            lo, hi = r << RUN_SHIFT, (r << RUN_SHIFT) | INDEX_MASK
            conn.execute("DELETE FROM edges WHERE from_id BETWEEN ? AND ? OR to_id BETWEEN ? AND ?", (lo, hi, lo, hi))
            if has_records:
                conn.execute(f"DELETE FROM {localizations.TABLE} WHERE leaf_id BETWEEN ? AND ?", (lo, hi))
            if has_sums:
                conn.execute("DELETE FROM vertex_checksums WHERE id BETWEEN ? AND ?", (lo, hi))
            conn.execute("DELETE FROM vertex_data WHERE id BETWEEN ? AND ?", (lo, hi))
            conn.execute("DELETE FROM vertices WHERE id BETWEEN ? AND ?", (lo, hi))
            if has_use:
                conn.execute("DELETE FROM experience_use WHERE experience = ? OR repeat = ?", (r, r))
            if has_derived:  # the run's words: the next run takes the highest free id, maybe this one
                conn.execute("DELETE FROM derived WHERE key LIKE ?", (f"{WORDS_KEY}/{r}/%",))
            conn.execute("DELETE FROM runs WHERE id = ?", (r,))
        for _, sql in saved:
            conn.execute(sql)
    with m.file.connection() as conn:
        conn.execute("VACUUM")
    return removed


__all__ = [
    "WORDS_KEY",
    "ExperienceInfo",
    "ExperienceLinks",
    "Retention",
    "experience_links",
    "experiences",
    "prune",
    "retention",
    "use_counts",
]
