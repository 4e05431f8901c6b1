"""The durable pose-graph map (:class:`Map`): one SQLite file of runs, keyframe vertices and edges, written by one
process at a time and read by any. This module holds the map's lifecycle and queries; :mod:`vtr.map.writing` its
writes (one transaction per vertex, a repeat's leaf with its localization record), :mod:`vtr.map.reading` its vertex
and edge reads (a bounded cache of decoded vertices), :mod:`vtr.map.database` the file layer (exclusive creation,
writer lock, WAL folded on close so a closed map is one self-contained file). Vertices, edges, durability and the
run lifecycle (running, finished, aborted, interrupted): docs/map.md."""

from __future__ import annotations

import json
from collections import OrderedDict
from contextlib import AbstractContextManager
from pathlib import Path
from types import TracebackType

import numpy as np
from numpy.typing import ArrayLike

from .. import __version__
from ..camera import StereoCamera
from ..config import MapConfig
from ..errors import MapError, UnfinishedRouteError
from . import checksums, damage, localizations
from .database import Connection, MapFile
from .localizations import LocalizationRecord
from .path import TaughtPath
from .reading import MapReading
from .records import (
    GRAVITY_META_KEY,
    INDEX_MASK,
    RUN_FINISHED,
    RUN_INTERRUPTED,
    RUN_RUNNING,
    RunInfo,
    VertexRecord,
    abort_reason,
    check_gravity_up,
    check_int,
    check_run_row,
    run_range,
    utc_now,
    vertex_id,
)
from .schema import DERIVED_TABLE, SCHEMA
from .writing import INTERRUPTED_REASON, MapWriting

MAP_FORMAT_VERSION = 3  # 3: run lifecycle state, abort reason; 2: raw descriptors (vtr.map.codec)
VERTEX_CACHE_SIZE = 64  # decoded vertices kept by Map.vertex (a -10..+20 window is 31)
MODES = ("r", "a")
# re-exported: vtr.map.store has always named them
__all__ = [
    "GRAVITY_META_KEY",
    "INTERRUPTED_REASON",
    "MAP_FORMAT_VERSION",
    "MODES",
    "VERTEX_CACHE_SIZE",
    "Map",
    "abort_reason",
    "check_gravity_up",
]


