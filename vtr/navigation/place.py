"""Place recognition over the taught vertices: where on the route a keyframe was seen (docs/localization.md).

A bag of binary words: a vocabulary of ``words`` ORB descriptors is learnt from the taught vertices'
own descriptors by k-majority clustering (k-means for Hamming space: each word is the bitwise majority
of the descriptors assigned to it), every taught vertex becomes a TF-IDF vector of the words its
features fall into, and a query keyframe is scored against all of them at once (cosine of the vectors,
a sparse matrix product). The best-scoring vertices are *candidates* only: the localizer verifies them
geometrically against their landmarks before anything is believed.

The index is learnt at the end of a teach and stored in the map (:meth:`PlaceIndex.to_bytes`); a map
written before it existed gets one built on open.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from ..config import PlaceConfig
from ..errors import MapError
from ..map import Map
from ..vo.features import descriptor_words
from ..vo.kernels import matching as km

DESCRIPTOR_BYTES = 32          # ORB: 256 bits
INDEX_MAGIC = b"VTRP\x01"


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
    bits = np.unpackbits(X, axis=1).astype(np.float32)        # (N, 256)
    for _ in range(iterations):
        a = km.nearest(_words(X), _words(centres))
        counts = np.bincount(a, minlength=k)
        sums = np.zeros((k, bits.shape[1]), np.float32)
        _sum_rows(sums, a, bits)
        used = counts > 0
        centres[used] = np.packbits((2 * sums[used] > counts[used, None]).astype(np.uint8), axis=1)
    return centres


def _sum_rows(out: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    from scipy.sparse import csr_matrix

    onehot = csr_matrix((np.ones(len(rows), np.float32), (rows, np.arange(len(rows)))), shape=(len(out), len(rows)))
    out += onehot @ values


def train_vocabulary(descriptors: np.ndarray, branching: int, iterations: int,
                     seed: int) -> tuple[np.ndarray, np.ndarray]:
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
class PlaceIndex:
    """The vocabulary, its inverse document frequencies (W,) and one unit TF-IDF row per taught vertex (a CSR
    matrix as ``indptr`` (V+1,), ``word`` and ``weight``), vertices in path order."""

    vocabulary: Vocabulary
    idf: np.ndarray
    indptr: np.ndarray
    word: np.ndarray
    weight: np.ndarray

    def __len__(self) -> int:
        return len(self.indptr) - 1

    @classmethod
    def build(cls, descriptor_sets: Callable[[], Iterable[np.ndarray]], n_vertices: int, config: PlaceConfig,
              seed: int = 0) -> PlaceIndex:
        """From each taught vertex's descriptors, in path order, read twice from ``descriptor_sets()`` (a sample
        of every vertex to learn the vocabulary, then each vertex's words), so memory does not grow with the route."""
        if n_vertices <= 0:
            raise MapError("place index: no taught vertex to index")
        rng = np.random.default_rng(seed)
        per_vertex = max(1, -(-config.training_descriptors // n_vertices))
        sample = []
        for d in descriptor_sets():
            d = np.asarray(d, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
            sample.append(d if len(d) <= per_vertex else d[rng.choice(len(d), per_vertex, replace=False)])
        vocabulary = Vocabulary(*train_vocabulary(np.concatenate(sample), config.branching,
                                                  config.training_iterations, seed))
        W, V = len(vocabulary), len(sample)
        compact = np.int16 if len(vocabulary) <= np.iinfo(np.int16).max else np.int32   # memory: one row a vertex
        words = [tuple(a.astype(compact) for a in np.unique(vocabulary.words_of(d), return_counts=True))
                 for d in descriptor_sets()]
        if len(words) != V:
            raise MapError(f"place index: the taught vertices changed while indexing ({V} then {len(words)})")
        df = np.bincount(np.concatenate([w for w, _ in words]), minlength=W) if V else np.zeros(W)
        idf = np.log((V + 1.0) / (df + 1.0)) + 1.0 / (V + 1.0)   # never 0: a word on every vertex still counts a little
        indptr = np.r_[0, np.cumsum([len(w) for w, _ in words])].astype(np.int64)
        word = np.concatenate([w for w, _ in words]).astype(np.int32) if V else np.zeros(0, np.int32)
        weight = np.concatenate([_unit(c * idf[w]) for w, c in words]).astype(np.float32)
        return cls(vocabulary, idf.astype(np.float32), indptr, word, weight)

    def _matrix(self):
        from scipy.sparse import csr_matrix

        return csr_matrix((self.weight, self.word, self.indptr), shape=(len(self), len(self.vocabulary)))

    def vector(self, descriptors: np.ndarray) -> np.ndarray:
        """Unit TF-IDF vector (W,) of a query's descriptors."""
        w = self.vocabulary.words_of(descriptors)
        v = np.bincount(w, minlength=len(self.vocabulary)).astype(np.float64) * self.idf
        return _unit(v)

    def scores(self, descriptors: np.ndarray) -> np.ndarray:
        """Cosine score (V,) of every taught vertex against a query's descriptors."""
        return np.asarray(self._csr @ self.vector(descriptors), np.float64).ravel()

    def query(self, descriptors: np.ndarray, k: int) -> PlaceMatch:
        """The ``k`` best-scoring taught vertices (path indices), best first."""
        s = self.scores(descriptors)
        k = min(int(k), len(s))
        top = np.argpartition(-s, k - 1)[:k] if k < len(s) else np.arange(len(s))
        top = top[np.argsort(-s[top], kind="stable")]
        return PlaceMatch(top.astype(np.int64), s[top])

    @property
    def _csr(self):
        m = self.__dict__.get("_csr_cache")
        if m is None:
            m = self._matrix()
            object.__setattr__(self, "_csr_cache", m)
        return m

    # -- storage ------------------------------------------------------------------------------------

    def to_bytes(self) -> bytes:
        buf = io.BytesIO()
        np.savez(buf, top=self.vocabulary.top, leaves=self.vocabulary.leaves, idf=self.idf, indptr=self.indptr,
                 word=self.word, weight=self.weight)
        return INDEX_MAGIC + buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes, where: str = "place index") -> PlaceIndex:
        if not data.startswith(INDEX_MAGIC):
            raise MapError(f"{where}: not a place index (bad magic)")
        try:
            with np.load(io.BytesIO(data[len(INDEX_MAGIC):]), allow_pickle=False) as z:
                out = cls(Vocabulary(z["top"], z["leaves"]), z["idf"], z["indptr"], z["word"], z["weight"])
        except (ValueError, KeyError, OSError, zipfile.BadZipFile) as err:
            raise MapError(f"{where}: damaged place index ({err})") from None
        W, B = len(out.vocabulary), len(out.vocabulary.top)
        if (out.vocabulary.top.shape != (B, DESCRIPTOR_BYTES)
                or out.vocabulary.leaves.shape != (B * B, DESCRIPTOR_BYTES) or out.idf.shape != (W,)
                or out.indptr.ndim != 1 or len(out.indptr) < 2 or out.indptr[-1] != len(out.word)
                or out.word.shape != out.weight.shape or (len(out.word) and (out.word.min() < 0 or out.word.max() >= W))
                or np.any(np.diff(out.indptr) < 0) or not np.all(np.isfinite(out.weight))):
            raise MapError(f"{where}: damaged place index (inconsistent arrays)")
        return out


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else v


def place_key(run: int) -> str:
    """The map's derived-data key of a taught run's place index."""
    return f"place_index/{int(run)}"


def route_place_index(map_: Map, config: PlaceConfig, seed: int = 0) -> PlaceIndex:
    """The taught route's place index: stored in the map, else built from its vertices (stored when the map is
    writable: a map taught before the index existed gets one the first time it is repeated)."""
    path = map_.taught_path()
    run = map_.reference_run()
    key = place_key(-1 if run is None else run)
    data = map_.derived(key)
    if data is not None:
        try:
            index = PlaceIndex.from_bytes(data, f"{map_.path}: {key}")
        except MapError:
            index = None                  # damaged derived data: rebuilt from the vertices below
        if index is not None and len(index) == len(path):
            return index
    index = PlaceIndex.build(lambda: (map_.vertex(int(i)).frame.features.descriptors for i in path.ids), len(path),
                             config, seed)
    if map_.mode == "a":
        map_.put_derived(key, index.to_bytes())
    return index


__all__ = ["PlaceIndex", "PlaceMatch", "Vocabulary", "k_majority", "place_key", "route_place_index", "train_vocabulary"]
