"""Place recognition over the taught vertices: where on the route a keyframe was seen (docs/localization.md).

A bag of binary words: a vocabulary of ``words`` ORB descriptors is learnt from the taught vertices'
own descriptors by k-majority clustering (k-means for Hamming space: each word is the bitwise majority
of the descriptors assigned to it), every taught vertex becomes a TF-IDF vector of the words its
features fall into, and a query keyframe is scored against them (cosine of the vectors). A route of up to
``place.shortlist`` vertices is scored whole (a sparse matrix product); a longer one in two passes, so a query
costs about the same at 50 000 vertices as at 1 000: an inverted file of each vertex's heaviest words, looked up
with the query's heaviest, shortlists the vertices sharing its most telling words, and only those are scored
exactly. The best-scoring vertices are *candidates* only: the localizer verifies them geometrically against
their landmarks before anything is believed.

The index is learnt at the end of a teach and stored in the map (:meth:`PlaceIndex.to_bytes`) with a digest of
the vertices it indexes (:func:`vertices_digest`: their ids, times and poses); a map written before it existed,
or whose stored index does not match its taught vertices (damaged, or copied from another map), gets one
rebuilt on open, with a warning for the mismatch.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import warnings
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..config import PlaceConfig
from ..errors import MapError
from ..map import Map
from ..vo.features import descriptor_words
from ..vo.kernels import matching as km
from .kernels import coarse_scores, row_scores

if TYPE_CHECKING:
    from scipy.sparse import csr_matrix

DESCRIPTOR_BYTES = 32  # ORB: 256 bits
INDEX_MAGIC = b"VTRP\x01"
DIGEST_BYTES = 16  # BLAKE2b of the indexed vertices (ids, times, poses)
ROWS_PER_BLOCK = 4096  # rows sorted at once when the inverted file is derived (bounds its temporary arrays)


def _words(descriptors: np.ndarray) -> np.ndarray:
    return descriptor_words(np.asarray(descriptors, np.uint8).reshape(-1, DESCRIPTOR_BYTES))


def k_majority(descriptors: np.ndarray, k: int, iterations: int, rng: np.random.Generator) -> np.ndarray:
    """``k`` binary centres (k, 32) of ``descriptors`` (N, 32) by k-majority clustering (k-means in Hamming
    space: a centre is the bitwise majority of its members); with ``k`` or fewer distinct descriptors, those
    (repeated up to ``k``)."""
    X = np.unique(np.ascontiguousarray(descriptors, np.uint8), axis=0)
    if len(X) <= k:
        return X[np.arange(k) % len(X)] if len(X) else np.zeros((k, DESCRIPTOR_BYTES), np.uint8)
    centres = X[rng.choice(len(X), k, replace=False)].copy()
    bits = np.unpackbits(X, axis=1).astype(np.float32)  # (N, 256)
    for _ in range(iterations):
        a = km.nearest(_words(X), _words(centres))
        counts = np.bincount(a, minlength=k)
        sums = np.zeros((k, bits.shape[1]), np.float32)
        _sum_rows(sums, a, bits)
        used = counts > 0
        centres[used] = np.packbits((2 * sums[used] > counts[used, None]).astype(np.uint8), axis=1)
    return centres


def _sum_rows(out: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    from scipy.sparse import csr_matrix  # scipy.sparse (~0.1 s) only when an index is built or scored

    onehot = csr_matrix((np.ones(len(rows), np.float32), (rows, np.arange(len(rows)))), shape=(len(out), len(rows)))
    out += onehot @ values


def train_vocabulary(
    descriptors: np.ndarray, branching: int, iterations: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """A two-level vocabulary tree: ``branching`` top nodes (B, 32) and ``branching`` leaf words under each
    (B * B, 32), by k-majority clustering of the descriptors, then of each node's members."""
    rng = np.random.default_rng(seed)
    X = np.ascontiguousarray(descriptors, np.uint8)
    top = k_majority(X, branching, iterations, rng)
    a = km.nearest(_words(X), _words(top))
    leaves = np.concatenate([k_majority(X[a == t], branching, iterations, rng) for t in range(branching)])
    return top, leaves


