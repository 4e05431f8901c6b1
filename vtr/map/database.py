"""The file layer of a map: one SQLite file, its connection, its writer lock and its lifecycle on disk.

This is the only module of ``vtr`` that talks to SQLite and the operating system about a map file;
:class:`vtr.map.store.Map` keeps the map's meaning (runs, vertices, edges, paths, derived data) and
reaches the file through :class:`MapFile`.

- Creation is exclusive: the schema is written to a temporary file beside the target, which is then
  hard-linked to the final name (fails if the name exists); without hard links the target is created
  with ``O_EXCL`` and the bytes copied. Of two processes creating one map exactly one wins and the
  other's cleanup never touches the winner's file. The new file is locked for writing before its name
  appears.
- One writing process at a time: a writable :class:`MapFile` holds the map's ``flock``
  (:class:`vtr.map.lock.MapLock`); a read-only one keeps a descriptor to probe it.
- Durability: WAL journal while writing, ``synchronous=FULL``; :meth:`MapFile.transaction` is one
  ``BEGIN IMMEDIATE`` ... ``COMMIT``. :meth:`MapFile.fold_wal` folds the write-ahead log back into
  the file and returns it to a rollback journal, so a closed map is one self-contained file.
- Read-only opening: ``mode=ro`` (sees a live writer's commits), else ``immutable=1`` for a closed
  map on read-only media (refused when a write-ahead log with data lies beside it).
"""

from __future__ import annotations

import os
import secrets
import sqlite3
import struct
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TypeVar

from perception_model.inputs import input_problem

from ..errors import MapError, VtrError
from .lock import MapLock

APPLICATION_ID = 0x56545231  # "VTR1" in the SQLite header marks the file as a vtr map
SQLITE_MAGIC = b"SQLite format 3\x00"
BUSY_TIMEOUT_MS = 10_000  # wait for another connection's write lock before failing
SYNCHRONOUS = "FULL"  # fsync the WAL at every commit: durable across power loss too
SIDE_FILES = ("-wal", "-shm", "-journal")  # SQLite's files beside a map
CREATING_SUFFIX = ".creating"  # temporary name of a map being created (hard-linked when complete)
NEW_FILE_MODE = 0o666  # a created map's mode before the umask (as open(2) makes files)
COPIED_FILE_MODE = 0o644  # mode of a map created by copy where hard links are missing
# the write-ahead log's format (sqlite.org/fileformat2.html#the_write_ahead_log): a 32-byte header, then frames of
# a 24-byte header and one page; the magic's last bit says whether checksums are big-endian
WAL_MAGIC = (0x377F0682, 0x377F0683)
WAL_HEADER = struct.Struct(">IIIIIIII")  # magic, version, page size, checkpoint seq, salt-1, salt-2, cksum-1, -2
WAL_FRAME = struct.Struct(">IIIIII")  # page number, db size after commit (0: not a commit), salts, checksums
WAL_WORD_MASK = 0xFFFFFFFF
WAL_MIN_PAGE_SIZE = 512  # SQLite's smallest page: a header with less is not a log

Connection = sqlite3.Connection  # an open map file's SQLite connection (``MapFile.conn``)

T = TypeVar("T")
M = TypeVar("M")


def connect(path: Path, readonly: bool, immutable: bool = False) -> Connection:
    """A connection; read-only ones through an ``mode=ro`` URI, or ``immutable=1`` (no locks, no
    -shm: for a closed map on read-only media)."""
    if readonly:
        target, uri = path.absolute().as_uri() + ("?immutable=1" if immutable else "?mode=ro"), True
    else:
        target, uri = str(path), False
    conn = sqlite3.connect(
        target, uri=uri, isolation_level=None, check_same_thread=False, timeout=BUSY_TIMEOUT_MS / 1000
    )
    conn.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
    conn.execute("PRAGMA foreign_keys = ON")
    if readonly:
        conn.execute("PRAGMA query_only = ON")
    else:
        conn.execute(f"PRAGMA synchronous = {SYNCHRONOUS}")
    return conn