class Map(MapReading, MapWriting):
    """A pose-graph map file. Use :meth:`create` or :meth:`open`; a context manager.

    ``camera`` is the rectified stereo calibration the map was taught with; ``path`` the file.
    """

    def __init__(
        self,
        file: MapFile,
        mode: str,
        camera: StereoCamera,
        meta: dict[str, str],
        cache_size: int,
        created: bool = False,
    ) -> None:
        self.path = file.path
        self.mode = mode
        self.camera = camera
        self.meta = dict(meta)
        self.format_version = int(meta["format_version"])
        self.created = created  # this session created the file (it may remove it if left empty)
        self._file = file
        self._lock = file.lock
        self._compress_level = int(meta.get("compress_level", MapConfig().compress_level))
        self._cache: OrderedDict[int, VertexRecord] = OrderedDict()
        self._cache_size = check_int(cache_size, "cache_size", 1)
        self._generation = 0  # bumps when the privileged path grows (invalidates its caches)
        self._path_cache: tuple[int, TaughtPath] | None = None
        self._open_run: int | None = None
        self._open_run_privileged = False
        self._open_run_touched = False  # this session began or wrote to the open run
        self._aborted = False  # this session aborted a run
        assert file.conn is not None  # verified on every read (vtr.map.checksums); damaged metadata refused
        self._checksums = checksums.checksummed(file.conn, str(file.path))
        if mode == "a":
            # we hold the writer lock, so a run still marked running was left by a killed writer: it stays
            # the open run (writing to it resumes it) until a new run begins
            assert file.conn is not None
            row = file.conn.execute("SELECT id, state, privileged FROM runs ORDER BY id DESC LIMIT 1").fetchone()
            if row is not None and row[1] == RUN_RUNNING:
                self._open_run, self._open_run_privileged = int(row[0]), bool(row[2])

    # ------------------------------------------------------------ opening

    @classmethod
    def create(
        cls,
        path: str | Path,
        camera: StereoCamera,
        config: MapConfig | None = None,
        *,
        cache_size: int = VERTEX_CACHE_SIZE,
        gravity_up: ArrayLike | None = None,
    ) -> Map:
        """Create a new, empty map at ``path`` (opened for appending). Refuses to overwrite anything.

        Atomic and exclusive (:meth:`vtr.map.database.MapFile.create`): the schema is written to a
        temporary file in the same folder and hard-linked to ``path``, which fails when ``path`` exists;
        of several processes creating one map exactly one succeeds, the others get "already exists" and
        remove only their own temporary file. The new map is locked for writing before its name appears.

        ``gravity_up`` (3,): the up direction (opposite to gravity) in the map frame, i.e. seen from the teach
        run's first left camera; kept in the map (:attr:`gravity_up`) for every later reader.
        """
        path = Path(path)
        up = None if gravity_up is None else check_gravity_up(gravity_up, "gravity_up")
        check_int(cache_size, "cache_size", 1)
        config = config or MapConfig()
        level = check_int(config.compress_level, "map.compress_level", 0)
        if level > 9:
            raise MapError(f"map.compress_level: {level} > 9")
        if not isinstance(camera, StereoCamera):
            raise MapError(f"camera: expected a StereoCamera, got {type(camera).__name__}")
        meta = {
            "format_version": str(MAP_FORMAT_VERSION),
            "camera": json.dumps(camera.to_dict()),
            "created": utc_now(),
            "vtr_version": __version__,
            "compress_level": str(level),
            checksums.META_KEY: checksums.META_VALUE,  # every vertex has checksums (vtr.map.checksums)
        }
        if up is not None:
            meta[GRAVITY_META_KEY] = json.dumps([float(x) for x in up])
        return MapFile.create(
            path, SCHEMA + checksums.SCHEMA, meta, lambda file: cls(file, "a", camera, meta, cache_size, created=True)
        )

    @classmethod
    def open(cls, path: str | Path, mode: str = "r", *, cache_size: int = VERTEX_CACHE_SIZE) -> Map:
        """Open an existing map: ``mode="r"`` read-only (writes raise ``MapError``), ``"a"`` to append runs.

        ``"a"`` takes the map's writer lock (``MapError`` "another process is writing this map" when
        another session holds it). ``"r"`` works on read-only files and folders too.
        """
        if mode not in MODES:
            raise MapError(f"map open mode must be one of {MODES}, got {mode!r}")
        check_int(cache_size, "cache_size", 1)
        path = Path(path)

        def check(meta: dict[str, str]) -> tuple[dict[str, str], StereoCamera]:
            if "format_version" not in meta:
                raise MapError(f"{path} is not a vtr map (no format version)")
            version = int(meta["format_version"])
            if version != MAP_FORMAT_VERSION:
                hint = (
                    "written by a newer vtr: upgrade vtr"
                    if version > MAP_FORMAT_VERSION
                    else "written by an older vtr: teach it again"
                )
                raise MapError(
                    f"{path}: map format version {version}, this vtr {__version__} reads only "
                    f"format version {MAP_FORMAT_VERSION} ({hint})"
                )
            return meta, StereoCamera.from_dict(json.loads(meta["camera"]))

        return MapFile.open(
            path, mode == "a", check, lambda file, checked: cls(file, mode, checked[1], checked[0], cache_size)
        )

    def close(self) -> None:
        """Finish the run this session wrote (it becomes immutable), fold the write-ahead log into the
        file and close it. A map this session created whose only run it aborted with no vertex is
        removed (a teach that wrote nothing leaves no file). Idempotent.

        Raises ``MapError`` when the log cannot be folded back (disk full): the file is then still
        valid together with its ``-wal`` beside it.
        """
        with self._lock:
            conn = self._file.conn
            if conn is None:
                return
            discard = False
            try:
                if self.mode == "a":
                    if self._open_run is not None and self._open_run_touched:
                        self._set_state(self._open_run, RUN_FINISHED, "")
                    discard = (
                        self.created
                        and self._aborted
                        and conn.execute("SELECT COUNT(*) FROM vertices").fetchone()[0] == 0
                    )
                    if not discard:
                        self._file.fold_wal()
            finally:
                self._file.close(remove=discard)
                self._cache.clear()

    def __enter__(self) -> Map:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Normal exit finishes the open run; an exception (Ctrl-C, SIGTERM too) aborts it with its reason."""
        if (
            exc is not None
            and not self.closed
            and self.mode == "a"
            and self._open_run is not None
            and self._open_run_touched
        ):
            try:
                self.abort_run(abort_reason(exc))
            except MapError:
                pass  # cannot write (disk full): the run stays running and reads as interrupted
        try:
            self.close()
        except MapError:
            if exc is None:
                raise  # else the first error is the one to report

    def __repr__(self) -> str:
        state = "closed" if self._file.closed else f"mode={self.mode!r}"
        return f"Map({str(self.path)!r}, {state})"

    @property
    def closed(self) -> bool:
        return self._file.closed

    def not_closed(self) -> str | None:
        """Why the map file alone is not the whole map: committed data left in its write-ahead log by a writer
        that was killed (a copy of the file without its ``-wal`` would lose it). None when the file is whole or a
        live writer holds the map (its log is expected). A writer (mode ``"a"``) folds such a log on open;
        ``vtr map check --repair`` does that."""
        if self.mode == "a" or self._file.writer_alive():
            return None
        pages = self._file.unfolded_pages()
        if not pages:
            return None
        return (
            f"not closed: {pages} page(s) committed in {self.path.name}-wal are not in the map file (its "
            f"writer was killed); run `vtr map check --repair` to fold them in (until then keep the -wal "
            "beside it: a copy of the map file alone lacks them)"
        )

    @property
    def gravity_up(self) -> np.ndarray | None:
        """Unit up direction (3,) in the map frame (the teach run's first left camera), as taught (``vtr teach
        --up``, or a source that knows its mount); None for a map taught without it: readers then take the first
        camera as level (up = its -y). MapError when the stored value is damaged."""
        raw = self.meta.get(GRAVITY_META_KEY)
        if raw is None:
            return None
        try:
            value = json.loads(raw)
        except ValueError:
            raise MapError(f"{self.path}: damaged gravity direction in the map's meta table: {raw[:40]!r}") from None
        return check_gravity_up(value, f"{self.path}: the map's gravity direction", MapError)

    @property
    def open_run(self) -> int | None:
        """The run new vertices go to (``None`` when read-only or when no run is open)."""
        return self._open_run

    def check_camera(self, camera: StereoCamera) -> None:
        """Raise ``MapError`` unless ``camera`` is the calibration the map was taught with."""
        if not camera.matches(self.camera):
            m, c = self.camera, camera
            raise MapError(
                f"map was taught with another camera: {self.path} has {m.width}x{m.height} fx={m.fx:.6g} "
                f"fy={m.fy:.6g} cx={m.cx:.6g} cy={m.cy:.6g} baseline={m.baseline:.6g} m, the input has "
                f"{c.width}x{c.height} fx={c.fx:.6g} fy={c.fy:.6g} cx={c.cx:.6g} cy={c.cy:.6g} "
                f"baseline={c.baseline:.6g} m"
            )

    # ------------------------------------------------------------ database access

    @property
    def file(self) -> MapFile:
        """The open map file (:mod:`vtr.map.database`): its SQLite connection and writer lock."""
        return self._file

    def _db(self) -> AbstractContextManager[Connection]:
        """The connection under the lock, with SQLite errors turned into ``MapError``."""
        return self._file.connection()

    def _tx(self) -> AbstractContextManager[Connection]:
        """One write transaction: committed when the block ends, rolled back on any error."""
        return self._file.transaction()

    def _check_writable(self) -> None:
        if self._file.closed:
            raise MapError(f"{self.path}: map is closed")
        if self.mode != "a":
            raise MapError(f"{self.path}: map opened read-only (open it with mode='a' to write)")

    def _check_open_run(self, run: int, what: str) -> None:
        if self._open_run is None:
            raise MapError(f"{self.path}: {what}: no open run (call begin_run first); finished runs are immutable")
        if run != self._open_run:
            raise MapError(
                f"{self.path}: {what}: run {run} is not the open run ({self._open_run}); finished runs are immutable"
            )

    def _run_row(self, conn: Connection, run: int) -> tuple:
        row = conn.execute("SELECT id, kind, privileged FROM runs WHERE id = ?", (int(run),)).fetchone()
        if row is None:
            raise MapError(f"{self.path}: no run {run}")
        return row

    # ------------------------------------------------------------ reading

    def next_vertex_id(self, run: int) -> int:
        """The id the next vertex of ``run`` gets."""
        lo, hi = run_range(check_int(run, "run", 0))
        with self._db() as conn:
            last = conn.execute("SELECT MAX(id) FROM vertices WHERE id BETWEEN ? AND ?", (lo, hi)).fetchone()[0]
        return lo if last is None else vertex_id(run, (int(last) & INDEX_MASK) + 1)

    def localization_records(self, run: int) -> list[LocalizationRecord]:
        """The localization records of repeat ``run``'s vertices in vertex order (:mod:`vtr.map.localizations`;
        none for a run written before the map kept them)."""
        with self._db() as conn:
            self._run_row(conn, check_int(run, "run", 0))
            return localizations.read(conn, run)

    def localization_count(self, run: int) -> int:
        """How many localization records repeat ``run`` has."""
        with self._db() as conn:
            return localizations.count(conn, check_int(run, "run", 0))

    def runs(self) -> list[RunInfo]:
        """All runs in id order, with their vertex counts and lifecycle state (see ``RunInfo``)."""
        with self._db() as conn:
            rows = conn.execute(
                "SELECT r.id, r.kind, r.privileged, r.source, r.created, r.state, r.reason, "
                "(SELECT COUNT(*) FROM vertices v WHERE v.id BETWEEN (r.id << 32) AND ((r.id << 32) | ?)) "
                "FROM runs r ORDER BY r.id",
                (INDEX_MASK,),
            ).fetchall()
        for r in rows:
            check_run_row(self.path, r)
        return [
            RunInfo(
                id=int(r[0]),
                kind=r[1],
                privileged=bool(r[2]),
                source=r[3],
                created=r[4],
                n_vertices=int(r[7]),
                state=self._seen_state(int(r[0]), r[5]),
                reason=r[6],
            )
            for r in rows
        ]

    def _seen_state(self, run: int, stored: str) -> str:
        """A stored state as it stands: ``running`` only while a live session writes the run."""
        if stored != RUN_RUNNING:
            return stored
        if self.mode == "a":  # we are the only writer
            return RUN_RUNNING if run == self._open_run and self._open_run_touched else RUN_INTERRUPTED
        alive = self._file.writer_alive()
        return RUN_RUNNING if alive else RUN_INTERRUPTED

    def run(self, run: int) -> RunInfo:
        """One run's info (``MapError`` if absent)."""
        for info in self.runs():
            if info.id == run:
                return info
        raise MapError(f"{self.path}: no run {run}")

    def check_taught_route(self, allow_partial: bool = False) -> None:
        """Raise ``MapError`` (one line) unless every taught (privileged) run is finished: an aborted,
        interrupted or still running teach is a route that may be cut short. ``allow_partial``
        accepts them anyway."""
        if allow_partial:
            return
        for r in self.runs():
            if r.privileged and not r.finished:
                raise UnfinishedRouteError(
                    f"{self.path}: teach run {r.id} is {r.describe()}, not finished", r.n_vertices
                )

    # ------------------------------------------------------------ the privileged path

    def _privileged(self) -> TaughtPath:
        with self._lock:
            cached = self._path_cache
            if cached is not None and cached[0] == self._generation:
                return cached[1]
            with self._db() as conn:
                rows = conn.execute(
                    "SELECT v.id, v.T_world_vertex, v.t_ns FROM vertices v JOIN runs r ON r.id = v.run "
                    "WHERE r.privileged = 1 ORDER BY v.id"
                ).fetchall()
                damage.check_vertex_runs(conn, str(self.path))
                if self._checksums:
                    for (run,) in conn.execute("SELECT id FROM runs WHERE privileged = 1").fetchall():
                        checksums.verify_rows(conn, str(self.path), *run_range(int(run)))
            ids, T = self._pose_arrays(rows)
            path = TaughtPath(ids, T, np.array([r[2] for r in rows], dtype=np.int64))
            damage.check_taught_path(str(self.path), path)
            with self._db() as conn:
                damage.check_path_edges(conn, str(self.path), path)
            self._path_cache = (self._generation, path)
            return path

    def taught_path(self) -> TaughtPath:
        """The privileged (teach) vertices in path order (run, then index), from the pose index only.

        Raises ``MapError`` "map has no taught run" when there is no privileged vertex.
        """
        path = self._privileged()
        if len(path) == 0:
            raise MapError(f"{self.path}: map has no taught run (no privileged vertices)")
        return path

    # ------------------------------------------------------------ export

    def reference_run(self) -> int | None:
        """The first privileged run: its world frame is the map frame of exports (``None`` if none)."""
        for info in self.runs():
            if info.privileged:
                return info.id
        return None

    # ------------------------------------------------------------ derived data

    def derived(self, key: str) -> bytes | None:
        """Derived data stored under ``key`` (e.g. the taught route's place index), None when absent.

        Derived data (table ``derived``) is computed from the vertices and may be rebuilt from them at any
        time: a map written before a kind of derived data existed simply has none.
        """
        with self._db() as conn:
            if conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'derived'").fetchone() is None:
                return None
            row = conn.execute("SELECT data FROM derived WHERE key = ?", (str(key),)).fetchone()
        return None if row is None else bytes(row[0])

    def put_derived(self, key: str, data: bytes) -> None:
        """Store (or replace) derived data under ``key``; needs a map opened for writing."""
        self._check_writable()
        with self._tx() as conn:
            conn.execute(DERIVED_TABLE)
            conn.execute("INSERT OR REPLACE INTO derived(key, data) VALUES (?, ?)", (str(key), bytes(data)))

    def stats(self) -> dict:
        """Counts and size: runs, vertices, features, landmarks, edges (and by kind), bytes on disk."""
        with self._db() as conn:
            n_runs = conn.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
            n_v, n_f, n_l = conn.execute(
                "SELECT COUNT(*), COALESCE(SUM(n_features), 0), COALESCE(SUM(n_landmarks), 0) FROM vertices"
            ).fetchone()
            by_kind = dict(conn.execute("SELECT kind, COUNT(*) FROM edges GROUP BY kind").fetchall())
        return {
            "path": str(self.path),
            "format_version": self.format_version,
            "runs": int(n_runs),
            "vertices": int(n_v),
            "features": int(n_f),
            "landmarks": int(n_l),
            "edges": int(sum(by_kind.values())),
            "temporal_edges": int(by_kind.get("temporal", 0)),
            "spatial_edges": int(by_kind.get("spatial", 0)),
            "bytes": self.bytes_on_disk(),
        }

    def bytes_on_disk(self) -> int:
        """Size of the map file plus its write-ahead log, bytes."""
        return self._file.bytes_on_disk()