@dataclass(frozen=True)
class Vocabulary:
    """Binary words in a two-level tree: ``top`` (B, 32) nodes, ``leaves`` (B * B, 32) words."""

    top: np.ndarray
    leaves: np.ndarray

    def __len__(self) -> int:
        return len(self.leaves)

    def words_of(self, descriptors: np.ndarray) -> np.ndarray:
        """Word index (N,) of each descriptor (N, 32) uint8."""
        if len(descriptors) == 0:
            return np.zeros(0, np.int64)
        return km.nearest_in_tree(_words(descriptors), _words(self.top), _words(self.leaves), len(self.top))


@dataclass(frozen=True)
class PlaceMatch:
    """Candidate taught vertices for one query, best first: path ``indices`` and their ``scores`` (cosine, 0..1)."""

    indices: np.ndarray
    scores: np.ndarray


@dataclass(frozen=True)
class CoarseFile:
    """The inverted file of the first pass: for each word (``indptr`` (W+1,)), the vertices (``vertex``, int32)
    that have it among their ``vertex_words`` heaviest words, and its weight there (``weight``, float32)."""

    indptr: np.ndarray
    vertex: np.ndarray
    weight: np.ndarray
    vertex_words: int

    @classmethod
    def of_rows(
        cls,
        indptr: np.ndarray,
        word: np.ndarray,
        weight: np.ndarray,
        n_words: int,
        vertex_words: int,
        rows_per_block: int = ROWS_PER_BLOCK,
    ) -> CoarseFile:
        """From the unit TF-IDF rows (CSR): each row's ``vertex_words`` heaviest words (ties: the lower word),
        in blocks of rows so memory stays that of the rows."""
        vs, ws, xs = [], [], []
        V = len(indptr) - 1
        for lo in range(0, V, rows_per_block):
            hi = min(lo + rows_per_block, V)
            a, b = int(indptr[lo]), int(indptr[hi])
            row = np.repeat(np.arange(lo, hi), np.diff(indptr[lo : hi + 1]))
            order = np.lexsort((word[a:b], -weight[a:b], row))  # by row, heaviest first
            rank = np.arange(b - a) - (indptr[row[order]] - a)
            keep = order[rank < vertex_words]
            vs.append(row[keep])
            ws.append(word[a:b][keep])
            xs.append(weight[a:b][keep])
        v, w, x = (np.concatenate(a) if a else np.zeros(0) for a in (vs, ws, xs))
        o = np.lexsort((v, w))
        return cls(
            np.r_[0, np.cumsum(np.bincount(w[o].astype(np.int64), minlength=n_words))].astype(np.int64),
            v[o].astype(np.int32),
            x[o].astype(np.float32),
            int(vertex_words),
        )

    @property
    def nbytes(self) -> int:
        return self.indptr.nbytes + self.vertex.nbytes + self.weight.nbytes