def _read_only_storage(err: BaseException) -> bool:
    """Whether ``err`` is SQLite (or the OS) refusing to write a read-only file or folder."""
    if isinstance(err, PermissionError):
        return True
    return isinstance(err, sqlite3.OperationalError) and ("readonly" in str(err) or "unable to open" in str(err))


def connect_readonly(path: Path) -> Connection:
    """Read-only connection: ``mode=ro`` (sees a live writer's commits and a killed writer's log); when
    that cannot open (a WAL-mode file on read-only media, no -shm), ``immutable=1`` provided no
    write-ahead log with data lies beside the file."""
    conn = connect(path, readonly=True)
    try:
        conn.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()
        return conn
    except sqlite3.OperationalError as err:
        conn.close()
        wal = Path(f"{path}-wal")
        if wal.exists() and wal.stat().st_size > 0:
            raise MapError(
                f"{path}: cannot open read-only ({err}) and {wal.name} holds data not yet in the map: "
                "open it once where it can be written (vtr map info on a writable copy of both files)"
            ) from err
    return connect(path, readonly=True, immutable=True)


def _wal_checksum(data: bytes, s0: int, s1: int, big_endian: bool) -> tuple[int, int]:
    """SQLite's cumulative WAL checksum over ``data`` (a multiple of 8 bytes), continuing ``(s0, s1)``."""
    words = struct.unpack(f"{'>' if big_endian else '<'}{len(data) // 4}I", data)
    for x0, x1 in zip(words[0::2], words[1::2], strict=True):
        s0 = (s0 + x0 + s1) & WAL_WORD_MASK
        s1 = (s1 + x1 + s0) & WAL_WORD_MASK
    return s0, s1


def unfolded_wal_pages(path: Path) -> int:
    """How many pages committed in the write-ahead log beside ``path`` differ from the map file itself: 0 when the
    file alone holds everything (no log, an empty one, only uncommitted or already folded frames), else the data
    a copy of the file alone would lose. Reads the log as SQLite's recovery does (salts and checksums, up to its
    last valid commit); never writes."""
    wal = Path(f"{path}-wal")
    try:
        log = wal.read_bytes()
    except FileNotFoundError:
        return 0
    except OSError as err:
        raise MapError(f"{wal}: cannot read the map's write-ahead log ({err})") from err
    if len(log) < WAL_HEADER.size:
        return 0
    magic, _version, page_size, _seq, salt1, salt2, c0, c1 = WAL_HEADER.unpack_from(log)
    if magic not in WAL_MAGIC or page_size < WAL_MIN_PAGE_SIZE or page_size & (page_size - 1):
        return 0
    big = magic == WAL_MAGIC[1]
    s = _wal_checksum(log[: WAL_HEADER.size - 8], 0, 0, big)
    if s != (c0, c1):
        return 0  # SQLite ignores a log whose header is not valid
    pages: dict[int, int] = {}  # page number -> offset of its latest committed frame
    pending: dict[int, int] = {}
    db_pages = 0
    off = WAL_HEADER.size
    while off + WAL_FRAME.size + page_size <= len(log):
        pgno, commit, f1, f2, k0, k1 = WAL_FRAME.unpack_from(log, off)
        if (f1, f2) != (salt1, salt2):
            break
        s = _wal_checksum(log[off : off + 8], *s, big)
        s = _wal_checksum(log[off + WAL_FRAME.size : off + WAL_FRAME.size + page_size], *s, big)
        if s != (k0, k1):
            break
        pending[pgno] = off + WAL_FRAME.size
        if commit:
            pages.update(pending)
            pending.clear()
            db_pages = commit
        off += WAL_FRAME.size + page_size
    if not pages:
        return 0
    differ = 0
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size < db_pages * page_size:
            return max(1, db_pages - os.fstat(f.fileno()).st_size // page_size)
        for pgno, at in pages.items():
            if pgno > db_pages:
                continue  # truncated away by a later commit
            f.seek((pgno - 1) * page_size)
            differ += f.read(page_size) != log[at : at + page_size]
    return differ


def check_side_files(path: Path) -> None:
    """``MapError`` naming a side file of the map (``-wal``, ``-shm``, ``-journal``) that is a symbolic link or not a
    regular file: SQLite would follow it (writing the log elsewhere) or fail with a message that blames the map."""
    for suffix in SIDE_FILES:
        side = Path(f"{path}{suffix}")
        if side.is_symlink():
            raise MapError(
                f"{side}: SQLite's {suffix[1:]} file beside the map is a symbolic link; a map's side files "
                "are never read or written through a link (remove it; the map itself is untouched)"
            )
        if side.exists() and not side.is_file():
            raise MapError(f"{side}: SQLite's {suffix[1:]} file beside the map is not a regular file (remove it)")


def remove_map_files(path: Path) -> None:
    """Unlink a map and its SQLite side files (only for a map this process created and holds)."""
    for p in (path, *(Path(f"{path}{s}") for s in SIDE_FILES)):
        p.unlink(missing_ok=True)


def copy_map_file(src: Path, dst: Path) -> None:
    """Copy a closed map file consistently to ``dst`` (SQLite's online backup: WAL content included)."""
    s, d = sqlite3.connect(src), sqlite3.connect(dst)  # read-write: the last one out removes the WAL files
    try:
        s.backup(d)
    finally:
        d.close()
        s.close()


def copy_map_read_only(src: Path, dst: Path) -> None:
    """Copy the map ``src`` whole to the new file ``dst`` (SQLite's online backup through a read-only connection:
    what a killed writer left in its write-ahead log is included; ``src`` and its folder are never written)."""
    s = connect_readonly(src)
    try:
        d = sqlite3.connect(dst)
        try:
            s.backup(d)
        finally:
            d.close()
    except sqlite3.Error as err:
        raise MapError(f"{src}: cannot copy the map to {dst} ({err})") from err
    finally:
        s.close()


def bytes_on_disk(path: Path) -> int:
    """Size of a map file plus its write-ahead log, bytes."""
    total = 0
    for p in (path, Path(f"{path}-wal")):
        try:
            total += p.stat().st_size
        except FileNotFoundError:
            pass
    return total


def _create_by_copy(tmp: Path, path: Path, tmp_lock: MapLock) -> MapLock:
    """``path`` created exclusively (``O_EXCL``) with ``tmp``'s bytes; returns the lock on it."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, COPIED_FILE_MODE)
    except FileExistsError:
        raise MapError(
            f"{path} already exists: refusing to overwrite a map (another process created it "
            "first, or remove it and choose another path)"
        ) from None
    try:
        lock = MapLock.writer(path, os.open(path, os.O_RDONLY))
    except BaseException:
        os.close(fd)
        path.unlink(missing_ok=True)
        raise
    try:
        os.write(fd, tmp.read_bytes())
        os.fsync(fd)
    except BaseException:
        path.unlink(missing_ok=True)
        lock.release()
        raise
    finally:
        os.close(fd)
    tmp_lock.release()
    return lock


@contextmanager
def transaction(conn: Connection, path: Path | None = None) -> Iterator[Connection]:
    """One write transaction on ``conn``: ``BEGIN IMMEDIATE``, committed when the block ends, rolled back on any
    error. With ``path``, SQLite errors become ``MapError`` naming it."""
    try:
        conn.execute("BEGIN IMMEDIATE")
        try:
            yield conn
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        conn.execute("COMMIT")
    except sqlite3.Error as err:
        if path is None:
            raise
        raise MapError(f"{path}: {err}") from err


class MapFile:
    """An open map file: its SQLite connection ``conn``, its lock ``lock`` (shared with the ``Map`` on
    it) and its writer lock. Made by :meth:`create` or :meth:`open`; :meth:`close` ends it."""

    def __init__(self, path: Path, conn: Connection, writer_lock: MapLock) -> None:
        self.path = path
        self.conn: Connection | None = conn
        self.lock = threading.RLock()
        self._writer_lock: MapLock | None = writer_lock

    @classmethod
    def create(cls, path: Path, script: str, meta: dict[str, str], build: Callable[[MapFile], T]) -> T:
        """A new map file at ``path`` with the schema ``script`` and the ``meta`` table rows, in WAL mode
        and locked for writing; returns ``build(file)``. Refuses to overwrite anything.

        On any error (in ``build`` too) the files this call made are removed and its lock released.
        """
        if path.is_dir():
            raise MapError(
                f"{path} is a directory: a vtr map is one SQLite file, give a file path such as {path / 'route.vtrmap'}"
            )
        check_side_files(path)  # a dangling link there would take the new map's log elsewhere
        leftovers = [p for p in (path, Path(f"{path}-wal"), Path(f"{path}-journal")) if p.exists()]
        if leftovers:
            raise MapError(
                f"{leftovers[0]} already exists: refusing to overwrite a map (remove it or choose another path)"
            )
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise MapError(f"{path}: cannot create the map folder ({err})") from err
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(8)}{CREATING_SUFFIX}")
        try:  # a private name; the mode is the usual 0o666 less the umask (mkstemp would make it 0o600)
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), NEW_FILE_MODE)
        except OSError as err:
            raise MapError(f"{path}: cannot create the map ({err})") from err
        conn: Connection | None = None
        lock: MapLock | None = None
        linked = False
        try:
            lock = MapLock.writer(tmp, fd)
            conn = connect(tmp, readonly=False)
            conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            conn.executescript("BEGIN IMMEDIATE;" + script)
            conn.executemany("INSERT INTO meta(key, value) VALUES (?, ?)", sorted(meta.items()))
            conn.execute("COMMIT")
            conn.close()
            conn = None
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise MapError(
                    f"{path} already exists: refusing to overwrite a map (another process created it "
                    "first, or remove it and choose another path)"
                ) from None
            except OSError:  # no hard links on this file system: exclusive create, then copy
                lock = _create_by_copy(tmp, path, lock)
            linked = True
            tmp.unlink()
            conn = connect(path, readonly=False)
            mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise MapError(f"{path}: the file system does not support SQLite WAL mode (got {mode})")
            return build(cls(path, conn, lock))
        except BaseException as err:
            if conn is not None:
                conn.close()
            if linked:
                remove_map_files(path)  # ours: created by this call and still locked by it
            remove_map_files(tmp)
            if lock is not None:
                lock.release()
            else:
                with suppress(OSError):  # MapLock.writer closes it when it fails
                    os.close(fd)
            if isinstance(err, sqlite3.Error):
                raise MapError(f"{path}: cannot create map ({err})") from err
            if isinstance(err, OSError):
                raise MapError(f"{path}: cannot create map ({err})") from err
            raise

    @classmethod
    def open(
        cls, path: Path, writable: bool, check: Callable[[dict[str, str]], M], build: Callable[[MapFile, M], T]
    ) -> T:
        """Open the existing map file ``path``: its ``meta`` rows go through ``check`` (which raises for a
        map this vtr cannot read), then a writable file switches to WAL mode; returns
        ``build(file, check(meta))``.

        ``writable`` takes the writer lock (``MapError`` "another process is writing this map" when
        another session holds it); read-only works on read-only files and folders too. On any error
        the connection is closed and the lock released; SQLite and decoding errors become ``MapError``.
        """
        if not path.exists():
            raise MapError(f"no map at {path}")
        if path.is_dir():
            raise MapError(f"{path} is a directory, not a map file")
        problem = input_problem(path)  # a named pipe or a device would block the open below forever
        if problem is not None:
            raise MapError(f"{path}: {problem}")
        check_side_files(path)
        conn = None
        lock = MapLock.writer(path) if writable else MapLock.reader(path)
        try:
            try:
                head = lock.read_head(len(SQLITE_MAGIC))
            except OSError as err:
                raise MapError(f"{path}: cannot read map ({err})") from err
            if head != SQLITE_MAGIC:
                raise MapError(f"{path} is not a vtr map (not an SQLite database)")
            conn = connect(path, readonly=False) if writable else connect_readonly(path)
            app_id = conn.execute("PRAGMA application_id").fetchone()[0]
            if app_id != APPLICATION_ID:
                raise MapError(f"{path} is not a vtr map (SQLite database without the vtr application id)")
            checked = check(dict(conn.execute("SELECT key, value FROM meta").fetchall()))
            if writable:
                jm = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
                if str(jm).lower() != "wal":
                    raise MapError(f"{path}: cannot switch the map to WAL journal mode (got {jm})")
                # a killed writer's committed log goes into the file now, so the file alone holds it again
                conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
            return build(cls(path, conn, lock), checked)
        except BaseException as err:
            if conn is not None:
                conn.close()
            lock.release()
            if isinstance(err, MapError):
                raise
            if writable and _read_only_storage(err):
                raise MapError(
                    f"{path}: readable, but this process cannot write it or create files beside it "
                    f"({err}): make {path.name} and its folder writable, or open it read-only "
                    "(vtr repeat --read-only-map)"
                ) from err
            if isinstance(err, sqlite3.Error | ValueError | KeyError | VtrError):
                raise MapError(f"{path}: not a readable vtr map ({type(err).__name__}: {err})") from err
            raise

    @property
    def closed(self) -> bool:
        return self.conn is None

    @contextmanager
    def connection(self) -> Iterator[Connection]:
        """The connection under the lock, with SQLite errors turned into ``MapError``."""
        with self.lock:
            if self.conn is None:
                raise MapError(f"{self.path}: map is closed")
            try:
                yield self.conn
            except sqlite3.Error as err:
                raise MapError(f"{self.path}: {err}") from err

    @contextmanager
    def transaction(self) -> Iterator[Connection]:
        """One write transaction: committed when the block ends, rolled back on any error."""
        with self.connection() as conn:
            with transaction(conn):
                yield conn

    def second_connection(self) -> Connection:
        """Another read-write connection to this file, for a thread that commits while this one's connection reads
        (a WAL reader never waits for a writer's commit and its fsync). The caller closes it before :meth:`close`
        and writes through it with :func:`transaction` (its SQLite errors become ``MapError`` naming the map)."""
        if self.conn is None or self._writer_lock is None or not self._writer_lock.exclusive:
            raise MapError(f"{self.path}: a second connection needs the map open for writing")
        try:
            return connect(self.path, readonly=False)
        except sqlite3.Error as err:
            raise MapError(f"{self.path}: cannot open a second connection ({err})") from err

    def writer_alive(self) -> bool:
        """Whether a session (this one when it holds the writer lock) writes the file right now."""
        return self._writer_lock.writer_alive() if self._writer_lock is not None else True

    def fold_wal(self) -> None:
        """Checkpoint the write-ahead log into the file and return to a rollback journal, so the closed
        map is one self-contained file that opens read-only anywhere."""
        conn = self.conn
        assert conn is not None
        try:
            busy = conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()[0]
        except sqlite3.Error as err:
            raise MapError(
                f"{self.path}: could not write the write-ahead log back into the map ({err}); its "
                f"latest data is in {self.path.name}-wal: keep that file beside it"
            ) from err
        if busy:
            return  # a reader is in the middle of a read: the last connection to close checkpoints
        try:
            conn.execute("PRAGMA busy_timeout = 0")
            conn.execute("PRAGMA journal_mode = DELETE").fetchone()
        except sqlite3.Error:
            pass  # another connection has the map open: it stays in WAL mode, its log empty

    def close(self, remove: bool = False) -> None:
        """Close the connection, remove the map's files when ``remove`` (a map this session created and
        holds), then release the lock. Idempotent."""
        with self.lock:
            if self.conn is None:
                return
            self.conn.close()
            self.conn = None
            if remove:
                remove_map_files(self.path)
            if self._writer_lock is not None:
                self._writer_lock.release()

    def bytes_on_disk(self) -> int:
        """Size of the map file plus its write-ahead log, bytes."""
        return bytes_on_disk(self.path)

    def unfolded_pages(self) -> int:
        """Pages committed in the write-ahead log but not in the file (see :func:`unfolded_wal_pages`)."""
        return unfolded_wal_pages(self.path)