@dataclass(frozen=True)
class PlaceIndex:
    """The vocabulary, its inverse document frequencies (W,) and one unit TF-IDF row per taught vertex (a CSR
    matrix as ``indptr`` (V+1,), ``word`` and ``weight``), vertices in path order; ``coarse``, the inverted file
    of the first pass of a long route's queries; ``shortlist`` and ``query_words`` (``place.*``) how it is used."""

    vocabulary: Vocabulary
    idf: np.ndarray
    indptr: np.ndarray
    word: np.ndarray
    weight: np.ndarray
    digest: bytes = b""  # vertices_digest of the vertices indexed (empty: an index stored before digests)
    coarse: CoarseFile | None = None  # None: derived from the rows when first needed (PlaceConfig's vertex_words)
    shortlist: int = PlaceConfig().shortlist
    query_words: int = PlaceConfig().query_words

    def __len__(self) -> int:
        return len(self.indptr) - 1

    @classmethod
    def build(
        cls,
        descriptor_sets: Callable[[], Iterable[np.ndarray]],
        n_vertices: int,
        config: PlaceConfig,
        seed: int = 0,
        digest: bytes = b"",
    ) -> PlaceIndex:
        """From each taught vertex's descriptors, in path order, read twice from ``descriptor_sets()`` (a sample
        of every vertex to learn the vocabulary, then each vertex's words), so memory does not grow with the route.
        ``digest``: :func:`vertices_digest` of those vertices, kept with the index."""
        if n_vertices <= 0:
            raise MapError("place index: no taught vertex to index")
        rng = np.random.default_rng(seed)
        per_vertex = max(1, -(-config.training_descriptors // n_vertices))
        sample = []
        for d in descriptor_sets():
            d = np.asarray(d, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
            sample.append(d if len(d) <= per_vertex else d[rng.choice(len(d), per_vertex, replace=False)])
        vocabulary = Vocabulary(
            *train_vocabulary(np.concatenate(sample), config.branching, config.training_iterations, seed)
        )
        W, V = len(vocabulary), len(sample)
        compact = np.int16 if len(vocabulary) <= np.iinfo(np.int16).max else np.int32  # memory: one row a vertex
        words = [
            tuple(a.astype(compact) for a in np.unique(vocabulary.words_of(d), return_counts=True))
            for d in descriptor_sets()
        ]
        if len(words) != V:
            raise MapError(f"place index: the taught vertices changed while indexing ({V} then {len(words)})")
        df = np.bincount(np.concatenate([w for w, _ in words]), minlength=W) if V else np.zeros(W)
        idf = np.log((V + 1.0) / (df + 1.0)) + 1.0 / (V + 1.0)  # never 0: a word on every vertex still counts a little
        indptr = np.r_[0, np.cumsum([len(w) for w, _ in words])].astype(np.int64)
        word = np.concatenate([w for w, _ in words]).astype(compact) if V else np.zeros(0, compact)
        weight = np.concatenate([_unit(c * idf[w]) for w, c in words]).astype(np.float32)
        del words
        coarse = CoarseFile.of_rows(indptr, word, weight, W, config.vertex_words)
        return cls(
            vocabulary,
            idf.astype(np.float32),
            indptr,
            word,
            weight,
            bytes(digest),
            coarse,
            config.shortlist,
            config.query_words,
        )

    def configured(self, config: PlaceConfig) -> PlaceIndex:
        """This index queried as ``config`` says (its inverted file rebuilt when ``vertex_words`` differs)."""
        coarse = self.coarse
        if coarse is None or coarse.vertex_words != config.vertex_words:
            coarse = CoarseFile.of_rows(self.indptr, self.word, self.weight, len(self.vocabulary), config.vertex_words)
        return dataclasses.replace(self, coarse=coarse, shortlist=config.shortlist, query_words=config.query_words)

    def nbytes(self) -> int:
        """Bytes of the index's arrays (the vocabulary, the rows, the inverted file and any cached matrix)."""
        own = sum(
            a.nbytes
            for a in (self.vocabulary.top, self.vocabulary.leaves, self.idf, self.indptr, self.word, self.weight)
        )
        m = self.__dict__.get("_csr_cache")
        cached = 0 if m is None else m.data.nbytes + m.indices.nbytes + m.indptr.nbytes
        return own + (self._coarse().nbytes if len(self) > self.shortlist else 0) + cached

    def _matrix(self) -> csr_matrix:
        from scipy.sparse import csr_matrix  # scipy.sparse on first use

        return csr_matrix((self.weight, self.word, self.indptr), shape=(len(self), len(self.vocabulary)))

    def vector(self, descriptors: np.ndarray) -> np.ndarray:
        """Unit TF-IDF vector (W,) of a query's descriptors."""
        w = self.vocabulary.words_of(descriptors)
        v = np.bincount(w, minlength=len(self.vocabulary)).astype(np.float64) * self.idf
        return _unit(v)

    def scores(self, descriptors: np.ndarray, also: np.ndarray | slice | None = None) -> np.ndarray:
        """Cosine score (V,) of the taught vertices against a query's descriptors: of every vertex on a route of
        up to ``shortlist`` vertices; on a longer one of the ``shortlist`` vertices sharing the query's most
        telling words (:meth:`shortlisted`) and of the vertices ``also`` (path indices or a slice: e.g. the
        window a tracked leaf is in, whose scores a check compares), 0 for the others."""
        q = self.vector(descriptors)
        if len(self) <= self.shortlist:
            return np.asarray(self._csr @ q, np.float64).ravel()
        out = np.zeros(len(self))
        rows = self.shortlisted(q)
        if also is not None:
            rows = np.union1d(rows, np.arange(len(self))[also])
        out[rows] = self._row_scores(rows, q)
        return out

    def shortlisted(self, q: np.ndarray) -> np.ndarray:
        """Path indices (ascending) of at most ``shortlist`` vertices best scored by the inverted file: the
        query's ``query_words`` heaviest words (ties: the lower word) against each vertex's heaviest."""

        coarse = self._coarse()
        nz = np.flatnonzero(q)
        top = nz[np.lexsort((nz, -q[nz]))[: self.query_words]]
        acc = coarse_scores(coarse.indptr, coarse.vertex, coarse.weight, top.astype(np.int64), q[top], len(self))
        rows = np.flatnonzero(acc > 0)
        if len(rows) > self.shortlist:
            rows = np.sort(rows[np.argpartition(-acc[rows], self.shortlist - 1)[: self.shortlist]])
        return rows

    def _row_scores(self, rows: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Exact cosine of vertices ``rows`` against the unit query vector ``q``."""

        return row_scores(self.indptr, self.word, self.weight, rows.astype(np.int64), q)

    def _coarse(self) -> CoarseFile:
        if self.coarse is None:
            object.__setattr__(
                self,
                "coarse",
                CoarseFile.of_rows(
                    self.indptr, self.word, self.weight, len(self.vocabulary), PlaceConfig().vertex_words
                ),
            )
        assert self.coarse is not None
        return self.coarse

    def query(self, descriptors: np.ndarray, k: int) -> PlaceMatch:
        """The ``k`` best-scoring taught vertices (path indices), best first."""
        s = self.scores(descriptors)
        k = min(int(k), len(s))
        top = np.argpartition(-s, k - 1)[:k] if k < len(s) else np.arange(len(s))
        top = top[np.argsort(-s[top], kind="stable")]
        return PlaceMatch(top.astype(np.int64), s[top])

    @property
    def _csr(self) -> csr_matrix:
        m = self.__dict__.get("_csr_cache")
        if m is None:
            m = self._matrix()
            object.__setattr__(self, "_csr_cache", m)
        return m

    # -- storage ------------------------------------------------------------------------------------

    def to_bytes(self) -> bytes:
        buf = io.BytesIO()
        c = self._coarse()
        np.savez(
            buf,
            top=self.vocabulary.top,
            leaves=self.vocabulary.leaves,
            idf=self.idf,
            indptr=self.indptr,
            word=self.word,
            weight=self.weight,
            digest=np.frombuffer(self.digest, np.uint8),
            coarse_indptr=c.indptr,
            coarse_vertex=c.vertex,
            coarse_weight=c.weight,
            coarse_vertex_words=np.array(c.vertex_words, np.int64),
        )
        return INDEX_MAGIC + buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes, where: str = "place index") -> PlaceIndex:
        if not data.startswith(INDEX_MAGIC):
            raise MapError(f"{where}: not a place index (bad magic)")
        try:
            with np.load(io.BytesIO(data[len(INDEX_MAGIC) :]), allow_pickle=False) as z:
                digest = z["digest"].astype(np.uint8).tobytes() if "digest" in z.files else b""
                coarse = None  # an index stored before the inverted file: derived when first needed
                if "coarse_indptr" in z.files:
                    coarse = CoarseFile(
                        z["coarse_indptr"], z["coarse_vertex"], z["coarse_weight"], int(z["coarse_vertex_words"])
                    )
                out = cls(
                    Vocabulary(z["top"], z["leaves"]), z["idf"], z["indptr"], z["word"], z["weight"], digest, coarse
                )
        except (ValueError, KeyError, OSError, zipfile.BadZipFile) as err:
            raise MapError(f"{where}: damaged place index ({err})") from None
        W, B = len(out.vocabulary), len(out.vocabulary.top)
        if (
            out.vocabulary.top.shape != (B, DESCRIPTOR_BYTES)
            or out.vocabulary.leaves.shape != (B * B, DESCRIPTOR_BYTES)
            or out.idf.shape != (W,)
            or out.indptr.ndim != 1
            or len(out.indptr) < 2
            or out.indptr[-1] != len(out.word)
            or out.word.shape != out.weight.shape
            or (len(out.word) and (out.word.min() < 0 or out.word.max() >= W))
            or np.any(np.diff(out.indptr) < 0)
            or not np.all(np.isfinite(out.weight))
        ):
            raise MapError(f"{where}: damaged place index (inconsistent arrays)")
        c = out.coarse
        if c is not None and (
            c.indptr.shape != (W + 1,)
            or c.indptr[0] != 0
            or c.indptr[-1] != len(c.vertex)
            or c.vertex.shape != c.weight.shape
            or np.any(np.diff(c.indptr) < 0)
            or (len(c.vertex) and (c.vertex.min() < 0 or c.vertex.max() >= len(out)))
            or not np.all(np.isfinite(c.weight))
            or c.vertex_words < 1
        ):
            raise MapError(f"{where}: damaged place index (inconsistent inverted file)")
        return out


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def place_key(run: int) -> str:
    """The map's derived-data key of a taught run's place index."""
    return f"place_index/{int(run)}"


def vertices_digest(ids: np.ndarray, t_ns: np.ndarray, T_world_vertex: np.ndarray) -> bytes:
    """The digest tying an index to the vertices it indexes: BLAKE2b of their ids, times and poses (the pose index
    alone, no feature data read; a vertex's features are tied to its row by the map's own checksums)."""
    h = hashlib.blake2b(digest_size=DIGEST_BYTES, person=b"vtr-place-index")
    for a, dtype in ((ids, "<i8"), (t_ns, "<i8"), (T_world_vertex, "<f8")):
        h.update(np.ascontiguousarray(a, dtype=dtype).tobytes())
    return h.digest()


def route_place_index(
    map_: Map, config: PlaceConfig, seed: int = 0, warn: Callable[[str], None] | None = None
) -> PlaceIndex:
    """The taught route's place index: stored in the map, else built from its vertices (stored when the map is
    writable: a map taught before the index existed gets one the first time it is repeated).

    A stored index that is damaged or whose digest does not match the taught vertices (copied from another map,
    or the vertices changed) is rebuilt, and ``warn`` (else :func:`warnings.warn`) is told why."""
    stored = stored_place_index(map_)
    if stored.index is not None:
        return stored.index.configured(config)
    if stored.problem is not None:
        message = f"{map_.path}: place index {stored.key}: {stored.problem}; rebuilt from the vertices"
        if warn is not None:
            warn(f"warning: {message}")
        else:
            warnings.warn(message, RuntimeWarning, stacklevel=2)
    return rebuild_place_index(map_, config, seed)


@dataclass(frozen=True)
class StoredPlaceIndex:
    """The taught route's stored place index checked against its vertices: ``index`` when it is usable, else
    ``problem`` (why not; None when the map has none stored, as a map taught before the index existed)."""

    key: str
    index: PlaceIndex | None
    problem: str | None


def stored_place_index(map_: Map) -> StoredPlaceIndex:
    """The stored place index of ``map_``'s taught route, checked: readable, and its digest that of the taught
    vertices (:func:`vertices_digest`) with one entry per vertex."""
    path = map_.taught_path()
    key = _route_key(map_)
    data = map_.derived(key)
    if data is None:
        return StoredPlaceIndex(key, None, None)
    try:
        index = PlaceIndex.from_bytes(data, f"{map_.path}: {key}")
    except MapError:
        return StoredPlaceIndex(key, None, "it is damaged")
    if not index.digest:
        return StoredPlaceIndex(key, None, "it has no digest of the vertices it indexes (stored by an older vtr)")
    if index.digest != vertices_digest(path.ids, path.t_ns, path.T_world_vertex) or len(index) != len(path):
        return StoredPlaceIndex(
            key, None, "it does not match the taught vertices (another map's index, or the vertices changed)"
        )
    return StoredPlaceIndex(key, index, None)


def rebuild_place_index(map_: Map, config: PlaceConfig, seed: int = 0) -> PlaceIndex:
    """Build the taught route's place index from its vertices; stored when the map is open for writing."""
    path = map_.taught_path()
    index = PlaceIndex.build(
        lambda: (map_.vertex(int(i)).frame.features.descriptors for i in path.ids),
        len(path),
        config,
        seed,
        vertices_digest(path.ids, path.t_ns, path.T_world_vertex),
    )
    if map_.mode == "a":
        map_.put_derived(_route_key(map_), index.to_bytes())
    return index


def _route_key(map_: Map) -> str:
    """The derived-data key of ``map_``'s taught route's place index (its first taught run's)."""
    run = map_.reference_run()
    return place_key(-1 if run is None else run)


__all__ = [
    "CoarseFile",
    "PlaceIndex",
    "PlaceMatch",
    "StoredPlaceIndex",
    "Vocabulary",
    "k_majority",
    "place_key",
    "rebuild_place_index",
    "route_place_index",
    "stored_place_index",
    "train_vocabulary",
    "vertices_digest",
]
