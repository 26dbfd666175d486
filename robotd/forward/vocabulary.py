"""The incremental visual vocabulary and its inverted index (paper 000 Sec. III, IV-B).

**Vocabulary** (:class:`Vocabulary`). Words are created online, as in Filliat 2007 (the
paper's ref. [7]): a descriptor is quantised to its nearest word when that word lies
within ``word_radius``; otherwise it becomes a new word (its descriptor is the word's
centre, which never moves afterwards). Descriptors of one image that found no word are
grouped greedily among themselves first, so one image does not mint two words for one
scene point. The paper used a tree of its own (Sec. III); so do we for binary (ORB) words:
:class:`BinaryWordTree`, an incremental hierarchical k-medians tree over the packed 256-bit
words (after iBoW-LCD's OBIndex2, written here), searched with a beam for all of an
image's descriptors at once in numpy, whose cost follows the tree's depth and not the
number of words, and from which purged words really leave (their memory is reused). It is
approximate: on ORB words it finds a word within the radius for about 92-95 % of the
descriptors an exact search finds one for (``bench/bench_forward_scale.py`` measures what
that costs in recall). Float (SIFT) words are searched by an HNSW graph (usearch, kept as a
library: incremental insertion, removal of keys); ``VocabularyParams.binary_search =
"usearch"`` puts binary words there too, for comparison.

**Inverted index** (:class:`InvertedIndex`). For every word, the images it was seen in and
how often; for every image, its number of words. The postings lie in flat arrays, not in an
object per word: most words are seen in one image or a few, and an object's own overhead
would outweigh their postings while the vocabulary is young (:class:`_Postings`). Nothing
else is stored: the tf-idf weight
of a (word, image) pair is computed when it is needed from the current counts, so it is
always current as images arrive ("kept current online"):

    tf(w, i)  = n(w, i) / n(i)        occurrences of w in image i / words in image i
    idf(w)    = log(N / df(w))        N images indexed, df(w) of them contain w

The virtual "no loop" image I_-1 (Sec. IV-B) is the set of the ``n`` words seen most often
so far (total occurrences, ties to the older word), ``n`` being the mean number of words per
image, each counted once: tf = 1 / n.
"""

from __future__ import annotations

import heapq
import sys
from dataclasses import dataclass

import numpy as np

__all__ = ["BinaryWordTree", "InvertedIndex", "TreeParams", "Vocabulary", "VocabularyParams", "hamming_bits",
           "pack_bits", "sorted_isin", "sorted_union"]


@dataclass(frozen=True)
class VocabularyParams:
    """Parameters of :class:`Vocabulary`.

    Fields:
        word_radius_l2: a unit-length SIFT descriptor joins the nearest word when it is at
            most this Euclidean distance away (two views of one point are typically 0.2-0.35
            apart, unrelated points 0.5 or more), else it becomes a new word.
        word_radius_bits: the same for binary (ORB) descriptors, in differing bits of 256.
        connectivity: HNSW graph degree (usearch ``connectivity``).
        expansion_add: HNSW candidate list size while inserting.
        expansion_search: HNSW candidate list size while searching (recall of the nearest
            word against speed).
        purge_after: words seen in one image only are removed from the search once that
            many images have come after it (iBoW-LCD's purging): most words of an
            image never recur, and they would otherwise fill the search structure; 0 =
            never (the paper). A purged word keeps its id and its place in the inverted
            index (it still counts for its one image) but no later descriptor can find it.
        binary_search: the nearest-word search for binary words: ``"tree"`` (our own
            incremental k-medians tree, :class:`BinaryWordTree`; purged words free their
            memory) or ``"usearch"`` (the HNSW graph, kept for comparison). Float (SIFT)
            words always use usearch.
        tree_branching, tree_leaf_size, tree_beam: the tree's :class:`TreeParams`.
    """

    word_radius_l2: float = 0.4
    word_radius_bits: int = 40
    connectivity: int = 12
    expansion_add: int = 40
    expansion_search: int = 24
    purge_after: int = 0
    binary_search: str = "tree"
    tree_branching: int = 16
    tree_leaf_size: int = 256
    tree_beam: int = 4

    def __post_init__(self) -> None:
        if self.binary_search not in ("tree", "usearch"):
            raise ValueError(f"binary_search must be 'tree' or 'usearch', got {self.binary_search!r}")


class Vocabulary:
    """Visual words created online with a logarithmic-time nearest-word search.

    ``binary``: descriptors are packed bits (``(N, 32) uint8``, Hamming distance) instead of
    unit-length floats (``(N, dim) float32``, Euclidean distance). Word ids are 0, 1, 2, ...
    in creation order.
    """

    def __init__(self, dim: int = 128, binary: bool = False,
                 params: VocabularyParams = VocabularyParams()) -> None:
        self.params = params
        self.binary = binary
        self.dim = dim
        self._tree: BinaryWordTree | None = None
        if binary and params.binary_search == "tree":
            if dim != 32:
                raise ValueError(f"the binary word tree takes 256-bit descriptors (dim 32), got dim {dim}")
            self._tree = BinaryWordTree(TreeParams(branching=params.tree_branching, leaf_size=params.tree_leaf_size,
                                                   beam=params.tree_beam))
            self._radius = float(params.word_radius_bits)
        elif binary:
            from usearch.index import Index

            self._index = Index(ndim=dim * 8, metric="hamming", dtype="b1",
                                connectivity=params.connectivity,
                                expansion_add=params.expansion_add,
                                expansion_search=params.expansion_search)
            # usearch's Hamming distance is in bits; compare with the radius as is.
            self._radius = float(params.word_radius_bits)
        else:
            from usearch.index import Index

            self._index = Index(ndim=dim, metric="l2sq", dtype="f32",
                                connectivity=params.connectivity,
                                expansion_add=params.expansion_add,
                                expansion_search=params.expansion_search)
            self._radius = float(params.word_radius_l2) ** 2  # usearch returns squared L2
        self._n_words = 0
        self._images = 0                        # add() calls so far (one per image)
        self._first = _GrowingInts()            # per image (add() call): the first word id it made
        self._again = _GrowingBits()            # per word: found in an image after the one that made it
        self._unpurged_from = 0                 # words below this id were all examined
        self.purged = 0
        # What the last add() changed, for a store to write (robotd.io.store): the new words'
        # ids (a range) and, unless the search holds them (last_new reads them there), their
        # descriptors
        self._last_new_ids = (0, 0)
        self._last_new_desc: np.ndarray | None = np.zeros((0, dim), np.uint8 if binary else np.float32)
        # their slots in the word tree, until the next add() (None: not kept, as while the
        # tree's slot s holds word s)
        self._last_new_slots: np.ndarray | None = None
        # the descriptors (of the last add()) that made them (uint16 while they fit)
        self.last_new_at = np.zeros(0, np.uint16)
        self.last_purged = np.zeros(0, np.int64)
        self.last_purged_descriptors = np.zeros((0, dim), np.uint8 if binary else np.float32)

    def __len__(self) -> int:
        """Words made so far (purged ones included: ids are never reused)."""
        return self._n_words

    def memory_bytes(self) -> int:
        """Bytes of the word search (the tree's arrays, or usearch's own figure; reserved
        capacity included), the per-word counters, and what the last :meth:`add` changed
        (kept for a store to write)."""
        search = self._tree.memory_bytes() if self._tree is not None else int(self._index.memory_usage)
        last = (self.last_new_at, self.last_purged, self.last_purged_descriptors)
        held = sum(a.nbytes for a in (self._last_new_desc, self._last_new_slots) if a is not None)
        return search + self._first.nbytes + self._again.nbytes + sum(a.nbytes for a in last) + held

    @property
    def last_new(self) -> tuple[np.ndarray, np.ndarray]:
        """The words the last :meth:`add` made: ids ``(K,) int64`` and descriptors ``(K,
        dim)`` as added (read from the word tree when it holds them, so not kept twice)."""
        lo, hi = self._last_new_ids
        keys = np.arange(lo, hi, dtype=np.int64)
        if self._last_new_desc is not None:
            return keys, self._last_new_desc
        return keys, self.word_descriptors(keys)

    def take_new_at(self) -> np.ndarray:
        """:attr:`last_new_at`, handed over once: not kept after (the image that made the
        words keeps them, as the keypoints it lends: not held twice)."""
        at, self.last_new_at = self.last_new_at, np.zeros(0, np.uint16)
        return at

    @property
    def n_searchable(self) -> int:
        """Words the search can still find (made minus purged)."""
        return self._n_words - self.purged

    @property
    def lends(self) -> bool:
        """True when the search keeps each word's descriptor where :meth:`word_descriptors`
        reads it back, and :attr:`last_purged_descriptors` gives purged words' descriptors
        (the binary word tree), so an image's store may leave its founding descriptors to
        it (:class:`robotd.forward.detector.ForwardDetector`)."""
        return self._tree is not None

    def image_words(self, image: int) -> tuple[int, int]:
        """The ids ``lo .. hi - 1`` of the words that image ``image`` (its :meth:`add` call,
        0, 1, ...) made."""
        hi = int(self._first.view[image + 1]) if image + 1 < self._images else self._n_words
        return int(self._first.view[image]), hi

    def born(self, words: np.ndarray) -> np.ndarray:
        """``(K,) int64``: the image (its :meth:`add` call) that made each of ``words``."""
        out: np.ndarray = np.searchsorted(self._first.view, np.asarray(words, np.int64), side="right") - 1
        return out

    def searchable(self, words: np.ndarray) -> np.ndarray:
        """``(K,) bool``: which of ``words`` (``(K,) int``, made already) the search can
        still find: not purged (a word is examined once, when it falls due; one found in a
        second image is never purged)."""
        w = np.asarray(words, np.int64)
        if self.params.purge_after <= 0:
            return np.ones(len(w), bool)
        out: np.ndarray = (w >= self._unpurged_from) | self._again.get(w)
        return out

    def word_descriptors(self, words: np.ndarray) -> np.ndarray:
        """The descriptors of searchable ``words`` (``(K,) int``), ``(K, 32) uint8`` as they
        were added; LookupError for a word the search does not hold (purged, or a search
        that does not lend: :attr:`lends`)."""
        if self._tree is None:
            raise LookupError("only the binary word tree gives its words' descriptors back")
        w = np.asarray(words, np.int64)
        lo, hi = self._last_new_ids
        if self._last_new_slots is not None and len(w) and int(w.min()) >= lo and int(w.max()) < hi:
            # the last add()'s words (the latest image's, as a store reads them): their slots are known
            last: np.ndarray = self._tree._desc.take(self._last_new_slots.take(w - lo), axis=0).view(np.uint8)
            return last
        d, found = self._tree.descriptors(words)
        if not found.all():
            raise LookupError(f"words {np.asarray(words)[~found][:5].tolist()} are not in the word search")
        out: np.ndarray = d.view(np.uint8)
        return out

    def _check(self, descriptors: np.ndarray) -> np.ndarray:
        d = np.ascontiguousarray(descriptors, np.uint8 if self.binary else np.float32)
        if d.ndim != 2 or d.shape[1] != self.dim:
            raise ValueError(f"expected (N, {self.dim}) descriptors, got shape {descriptors.shape}")
        return d

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """The nearest existing word of each descriptor, or -1 when none is within the
        radius. ``(N,) int64``. The vocabulary is not changed."""
        d = self._check(descriptors)
        out = np.full(len(d), -1, np.int64)
        if not len(d) or not self._n_words:
            return out
        if self._tree is not None:
            keys_t, dist_t = self._tree.nearest(pack_bits(d))
            found_t = (keys_t >= 0) & (dist_t <= self._radius)
            out[found_t] = keys_t[found_t]
            return out
        m = self._index.search(d, 1, threads=1)
        # usearch answers one query with a Matches (no counts), several with BatchMatches.
        counts = np.asarray(getattr(m, "counts", [len(np.atleast_1d(m.keys))])).reshape(-1)
        keys = np.asarray(m.keys, np.int64).reshape(len(d), -1)[:, 0]
        dist = np.asarray(m.distances, np.float64).reshape(len(d), -1)[:, 0]
        found = (counts > 0) & (dist <= self._radius)
        out[found] = keys[found]
        return out

    def _pairwise(self, d: np.ndarray) -> np.ndarray:
        """Distances between the rows of ``d`` in the units of the radius (bits, or squared L2)."""
        if self.binary:
            q = pack_bits(d)
            return hamming_bits(q[:, None, :], q[None, :, :])
        sq = np.einsum("ij,ij->i", d, d).astype(np.float64)
        return np.maximum(sq[:, None] + sq[None, :] - 2.0 * (d.astype(np.float64) @ d.T.astype(np.float64)), 0.0)

    def _group(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Group an image's unmatched descriptors ``d`` into new words: taken in order, each
        one that no earlier new word covers founds a word that also takes every later
        unclaimed descriptor within the radius. Returns each descriptor's word as a rank
        among the founders (``(M,) int64``, 0 = the first founder) and the founders'
        indices. Descriptors with no other within the radius found their own word without
        entering the greedy loop, which so runs over the few that have neighbours only."""
        m = len(d)
        close = self._pairwise(d) <= self._radius
        np.fill_diagonal(close, False)
        owner = np.arange(m)
        claimed = np.zeros(m, bool)
        for k in np.flatnonzero(close.any(axis=1)).tolist():
            if claimed[k]:
                continue
            claim = close[k] & ~claimed
            claim[:k + 1] = False
            owner[claim] = k
            claimed[claim] = True
        founders = np.flatnonzero(~claimed)
        return np.searchsorted(founders, owner).astype(np.int64), founders

    def add(self, descriptors: np.ndarray) -> tuple[np.ndarray, int]:
        """Quantise one image's descriptors, creating words for those that found none.

        Returns the word of each descriptor, ``(N,) int64`` (never -1), and how many words
        were created. Unmatched descriptors are taken in order; each one that no earlier
        new word of this image covers founds a word that also takes every later unmatched
        descriptor within the radius.
        """
        d = self._check(descriptors)
        if self._tree is not None:
            self._tree.last_greedy = None
        words = self.quantize(d)
        self._first.resize(self._images + 1)
        self._first.view[self._images] = self._n_words
        self._images += 1
        none = d[:0].copy()  # not a view: that would keep the caller's descriptors alive
        self._last_new_ids, self._last_new_desc, self._last_new_slots = (self._n_words, self._n_words), none, None
        self.last_new_at = np.zeros(0, np.uint16)
        self.last_purged = np.zeros(0, np.int64)
        self.last_purged_descriptors = none
        # a word found twice in the image is written twice with the same value (no unique)
        found = words[words >= 0]
        self._again.set(found)  # only "more than once" matters
        new = np.flatnonzero(words < 0)
        if not len(new):
            self._purge()
            if self._tree is not None:
                self._tree.last_greedy = None  # a view of the search's (N, beam) leaves: not kept
            return words, 0
        owner, founders = self._group(d[new])
        keys = np.arange(self._n_words, self._n_words + len(founders), dtype=np.int64)
        if self._tree is not None:
            # the search above left the tree as it was: its greedy leaves are where they go
            greedy = self._tree.last_greedy
            slots = self._tree.add(keys, pack_bits(d[new[founders]]), None if greedy is None else greedy[new[founders]])
            self._last_new_slots = None if self._tree.slots_are_words else slots
            self._tree.last_greedy = None  # a view of the search's (N, beam) leaves: not kept
        else:
            self._index.add(keys, d[new[founders]], threads=1)
        self._n_words += len(founders)
        self._again.resize(self._n_words)
        words[new] = self._n_words - len(founders) + owner
        self._last_new_ids = (int(keys[0]), int(keys[-1]) + 1)
        self._last_new_desc = None if self._tree is not None else d[new[founders]]
        self.last_new_at = new[founders].astype(np.uint16 if len(d) <= 0xFFFF else np.int64)
        self._purge()
        return words, len(founders)

    def restore(self, descriptors: np.ndarray, born: np.ndarray, purged: np.ndarray,
                seen: np.ndarray, n_images: int) -> None:
        """Rebuild an empty vocabulary from stored words (ids 0 .. n - 1 in order):
        ``descriptors (n, dim)``, ``born (n,)`` the image that made each, ``purged (n,)
        bool``, ``seen (n,)`` images each was found in, ``n_images`` images added so far.
        Purged words keep their ids but are not searchable."""
        if self._n_words:
            raise ValueError("restore() needs an empty vocabulary")
        d = self._check(descriptors)
        n = len(d)
        born = np.asarray(born, np.int64)
        purged = np.asarray(purged, bool)
        if not (len(born) == len(purged) == len(seen) == n):
            raise ValueError("descriptors, born, purged and seen must have one row per word")
        keep = np.flatnonzero(~purged)
        if len(keep) and self._tree is not None:
            self._tree.add(keep.astype(np.int64), pack_bits(d[keep]))
        elif len(keep):
            self._index.add(keep.astype(np.int64), d[keep], threads=1)
        self._n_words = n
        if len(born) and (np.any(np.diff(born) < 0) or born[0] < 0 or born[-1] >= max(int(n_images), 1)):
            raise ValueError("born must not decrease and must lie in 0 .. n_images - 1 (words are made in image order)")
        self._first.resize(int(n_images))
        self._first.view[:] = np.searchsorted(born, np.arange(int(n_images)), side="left")
        self._again.resize(n)
        self._again.set(np.flatnonzero(np.asarray(seen, np.int64) > 1))
        self._images = int(n_images)
        self.purged = int(purged.sum())
        age = self.params.purge_after
        if age > 0:  # the words already due were examined when they fell due
            self._unpurged_from = int(np.searchsorted(born, self._images - 1 - age, side="right"))

    def _purge(self) -> None:
        """Remove from the search the words seen in one image only, made ``purge_after``
        images ago or earlier (the words are examined once, in creation order)."""
        age = self.params.purge_after
        if age <= 0:
            return
        limit = self._images - 1 - age          # words born at or before this image are due
        if limit < 0:
            return
        lo = self._unpurged_from
        hi = int(self._first.view[limit + 1])   # the first word made after image ``limit``
        if hi <= lo:
            return
        gone = lo + np.flatnonzero(~self._again.between(lo, hi))
        if len(gone):
            if self._tree is not None:
                self.last_purged_descriptors = self._tree.remove(gone).view(np.uint8)
            else:
                self._index.remove(gone.astype(np.int64))
            self.purged += len(gone)
            self.last_purged = gone.astype(np.int64)
        self._unpurged_from = hi


def hamming_bits(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Differing bits between packed 256-bit strings, ``(..., 4) uint64`` each (broadcast);
    ``(...) int32``."""
    if a.shape != b.shape:
        # numpy broadcasts an XOR in inner loops of the 4 words (a tree level's 300 x 64
        # strings: 3-5x the time of the XOR of two whole arrays): the smaller operand is
        # repeated whole to the other's shape first. Not when both would grow (an
        # all-pairs table: the repeats would triple the megabytes it takes).
        shape = np.broadcast_shapes(a.shape, b.shape)
        if a.shape == shape:
            b = _spread(b, shape)
        elif b.shape == shape:
            a = _spread(a, shape)
    # uint8 per 64 bits, summed as one uint32 per string (a reduce over 4 is slow): bytes 0
    # and 2, and 1 and 3, add without carry (64 + 64 < 256) in either byte order
    x = np.bitwise_count(a ^ b).view(np.uint32)[..., 0]
    y = x + (x >> 16)
    out: np.ndarray = ((y & 0xFF) + ((y >> 8) & 0xFF)).astype(np.int32)
    return out


def sorted_union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.union1d(a, b)`` of two sorted 1-d arrays of unique values, by one sort of
    both (``np.union1d`` goes through ``np.unique``'s hashing first)."""
    c = np.concatenate([a, b])
    c.sort()
    keep = np.ones(len(c), bool)
    np.not_equal(c[1:], c[:-1], out=keep[1:])
    out: np.ndarray = c[keep]
    return out


def sorted_isin(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.isin(a, b)`` for a sorted 1-d ``b`` (``(len(a),) bool``), by binary search
    (``np.isin`` fills a table over the values' whole range)."""
    if not len(b):
        return np.zeros(len(a), bool)
    at = np.searchsorted(b, a)
    at[at == len(b)] = 0
    out: np.ndarray = b[at] == a
    return out


def _spread(x: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``x (..., 4)`` repeated along its axes of one to ``shape`` (its last axis kept): the
    values of ``np.broadcast_to(x, shape)`` as a contiguous array, by whole strings."""
    x = x.reshape((1,) * (len(shape) - x.ndim) + x.shape)
    for axis, (have, want) in enumerate(zip(x.shape[:-1], shape[:-1])):
        if have != want:
            x = np.repeat(x, want, axis=axis)
    return x


def _first_k(dist: np.ndarray, k: int) -> np.ndarray:
    """The columns of the ``k`` smallest values of each row of ``dist (N, M)`` int (values
    -1 .. 2**20), in order, ties to the lower column: ``np.argsort(dist, axis=1,
    kind="stable")[:, :k]``, by one sort of int32 keys made unique by the column (numpy's
    sort of int32 rows is vectorised; an argsort or argpartition and the gathers after
    them took most of a tree descent's time)."""
    m = dist.shape[1]
    kt = np.dtype(np.int32 if (int(_FAR) + 1) * m < 2**31 else np.int64)  # int64 only for a very wide beam
    key: np.ndarray = dist.astype(kt) * m + np.arange(m, dtype=kt)
    out: np.ndarray = np.sort(key, axis=1)[:, :k] % m
    return out


def pack_bits(descriptors: np.ndarray) -> np.ndarray:
    """``(N, 32) uint8`` binary descriptors as ``(N, 4) uint64`` (the same bits)."""
    d = np.ascontiguousarray(descriptors, np.uint8)
    return d.view(np.uint64)


def _grown(n: int) -> int:
    """The capacity a growing array of capacity ``n`` takes next: a thirty-second more and
    one (amortised O(1) appends as with doubling, but at most about a thirty-second of the
    memory is spare room, and no first block: the per-word arrays hold every word ever
    made, the word tree's per-slot arrays every word it can find, and they all grow at the
    same images, so their spare room adds up; over a run's first images every word made is
    searchable, and a first block of 16 entries in each of the two dozen arrays, per word,
    per image, per node and per leaf, weighs most on the first image). Copying an array a
    thirty-second larger each time costs little beside the search over it; an array that
    grows by a whole image's entries at once takes what it needs."""
    return n + n // 32 + 1


def _within(lengths: np.ndarray) -> np.ndarray:
    """Each entry's position in its run, for runs of ``lengths`` laid end to end:
    ``[0, 1, .., lengths[0] - 1, 0, 1, ..]`` (``np.repeat(start, lengths) + _within(lengths)``
    are the runs' flat positions)."""
    return np.arange(int(lengths.sum())) - np.repeat(np.cumsum(lengths) - lengths, lengths)


_INT_BYTES = sys.getsizeof(1 << 20)  # a Python int beyond the small ones it shares (28 bytes)
_LEAF_BLOCK = 16          # a leaf's block in the word tree's pool: a multiple of this many entries
_FAR = np.int32(1 << 20)  # a distance no real pair reaches (256 bits at most)
_PREFILTER_BITS = 20       # see BinaryWordTree.nearest
_NO_KEY = np.int64(np.iinfo(np.int64).max)  # no word found yet (BinaryWordTree._scan)
_SLOT_TABLE_SPAN = 1 << 16  # BinaryWordTree.slots_of: ids spread over at most this many by a table


@dataclass(frozen=True)
class TreeParams:
    """Parameters of :class:`BinaryWordTree`.

    Fields:
        branching: children a full leaf is split into (k of the k-medians).
        leaf_size: words a leaf holds; one more splits it.
        beam: leaves a query scans: at each level the ``beam`` nodes whose centres are
            nearest to the query are kept (best-bin-first over the tree). More finds the
            nearest word more often, for more time.
        median_iterations: k-medians rounds when a leaf is split.
    """

    branching: int = 16
    leaf_size: int = 256
    beam: int = 4
    median_iterations: int = 3

    def __post_init__(self) -> None:
        if self.branching < 2 or self.leaf_size < 2 or self.beam < 1 or self.median_iterations < 0:
            raise ValueError("the word tree needs branching >= 2, leaf_size >= 2, beam >= 1, median_iterations >= 0")


class BinaryWordTree:
    """An incremental tree of binary words (Hamming distance; after the hierarchical
    k-medians vocabulary of iBoW-LCD's OBIndex2, our own).

    Every node has a centre (256 bits); a leaf holds up to ``leaf_size`` words. A word is
    added to the leaf reached by going down to the child with the nearest centre; a leaf
    that overflows becomes an inner node whose ``branching`` children are the k-medians
    clusters of its words (centres: bitwise majorities; seeds: the farthest-first words,
    so the tree is deterministic). A search goes down with a beam of ``beam`` nodes and
    scans their leaves: all queries of an image at once, in numpy (packed ``uint64``
    words, ``np.bitwise_count``), so its cost follows the depth and the beam, not the
    number of words. Removal frees the word's slot (its descriptor row is reused by the
    next word), so purged words do not hold memory.
    """

    def __init__(self, params: TreeParams = TreeParams()) -> None:
        self.params = params
        b = params.branching
        # nodes
        self._centre = np.zeros((2, 4), np.uint64)
        # children: a row of ``branching`` node ids (-1 none) per inner node only (most
        # nodes are leaves); row 0 is a spare with no child, the row of every leaf
        self._inner = np.zeros(2, np.int16)             # per node: its row of children (int32 when more)
        self._kids = np.full((1, b), -1, np.int16)      # int32 once there are more nodes
        self._n_inner = 1
        self._leaf_row = np.full(2, -1, np.int32)       # per node: its row in the pool, -1 inner
        self._n_nodes = 1
        # leaves: each a row, whose slots lie in order in a block of one flat pool: a block
        # holds the leaf's words and room for a few more (a multiple of _LEAF_BLOCK, not
        # ``leaf_size``: a leaf starts with about leaf_size / branching words at its
        # parent's split); a leaf that outgrows its block moves to a longer one at the
        # pool's end, and the pool is compacted once the blocks left behind take a quarter
        # of it
        self._pool = np.full(0, -1, np.int16)           # int32 once there are more slots
        self._pool_end = 0                               # the pool's used length
        self._pool_dead = 0                              # of it, in blocks left behind
        self._row_start = np.zeros(1, np.int32)          # per row: its block's start in the pool
        self._row_cap = np.zeros(1, np.int32)            # per row: its block's length
        self._fill = np.zeros(1, np.int32)
        self._n_rows = 1
        self._free_rows: list[int] = []
        self._leaf_row[0] = 0                            # the root, a leaf to begin with
        # words: one slot each (descriptor, word id, leaf row, position in it). The word
        # ids are kept only once a slot holds another word than its own number (None:
        # slot s holds word s, as while words come in id order and none was removed), and
        # the rows and positions only from the first removal, which alone reads them
        # (None: not kept; built from the leaves' blocks then), so a young tree holds its
        # descriptors and the leaves' blocks only
        self._desc = np.zeros((1, 4), np.uint64)
        self._slot_word: np.ndarray | None = None
        self._slot_row: np.ndarray | None = None        # int16 while the rows fit, then int32
        self._slot_pos: np.ndarray | None = None
        self._n_slots = 0
        self._free_slots: list[int] = []
        self.n_live = 0
        self.last_greedy: np.ndarray | None = None  # (N,) greedy leaves of the last search

    def __len__(self) -> int:
        return self.n_live

    def memory_bytes(self) -> int:
        """Bytes of the tree's arrays (their spare capacity included) and of its lists of
        free rows and slots (their tables and an int object per entry)."""
        arrays = (self._centre, self._inner, self._kids, self._leaf_row, self._pool, self._row_start, self._row_cap, self._fill,
                  self._desc, self._slot_word, self._slot_row, self._slot_pos)
        free = sys.getsizeof(self._free_rows) + sys.getsizeof(self._free_slots)
        return (sum(a.nbytes for a in arrays if a is not None) + free
                + _INT_BYTES * (len(self._free_rows) + len(self._free_slots)))

    @property
    def slots_are_words(self) -> bool:
        """True while slot s holds word s (no per-slot word ids kept)."""
        return self._slot_word is None

    def slot_words(self) -> np.ndarray:
        """The word held by each slot, ``(n_slots,) int32``, -1 for a free slot."""
        if self._slot_word is None:
            return np.arange(self._n_slots, dtype=np.int32)
        return self._slot_word[:self._n_slots]

    def _keep_slot_words(self) -> np.ndarray:
        """Keep the slots' word ids from now on (a slot is about to hold another word
        than its own number); returns them."""
        if self._slot_word is None:
            self._slot_word = np.full(_grown(self._n_slots), -1, np.int32)
            self._slot_word[:self._n_slots] = np.arange(self._n_slots, dtype=np.int32)
        return self._slot_word

    def _keep_slot_places(self) -> tuple[np.ndarray, np.ndarray]:
        """Keep each slot's leaf row and position in it from now on (the first removal),
        read off the leaves' blocks; returns them."""
        if self._slot_row is not None and self._slot_pos is not None:
            return self._slot_row, self._slot_pos
        cap = _grown(self._n_slots)
        self._slot_row = np.zeros(cap, np.int16 if self._n_rows <= np.iinfo(np.int16).max + 1 else np.int32)
        self._slot_pos = np.zeros(cap, np.uint8 if self.params.leaf_size <= 256 else np.int32)
        rows = self._leaf_row[:self._n_nodes]
        rows = rows[rows >= 0].astype(np.int64)
        fill = self._fill[rows].astype(np.int64)
        total = int(fill.sum())
        if total:
            within = _within(fill)
            slots = self._pool[np.repeat(self._row_start[rows].astype(np.int64), fill) + within]
            self._slot_row[slots] = np.repeat(rows, fill)
            self._slot_pos[slots] = within
        return self._slot_row, self._slot_pos

    # -- growing arrays -------------------------------------------------------------------
    @staticmethod
    def _grow(a: np.ndarray, n: int, fill: int = 0) -> np.ndarray:
        if n <= len(a):
            return a
        b = np.full((max(n, _grown(len(a))),) + a.shape[1:], fill, a.dtype)
        b[:len(a)] = a
        return b

    def _new_node(self, centre: np.ndarray) -> int:
        """A new leaf with this centre (:meth:`_children` lists it as its own child)."""
        n = self._n_nodes
        if n > np.iinfo(self._kids.dtype).max:
            self._kids = self._kids.astype(np.int32)
        self._centre = self._grow(self._centre, n + 2)   # + 2: the spare entry -1 (no child)
        self._inner = self._grow(self._inner, n + 2)
        self._leaf_row = self._grow(self._leaf_row, n + 2, -1)
        self._centre[n] = centre
        self._inner[n] = 0
        self._n_nodes = n + 1
        if self._free_rows:
            row = self._free_rows.pop()
        else:
            row = self._n_rows
            if self._slot_row is not None and row > np.iinfo(self._slot_row.dtype).max:
                self._slot_row = self._slot_row.astype(np.int32)
            self._row_start = self._grow(self._row_start, row + 1)
            self._row_cap = self._grow(self._row_cap, row + 1)
            self._fill = self._grow(self._fill, row + 1)
            self._n_rows = row + 1
        self._row_start[row] = self._pool_end
        self._row_cap[row] = 0                           # a block when its first word comes
        self._fill[row] = 0
        self._leaf_row[n] = row
        return n

    def _children(self, nodes: np.ndarray) -> np.ndarray:
        """The children of ``nodes`` (``(...)`` node ids, -1 none), ``(..., branching)``, -1
        none: an inner node's, a leaf itself as its only child, none for -1."""
        rows = self._inner.take(nodes)
        kids = self._kids.take(rows, axis=0)
        np.copyto(kids[..., 0], nodes, where=rows == 0)
        return kids

    def _make_inner(self, node: int) -> None:
        """Give leaf ``node`` a row of children (none yet)."""
        r = self._n_inner
        if r > np.iinfo(self._inner.dtype).max:
            self._inner = self._inner.astype(np.int32)
        if r == len(self._kids):  # a thirty-second more, not 16 rows more (inner nodes are few)
            kids = np.full((r + r // 32 + 1, self._kids.shape[1]), -1, self._kids.dtype)
            kids[:r] = self._kids
            self._kids = kids
        self._kids[r] = -1
        self._inner[node] = r
        self._n_inner = r + 1

    def leaf_slots(self, node: int) -> np.ndarray:
        """The slots of leaf ``node``'s words in their order, ``(fill,)`` int16 or int32 (a view)."""
        row = int(self._leaf_row[node])
        start = int(self._row_start[row])
        return self._pool[start:start + int(self._fill[row])]

    def _reserve(self, rows: np.ndarray, need: np.ndarray) -> None:
        """Give rows ``rows`` (``(K,)`` distinct) blocks of at least ``need`` entries: a row
        whose block is too short moves (its words in order) to a new block at the pool's
        end, a multiple of :data:`_LEAF_BLOCK` long (at most ``leaf_size``)."""
        short = need > self._row_cap[rows]
        if not short.any():
            return
        rows, need = rows[short], need[short]
        cap = np.maximum(np.minimum(-(-need // _LEAF_BLOCK) * _LEAF_BLOCK, self.params.leaf_size), need)
        self._pool_dead += int(self._row_cap[rows].sum())
        start = self._pool_end + np.cumsum(cap) - cap
        end = self._pool_end + int(cap.sum())
        self._pool = self._grow(self._pool, end, -1)
        fill = self._fill[rows]
        total = int(fill.sum())
        if total:
            within = _within(fill)
            self._pool[np.repeat(start, fill) + within] = self._pool[np.repeat(self._row_start[rows], fill) + within]
        self._row_start[rows] = start
        self._row_cap[rows] = cap
        self._pool_end = end
        if self._pool_dead * 4 > self._pool_end:
            self._compact()

    def _compact(self) -> None:
        """Move every leaf's block to the front of the pool, in row order, dropping the
        blocks left behind (the rows' blocks keep their lengths)."""
        n = self._n_rows
        cap = self._row_cap[:n].copy()
        live = np.flatnonzero(cap > 0)
        cap_l = cap[live]
        start = np.cumsum(cap_l) - cap_l
        total = int(cap_l.sum())
        pool = np.full(_grown(total), -1, self._pool.dtype)
        if total:
            within = np.arange(total) - np.repeat(start, cap_l)
            pool[:total] = self._pool[np.repeat(self._row_start[live], cap_l) + within]
        self._pool = pool
        self._row_start[live] = start
        self._row_start[:n][cap == 0] = total
        self._pool_end = total
        self._pool_dead = 0

    # -- search ---------------------------------------------------------------------------
    def _descend(self, q: np.ndarray, beam: int) -> np.ndarray:
        """The ``beam`` leaves (node ids, ``(N, <= beam)``, -1 none) reached by each query.

        The first of each row is the greedy path (the nearest child at every level): the
        path a word took when it was added, so a stored word is always found. A leaf lists
        itself as its only child, and row -1 of the node arrays is a spare with no child,
        so one gather expands a whole front.

        A query whose front holds leaves only is done: a further level would give it the
        same front (each leaf competes again with its own centre's distance, in the order
        it was kept), so only the queries with an inner node in their front go down a level
        (the tree's depth differs from branch to branch: one deep branch does not make the
        whole image's queries go down again)."""
        n = len(q)
        front: np.ndarray = np.zeros((n, 1), np.int32)  # then the children's dtype
        b = self.params.branching
        while True:
            kids = self._children(front)                              # (N, F, b)
            active = np.flatnonzero((kids[:, :, 0] != front).any(axis=1))
            if not len(active):                                       # all leaves (or -1)
                return front
            qa = q
            if len(active) < n:
                kids, qa = kids.take(active, axis=0), q.take(active, axis=0)
            cand = kids.reshape(len(active), -1)
            dist = hamming_bits(qa[:, None, :], self._centre.take(cand, axis=0))
            dist[cand < 0] = _FAR
            dist[np.arange(len(active)), np.argmin(dist[:, :b], axis=1)] = -1  # the greedy child: kept, first
            below = np.take_along_axis(cand, _first_k(dist, beam), axis=1)
            if len(active) < n:
                if below.shape[1] != front.shape[1]:  # a beam wider than the branching: the front widens
                    wide = np.full((n, below.shape[1]), -1, below.dtype)
                    wide[:, :front.shape[1]] = front
                    front = wide
                front[active] = below
            else:
                front = below

    def nearest(self, q: np.ndarray, beam: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The nearest word found for each query (``(N, 4) uint64``): ``(word ids (N,)
        int64, -1 when none was found; distances (N,) int32 bits)``.
        :attr:`last_greedy` keeps each query's greedy leaf (the one :meth:`add` would put
        it in while the tree is unchanged; None when the tree was empty).

        The leaves' words are first compared on their first 64 bits only: a word within
        the radius (40 of 256 bits) differs there by 8 bits (median); of 24,435 such pairs of
        ORB descriptors of a real corridor none differed by more than 18, so those above
        :data:`_PREFILTER_BITS` (20) are skipped (an unrelated word differs by about 32);
        the full distance is computed for the few percent that pass. (Scanning the greedy
        leaf first and stopping there when it holds a word within the radius was tried:
        it changed 9 % of the office route's answers and took longer, as most queries
        then scan twice.)"""
        n = len(q)
        none = np.full(n, -1, np.int64), np.full(n, _FAR, np.int32)
        self.last_greedy = None
        if not n or not self.n_live:
            return none
        leaves = self._descend(q, beam or self.params.beam)
        self.last_greedy = leaves[:, 0]
        best = np.full(n, _NO_KEY, np.int64)
        pair_q, pair_k = np.nonzero(leaves >= 0)                     # (query, leaf) pairs, by query
        self._scan(q, pair_q, leaves[pair_q, pair_k], best)
        found = best != _NO_KEY
        words, dist = none
        slot = best[found] & 0xFFFFFFFF
        words[found] = slot if self._slot_word is None else self._slot_word[slot]
        dist[found] = (best[found] >> 32).astype(np.int32)
        return words, dist

    def _scan(self, q: np.ndarray, pair_q: np.ndarray, nodes: np.ndarray, best: np.ndarray) -> None:
        """Scan leaf ``nodes[j]`` for query ``pair_q[j]`` (``pair_q`` not decreasing);
        ``best (N,) int64``: each query's nearest so far as ``distance << 32 | slot``
        (:data:`_NO_KEY` none), lowered in place (ties to the lowest slot)."""
        if not len(pair_q):
            return
        rows = self._leaf_row[nodes]
        fill = self._fill[rows]
        total = int(fill.sum())
        if not total:
            return
        # the filled part of each pair's leaf only: flat pool positions, their slots and
        # query (np.take and np.repeat: numpy's fancy indexing of a 2-d array by an index
        # array and a scalar takes several times as long)
        first = np.cumsum(fill) - fill
        pos = np.repeat(self._row_start.take(rows).astype(np.int64) - first, fill) + np.arange(total)
        slots = self._pool.take(pos)
        d0 = np.bitwise_count(np.repeat(q.take(pair_q, axis=0)[:, 0], fill) ^ self._desc[:, 0].take(slots))
        keep = np.flatnonzero(d0 <= _PREFILTER_BITS)
        if not len(keep):
            return
        s = slots.take(keep)
        qi = np.repeat(pair_q.astype(np.int32), fill).take(keep)
        full = hamming_bits(q.take(qi, axis=0), self._desc.take(s, axis=0))
        # per query (qi comes sorted): the nearest, ties to the lowest slot
        key = (full.astype(np.int64) << 32) | s.astype(np.int64)
        start = np.flatnonzero(np.diff(qi, prepend=-1))
        at = qi[start]
        best[at] = np.minimum(best[at], np.minimum.reduceat(key, start))

    # -- changes --------------------------------------------------------------------------
    def add(self, words: np.ndarray, q: np.ndarray, leaves: np.ndarray | None = None) -> np.ndarray:
        """Add words (ids ``(N,)`` int, new to the tree) with descriptors ``(N, 4) uint64``;
        ``leaves (N,)``: their greedy leaves when known (:attr:`last_greedy` of a search of
        the unchanged tree), else they are found here. Returns their slots, ``(N,) int32``
        (where :meth:`descriptors` reads them until a removal frees one)."""
        words = np.asarray(words, np.int64)
        if not len(words):
            return np.zeros(0, np.int32)
        slots = added = self._new_slots(words, q)
        leaves = self._descend(q, 1)[:, 0] if leaves is None else np.asarray(leaves, np.int32)
        order = np.argsort(leaves, kind="stable")
        leaves, slots = leaves[order], slots[order]
        first = np.ones(len(leaves), bool)
        first[1:] = leaves[1:] != leaves[:-1]
        start = np.flatnonzero(first)
        rank = np.arange(len(leaves)) - np.repeat(start, np.diff(np.append(start, len(leaves))))
        rows = self._leaf_row[leaves]
        pos = self._fill[rows] + rank
        need = self._fill[rows] + np.repeat(np.diff(np.append(start, len(leaves))), np.diff(np.append(start, len(leaves))))
        fits = need <= self.params.leaf_size
        # leaves with room: all at once (their blocks made long enough first); full ones
        # one by one (they split)
        self._reserve(rows[first & fits], need[first & fits])
        self._pool[self._row_start[rows[fits]] + pos[fits]] = slots[fits]
        if self._slot_row is not None and self._slot_pos is not None:
            self._slot_row[slots[fits]] = rows[fits]
            self._slot_pos[slots[fits]] = pos[fits]
        np.add.at(self._fill, rows[fits], 1)
        over = ~fits
        if over.any():
            for node in np.unique(leaves[over]).tolist():
                self._put(node, slots[over & (leaves == node)])
        self.n_live += len(words)
        return added

    def _new_slots(self, words: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Slots for new words (free ones first, then new rows), holding their descriptors."""
        k = min(len(words), len(self._free_slots))
        reused = [self._free_slots.pop() for _ in range(k)]
        n0 = self._n_slots
        fresh = np.arange(n0, n0 + len(words) - k, dtype=np.int64)
        n1 = n0 + len(fresh)
        slots = np.concatenate([np.asarray(reused, np.int64), fresh])
        if self._slot_word is None and not np.array_equal(words, slots):
            self._keep_slot_words()
        if n1 > np.iinfo(self._pool.dtype).max:
            self._pool = self._pool.astype(np.int32)
        self._desc = self._grow(self._desc, n1 + 1)  # + 1: a spare row, read for slot -1
        if self._slot_word is not None:
            self._slot_word = self._grow(self._slot_word, n1, -1)
        if self._slot_row is not None and self._slot_pos is not None:
            self._slot_row = self._grow(self._slot_row, n1)
            self._slot_pos = self._grow(self._slot_pos, n1)
        self._n_slots = n1
        self._desc[slots] = q
        if self._slot_word is not None:
            self._slot_word[slots] = words
        return slots.astype(np.int32)

    def _put(self, node: int, slots: np.ndarray) -> None:
        """Place ``slots`` in leaf ``node``, splitting it when it overflows."""
        row = int(self._leaf_row[node])
        f = int(self._fill[row])
        if f + len(slots) <= self.params.leaf_size:
            self._reserve(np.array([row]), np.array([f + len(slots)]))
            at = int(self._row_start[row]) + f
            self._pool[at:at + len(slots)] = slots
            if self._slot_row is not None and self._slot_pos is not None:
                self._slot_row[slots] = row
                self._slot_pos[slots] = np.arange(f, f + len(slots), dtype=np.int32)
            self._fill[row] = f + len(slots)
            return
        members = np.concatenate([self.leaf_slots(node), slots])
        self._pool_dead += int(self._row_cap[row])
        self._row_cap[row] = 0
        self._free_rows.append(row)
        self._leaf_row[node] = -1
        self._make_inner(node)
        groups, centres = self._split(self._desc[members])
        for j, (g, c) in enumerate(zip(groups, centres)):
            child = self._new_node(c)
            self._kids[self._inner[node], j] = child
            self._put(child, members[g])

    def _split(self, d: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """k-medians of ``d (M, 4) uint64``: index groups and their centres (bitwise
        majorities); deterministic (farthest-first seeds from the first row)."""
        b = self.params.branching
        m = len(d)
        seeds = [0]
        near = hamming_bits(d, d[0])
        while len(seeds) < min(b, m):
            j = int(np.argmax(near))
            if near[j] == 0:
                break
            seeds.append(j)
            near = np.minimum(near, hamming_bits(d, d[j]))
        centres = d[seeds]
        bits = np.unpackbits(d.view(np.uint8).reshape(m, -1), axis=1)
        for _ in range(self.params.median_iterations + 1):
            assign = np.argmin(hamming_bits(d[:, None, :], centres[None]), axis=1)
            used = np.unique(assign)
            counts = np.bincount(assign, minlength=len(centres))[used]
            sums = np.stack([bits[assign == j].sum(axis=0, dtype=np.int32) for j in used.tolist()])
            maj = (2 * sums > counts[:, None]).astype(np.uint8)
            centres = np.packbits(maj, axis=1).view(np.uint64).reshape(len(used), 4)
        assign = np.argmin(hamming_bits(d[:, None, :], centres[None]), axis=1)
        groups = [np.flatnonzero(assign == j) for j in range(len(centres))]
        keep = [j for j, g in enumerate(groups) if len(g)]
        groups, cents = [groups[j] for j in keep], [centres[j] for j in keep]
        if len(groups) == 1:  # identical words: split them in order (a full leaf must shrink)
            groups = np.array_split(np.arange(m), min(b, m))
            cents = [cents[0]] * len(groups)
        return groups, cents

    def slots_of(self, words: np.ndarray) -> np.ndarray:
        """The slot of each of ``words`` (``(K,) int``), ``(K,) int64``, -1 for a word the
        tree does not hold.

        Found by a pass over the slots' word ids restricted to the ids' range (the words
        asked for together are those of one image or of one image's age, a narrow range),
        so the tree keeps no per-word array over every word id ever made (about 90 per
        image on the office route, 4 bytes each)."""
        w = np.asarray(words, np.int64)
        out = np.full(len(w), -1, np.int64)
        if not len(w):
            return out
        lo, span = int(w.min()), int(w.max()) - int(w.min())
        if self._slot_word is None:  # slot s holds word s
            return np.where((w >= 0) & (w < self._n_slots), w, -1)
        held = self._slot_word[:self._n_slots]
        # held - lo as uint32 (a Python int: no int64 copy): free slots (-1) and ids below
        # lo wrap around above the span, so one comparison finds the range
        near = np.flatnonzero((held - lo).view(np.uint32) <= span)
        if span <= _SLOT_TABLE_SPAN:  # a table over the range: each id there is held once at most
            table = np.full(span + 1, -1, np.int64)
            table[held.take(near) - lo] = near
            return table.take(w - lo)
        keys = held[near]
        order = np.argsort(keys)
        keys, near = keys[order], near[order]
        at = np.minimum(np.searchsorted(keys, w), max(len(keys) - 1, 0))
        found = (keys[at] == w) if len(keys) else np.zeros(len(w), bool)
        out[found] = near[at[found]]
        return out

    def descriptors(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The descriptors of ``words`` (``(K,) int``): ``(K, 4) uint64`` (a zero row for a
        word the tree does not hold) and ``(K,) bool`` whether it holds each."""
        slots = self.slots_of(words)
        found = slots >= 0
        if found.all():
            return self._desc.take(slots, axis=0), found
        out = np.zeros((len(slots), 4), np.uint64)
        out[found] = self._desc[slots[found]]
        return out, found

    def remove(self, words: np.ndarray) -> np.ndarray:
        """Take words out (ids held by the tree; others are ignored); their slots are reused
        (their descriptor rows by the next words added). Returns the words' descriptors as
        they were, ``(K, 4) uint64`` (a zero row for a word the tree did not hold)."""
        w_all = np.asarray(words, np.int64)
        gone = np.zeros((len(w_all), 4), np.uint64)
        if not len(w_all):
            return gone
        at = self.slots_of(w_all)
        gone[at >= 0] = self._desc[at[at >= 0]]
        if not (at >= 0).any():
            return gone
        words_of = self._keep_slot_words()
        rows_of, pos_of = self._keep_slot_places()
        slots = at.tolist()
        # one word at a time (a removal moves the leaf's last entry into the hole, and the
        # entries' order decides a later split), through memoryviews: numpy's scalar
        # indexing costs several times a memoryview's
        pool, fill, row_start = self._pool.data, self._fill.data, self._row_start.data
        slot_row, slot_pos, slot_word = rows_of.data, pos_of.data, words_of.data
        for w, s in zip(w_all.tolist(), slots):
            if s < 0 or slot_word[s] != w:  # not held, or named twice
                continue
            row, pos = slot_row[s], slot_pos[s]
            at = row_start[row]
            last = fill[row] - 1
            moved = pool[at + last]
            pool[at + pos] = moved
            slot_pos[moved] = pos
            pool[at + last] = -1
            fill[row] = last
            slot_word[s] = -1
            self._free_slots.append(s)
            self.n_live -= 1
        return gone


_WIDER: dict[type, type] = {np.int8: np.int16, np.int16: np.int32, np.int32: np.int64}
_TOP: dict[type, int] = {t: int(np.iinfo(t).max) for t in (np.int8, np.int16, np.int32, np.int64)}


class _GrowingInts:
    """An integer array (int32 unless told) that grows by a thirty-second (:func:`_grown`; amortised O(1) append)."""

    def __init__(self, dtype: type = np.int32) -> None:
        self._a: np.ndarray = np.zeros(0, dtype)
        self.n = 0

    def resize(self, n: int) -> None:
        if n > len(self._a):
            b = np.zeros(max(n, _grown(len(self._a))), self._a.dtype)
            b[:self.n] = self._a[:self.n]
            self._a = b
        self.n = max(self.n, n)

    @property
    def view(self) -> np.ndarray:
        return self._a[:self.n]

    def add(self, at: np.ndarray, values: np.ndarray | int) -> None:
        """``view[at] += values`` (``at`` distinct), the array first widened to the next
        integer type when a sum would not fit its own (counters start narrow)."""
        if len(at):
            top = int(np.max(self._a[at].astype(np.int64) + values))  # the largest sum itself
            while top > _TOP[self._a.dtype.type]:
                self._a = self._a.astype(_WIDER[self._a.dtype.type])
        self._a[at] += values

    @property
    def nbytes(self) -> int:
        """Bytes held (the spare capacity included)."""
        return int(self._a.nbytes)


class _GrowingBits:
    """A growing array of bits (one per word: 1/8 of a byte, not a byte), packed eight to a
    byte, lowest bit first; new bits are 0."""

    def __init__(self) -> None:
        self._a: np.ndarray = np.zeros(0, np.uint8)
        self.n = 0

    def resize(self, n: int) -> None:
        need = (n + 7) >> 3
        if need > len(self._a):
            b = np.zeros(max(need, _grown(len(self._a))), np.uint8)
            b[:len(self._a)] = self._a
            self._a = b
        self.n = max(self.n, n)

    def set(self, at: np.ndarray) -> None:
        """Set the bits ``at`` (``(K,) int``, below ``n``, repeats allowed)."""
        at = np.asarray(at, np.int64)
        np.bitwise_or.at(self._a, at >> 3, np.left_shift(1, at & 7).astype(np.uint8))

    def get(self, at: np.ndarray) -> np.ndarray:
        """``(K,) bool``: the bits ``at`` (``(K,) int``, below ``n``)."""
        at = np.asarray(at, np.int64)
        out: np.ndarray = ((self._a[at >> 3] >> (at & 7).astype(np.uint8)) & 1).astype(bool)
        return out

    def between(self, lo: int, hi: int) -> np.ndarray:
        """``(hi - lo,) bool``: the bits ``lo .. hi - 1``."""
        bits = np.unpackbits(self._a[lo >> 3:(hi + 7) >> 3], bitorder="little")
        out: np.ndarray = bits[lo & 7:(lo & 7) + hi - lo].astype(bool)
        return out

    @property
    def nbytes(self) -> int:
        """Bytes held (the spare capacity included)."""
        return int(self._a.nbytes)


def _block_room(count: np.ndarray) -> np.ndarray:
    """The postings a block of ``count`` (>= 2, ``(K,)`` int) has room for: the power of two
    at or above it (:class:`_Postings`)."""
    return np.left_shift(1, np.frexp(np.asarray(count, np.float64) - 1.0)[1]).astype(np.int64)


class _Postings:
    """Every word's postings (``uint32``, ``slot << _COUNT_BITS | n(w, i)``) in the order they
    came, in two flat arrays rather than an object per word (most words are seen in one
    image or a few: an object's own overhead would outweigh its postings), and every word's
    document frequency ``df``, which is also how many postings a word with any holds.

    ``head[w]`` (one ``uint32`` per word): 0 when ``w`` has no posting; below :data:`_BLOCK`
    its one posting itself; else ``_BLOCK | offset`` of its block in ``store``: its ``df[w]``
    (>= 2) postings, room up to the power of two at or above it (no count of its own: df
    is it). A block that fills up moves to a block twice as long at the store's end; the
    store is compacted once the blocks left behind take a quarter of it. A word whose
    postings were dropped keeps its df (:meth:`drop`)."""

    def __init__(self) -> None:
        self.head = _GrowingInts(np.uint32)
        # 1 byte a word until a count passes 127, then 2 until one passes 32,767: most words
        # are seen a few times; counters start narrow and widen (:meth:`_GrowingInts.add`)
        self.df = _GrowingInts(np.int8)
        self._store = np.zeros(2, np.uint32)  # gather reads entry 0 for a word without a block
        self._end = 0           # the store's used length
        self._dead = 0          # of it, in blocks left behind (at least)

    @property
    def nbytes(self) -> int:
        """Bytes held (the spare capacity included)."""
        return self.head.nbytes + self.df.nbytes + int(self._store.nbytes)

    def resize(self, n: int) -> None:
        """Room for words ``0 .. n - 1`` (new ones without postings, df 0)."""
        self.head.resize(n)
        self.df.resize(n)

    def gather(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The postings of ``words`` (``(K,) int64``, distinct), word after word in that order,
        ``(total,) uint32``, and how many each has, ``(K,) int64``."""
        h = self.head.view[words]
        block = h >= _BLOCK
        off = np.where(block, h & ~_BLOCK, 0).astype(np.int64)  # 0: read, then overwritten
        held = np.where(block, self.df.view[words], h != 0).astype(np.int64)
        start = np.cumsum(held) - held
        out = self._store.take(np.repeat(off - start, held) + np.arange(int(start[-1] + held[-1]) if len(held) else 0))
        single = (h != 0) & ~block
        out[start[single]] = h[single]
        return out, held

    def of(self, word: int) -> np.ndarray:
        """The postings of one word, ``(c,) uint32`` (empty beyond the words known)."""
        if not 0 <= word < self.head.n:
            return np.zeros(0, np.uint32)
        return self.gather(np.array([word], np.int64))[0]

    def append(self, words: np.ndarray, values: np.ndarray) -> None:
        """Append posting ``values[k]`` (``uint32`` < _BLOCK) to word ``words[k]`` (``(K,)
        int64``, distinct, below ``head.n``, none with dropped postings), each word's df
        counting it."""
        h = self.head.view[words]
        none = h == 0
        self.head.view[words[none]] = values[none]
        block = h >= _BLOCK
        off = (h[block] & ~_BLOCK).astype(np.int64)
        cnt = self.df.view[words[block]].astype(np.int64)
        full = (cnt & (cnt - 1)) == 0                       # a power of two: no room left
        room = ~full
        vb = values[block]
        self._store[off[room] + cnt[room]] = vb[room]
        # the rest move to new blocks at the end: a word with one posting to a block of 2,
        # a full block to one twice as long
        single = ~none & ~block
        hs, vs, ws = h[single], values[single], words[single]
        fo, fc, fv, fw = off[full], cnt[full], vb[full], words[block][full]
        k = len(hs)
        if k or len(fc):
            e0 = self._end
            end = e0 + 2 * k + int((2 * fc).sum())
            if end > len(self._store):
                grown = np.zeros(max(end, _grown(len(self._store))), np.uint32)
                grown[:e0] = self._store[:e0]
                self._store = grown
            st = self._store
            if k:
                new = st[e0:e0 + 2 * k]
                new[0::2], new[1::2] = hs, vs
                self.head.view[ws] = (e0 + 2 * np.arange(k)).astype(np.uint32) | _BLOCK
            if len(fc):
                size = 2 * fc
                start = e0 + 2 * k + np.cumsum(size) - size
                within = _within(fc)
                st[np.repeat(start, fc) + within] = st[np.repeat(fo, fc) + within]
                st[start + fc] = fv
                self.head.view[fw] = start.astype(np.uint32) | _BLOCK
                self._dead += int(fc.sum())                 # the full blocks: left behind
            self._end = end
        self.df.add(words, 1)
        if self._dead * 4 > self._end:
            self._compact()

    def find(self, word: int, value: int) -> int:
        """Where posting ``value`` is in ``word``'s postings, -1 when it is not there."""
        hit = np.flatnonzero(self.of(word) == value)
        return int(hit[0]) if len(hit) else -1

    def pop(self, word: int, k: int) -> None:
        """Remove the ``k``-th posting of ``word`` (the others keep their order; its df
        counts one less)."""
        h = int(self.head.view[word])
        c = int(self.df.view[word])
        self.df.view[word] = c - 1
        if h < _BLOCK:
            self.head.view[word] = 0
            return
        off = h & ~int(_BLOCK)
        self._store[off + k:off + c - 1] = self._store[off + k + 1:off + c].copy()
        if c == 2:  # one left: it goes back into the head
            self.head.view[word] = self._store[off]
            self._dead += int(_block_room(np.array([c]))[0])

    def drop(self, words: np.ndarray) -> None:
        """Forget the postings of ``words`` (``(K,) int64`` below ``head.n``); their df stay."""
        h = self.head.view[words]
        cnt = self.df.view[words[h >= _BLOCK]].astype(np.int64)
        self._dead += int(_block_room(cnt).sum()) if len(cnt) else 0
        self.head.view[words] = 0
        if self._dead * 4 > self._end:
            self._compact()

    def _compact(self) -> None:
        """Move every block to the front of a new store, in word order, each as long as
        its count needs (:func:`_block_room`), dropping the blocks left behind."""
        words = np.flatnonzero(self.head.view >= _BLOCK)
        off = (self.head.view[words] & ~_BLOCK).astype(np.int64)
        cnt = self.df.view[words].astype(np.int64)
        size = _block_room(cnt) if len(cnt) else np.zeros(0, np.int64)
        start = np.cumsum(size) - size
        end = int(size.sum())
        store = np.zeros(_grown(end), np.uint32)
        if len(cnt):
            within = _within(cnt)
            store[np.repeat(start, cnt) + within] = self._store[np.repeat(off, cnt) + within]
        self._store = store
        self.head.view[words] = start.astype(np.uint32) | _BLOCK
        self._end = end
        self._dead = 0


_COUNT_BITS = 10            # n(w, i) up to 1023
_COUNT_MASK = (1 << _COUNT_BITS) - 1
_BLOCK = np.uint32(1 << 31)  # a word's head with this bit set points to its block of postings
_MAX_SLOTS = 1 << (31 - _COUNT_BITS)  # 2,097,152 images indexed at once (a posting stays below _BLOCK)
_VIRTUAL_MARGIN = 256       # candidates kept for the virtual image beyond its n words


def _word_dtype(n_words: int) -> type:
    """The narrowest type for word ids below ``n_words``: uint16 while they fit, else int32."""
    return np.uint16 if n_words <= 0x10000 else np.int32


class InvertedIndex:
    """Word -> images it was seen in (with counts), and the tf-idf statistics.

    Each indexed image holds a *slot*; scores come back as one value per slot
    (:attr:`image_ids` says which image holds it, -1 for a free slot). Images added and
    never removed hold slots 0, 1, 2, ... in insertion order, so that scores are then
    simply in insertion order. :meth:`remove_image` takes an image out (a working memory
    moving a place to long-term memory): its words no longer vote and N, df, the
    occurrence counts and the virtual image no longer count it; its slot is reused by the
    next image added. An image may be added again after its removal (retrieval).
    """

    def __init__(self) -> None:
        # Postings: per word, slot << _COUNT_BITS | n(w, i) of each image it is in (4 bytes
        # an entry, in flat arrays: no object per word)
        self._post = _Postings()
        self._df = self._post.df                 # per word: images containing it
        self._occ = _GrowingInts(np.int8)        # per word: total occurrences (narrow as df)
        self._image_len = _GrowingInts()         # per slot: n(i), words (with repeats) in the image
        self._image_ids = _GrowingInts()         # per slot: the image in it, -1 when free
        # per image id: its slot + 1 when indexed, 0 never added, -1 removed (it may be
        # added again); arrays, not a dict and a list of Python ints (about 100 bytes an image)
        self._slot_at = _GrowingInts()
        self._n_indexed = 0                      # N
        self._free: list[int] = []               # free slots (a min-heap)
        self._last_added = -1                    # the highest image id added
        self._total = 0                          # sum of n(i) over the indexed images
        # Word ids below n_words with df == 0 (ids skipped, or words whose images all
        # left): while there is none, the virtual image is chosen among all the words
        # without listing them (no per-word list of the words in use).
        self._n_unused = 0
        # The virtual image's candidates (:meth:`virtual_image`): every word seen at least
        # _v_floor times; None: to be chosen again over all words.
        self._v_cand: np.ndarray | None = None
        self._v_floor = 1

    @property
    def n_images(self) -> int:
        """N: images indexed."""
        return self._n_indexed

    @property
    def n_slots(self) -> int:
        """Slots (the length of :meth:`vote`'s scores): indexed images plus free slots."""
        return self._image_ids.n

    @property
    def image_ids(self) -> np.ndarray:
        """``(n_slots,) int64``: the id of the image in each slot (= score order), -1 when
        free; the insertion order when no image was removed."""
        return self._image_ids.view.astype(np.int64)

    @property
    def n_words(self) -> int:
        """Words the index knows (the highest word id added + 1)."""
        return self._df.n

    def _slot(self, image_id: int) -> int:
        """The slot of image ``image_id``, -1 when it is not indexed."""
        if not 0 <= image_id < self._slot_at.n:
            return -1
        return max(int(self._slot_at.view[image_id]) - 1, -1)

    def __contains__(self, image_id: int) -> bool:
        return self._slot(int(image_id)) >= 0

    def add_image(self, image_id: int, words: np.ndarray) -> None:
        """Index image ``image_id`` with its words (``(K,) int``, repeats counted).

        A new image must have a higher id than every image added before; an image removed
        earlier may come back with its old id (and the same words)."""
        image_id = int(image_id)
        if self._slot(image_id) >= 0:
            raise ValueError(f"image {image_id} is indexed already")
        removed = 0 <= image_id < self._slot_at.n and int(self._slot_at.view[image_id]) == -1
        if image_id <= self._last_added and not removed:
            raise ValueError(f"image ids must increase: {image_id} after {self._last_added}")
        w = np.asarray(words, np.int64)
        if len(w) and w.min() < 0:
            raise ValueError("word ids must be >= 0")
        if self._free:
            slot = heapq.heappop(self._free)
        else:
            slot = self._image_ids.n
            if slot >= _MAX_SLOTS:
                raise ValueError(f"the inverted index holds at most {_MAX_SLOTS} images at once")
            self._image_ids.resize(slot + 1)
            self._image_len.resize(slot + 1)
        self._image_ids.view[slot] = image_id
        self._slot_at.resize(image_id + 1)
        self._slot_at.view[image_id] = slot + 1
        self._n_indexed += 1
        self._last_added = max(self._last_added, image_id)
        self._image_len.view[slot] = len(w)
        self._total += len(w)
        if not len(w):
            return
        uw, cnt = np.unique(w, return_counts=True)
        top = int(uw[-1]) + 1
        if top > self._df.n:
            self._n_unused += top - self._df.n
            self._post.resize(top)
            self._occ.resize(top)
        self._n_unused -= int(np.count_nonzero(self._df.view[uw] == 0))
        # n(w, i) is kept up to 1023 (a word more often in one image counts 1023 times in
        # its vote: not reached with a few hundred features per image); df counts it
        self._post.append(uw, ((slot << _COUNT_BITS) | np.minimum(cnt, _COUNT_MASK)).astype(np.uint32))
        self._occ.add(uw, cnt)
        if self._v_cand is not None:  # words now seen often enough join the candidates
            up = uw[self._occ.view[uw] >= self._v_floor]
            if len(up):
                dt = _word_dtype(self._df.n)
                self._v_cand = sorted_union(self._v_cand.astype(dt, copy=False), up.astype(dt))

    def remove_image(self, image_id: int, words: np.ndarray) -> None:
        """Take image ``image_id`` out of the index, given the words it was added with
        (``(K,) int``, repeats counted; the caller keeps them to add the image back).
        Costs the length of its words' posting lists, not the index's size."""
        image_id = int(image_id)
        slot = self._slot(image_id)
        if slot < 0:
            raise ValueError(f"image {image_id} is not indexed")
        w = np.asarray(words, np.int64)
        if len(w) != int(self._image_len.view[slot]):
            raise ValueError(f"image {image_id} was indexed with {int(self._image_len.view[slot])} "
                             f"words, not {len(w)}")
        uw, cnt = np.unique(w, return_counts=True)
        if len(uw) and (uw[0] < 0 or uw[-1] >= self._df.n):
            raise ValueError(f"image {image_id}: word ids outside 0 .. {self._df.n - 1}")
        where = []
        for wid, c in zip(uw.tolist(), np.minimum(cnt, _COUNT_MASK).tolist()):
            k = self._post.find(wid, slot << _COUNT_BITS | c)
            if k < 0:
                raise ValueError(f"image {image_id} was not indexed with word {wid} x {c}")
            where.append(k)
        for wid, k in zip(uw.tolist(), where):
            self._post.pop(wid, k)  # df counts one less
        self._slot_at.view[image_id] = -1
        self._n_indexed -= 1
        if len(uw):
            self._occ.view[uw] -= cnt
            self._n_unused += int(np.count_nonzero(self._df.view[uw] == 0))
        self._total -= len(w)
        self._v_cand = None  # counts fell: the candidates are chosen again
        self._image_len.view[slot] = 0
        self._image_ids.view[slot] = -1
        heapq.heappush(self._free, slot)

    def drop_postings(self, words: np.ndarray) -> None:
        """Free the postings of ``words`` that no query can contain any more (words purged
        from the vocabulary's search): their images keep their word counts and the words
        their document frequencies, so every other score stays as it was. Not for an index
        whose images may be removed again (a bounded working memory checks postings)."""
        w = np.asarray(words, np.int64)
        self._post.drop(w[(w >= 0) & (w < self._post.head.n)])

    def document_frequency(self, word: int) -> int:
        """df(w): indexed images that contain ``word``."""
        return int(self._df.view[word]) if word < self._df.n else 0

    def occurrences(self) -> np.ndarray:
        """``(n_words,) int64``: total occurrences of each word over the indexed images."""
        return self._occ.view.astype(np.int64)

    def idf(self, words: np.ndarray) -> np.ndarray:
        """``log(N / df(w))`` for each word, ``(K,) float64``; 0 for a word in no image."""
        w = np.asarray(words, np.int64)
        df = np.zeros(len(w), np.float64)
        known = w < self._df.n
        df[known] = self._df.view[w[known]]
        out = np.zeros(len(w), np.float64)
        seen = df > 0
        out[seen] = np.log(self.n_images / df[seen])
        return out

    def tfidf(self, word: int, image_id: int) -> float:
        """tf(w, i) * idf(w) with the current counts (0 when ``word`` is not in the image)."""
        slot = self._slot(int(image_id))
        if slot < 0:
            raise KeyError(image_id)
        post = self._post.of(int(word))
        mine = post[(post >> _COUNT_BITS) == slot]
        if not len(mine):
            return 0.0
        n_wi = int(mine[0] & _COUNT_MASK)
        return n_wi / int(self._image_len.view[slot]) * float(self.idf(np.array([word]))[0])

    def virtual_image(self) -> np.ndarray:
        """The words of the virtual "no loop" image I_-1: the ``n`` most frequently seen
        words, ``n`` = round(mean words per image); ``(n,) int64``, most frequent first
        (ties: the older word first). Empty before the first word.

        Chosen among candidates, not all words: every word seen at least ``floor`` times
        (kept as images add occurrences). While they number ``n`` or more, the ``n``-th
        most frequent word is seen at least ``floor`` times, so every word that can be
        among the ``n`` (ties included) is a candidate and the choice is the one over all
        words. The candidates are chosen again over all words after a removal (counts
        fall), or when they number fewer than ``n`` or many more; so many (over the first
        images, when most words are seen once) are not kept: the choice is the same with
        any candidates that hold every word that can be among the ``n``."""
        if not self.n_images or not self._total:
            return np.zeros(0, np.int64)
        n = max(1, int(round(self._total / self.n_images)))
        cand = self._v_cand
        if cand is None or len(cand) < n or len(cand) > 4 * n + _VIRTUAL_MARGIN:
            cand = self._virtual_candidates(n + _VIRTUAL_MARGIN)
            if len(cand) > 4 * n + _VIRTUAL_MARGIN:  # they would be chosen again next time
                self._v_cand = None
        occ = self._occ.view[cand]
        n = min(n, len(cand))  # fewer candidates only when fewer words are in use
        # Stable sort on -occurrences: equal counts keep word-id order.
        part = np.argpartition(-occ, n - 1)[:n] if n < len(occ) else np.arange(len(occ))
        top = cand[occ >= occ[part].min()]
        order = top[np.lexsort((top, -self._occ.view[top]))]
        return order[:n].astype(np.int64)

    def _virtual_candidates(self, k: int) -> np.ndarray:
        """The words seen at least as often as the ``k``-th most frequent (all the words in
        use when fewer), ``(M,)`` sorted (uint16 or int32: :func:`_word_dtype`), M >= min(k,
        words in use); kept as the candidates with that count as their floor (at least 1:
        words in use only)."""
        occ = self._occ.view
        floor = 1
        if k < len(occ):
            floor = max(1, int(np.partition(occ, len(occ) - k)[len(occ) - k]))
        self._v_floor = floor
        self._v_cand = np.flatnonzero(occ >= floor).astype(_word_dtype(len(occ)))
        return self._v_cand

    def vote(self, words: np.ndarray) -> tuple[np.ndarray, float]:
        """The voting scores of Sec. IV-B for a query image with ``words`` (``(K,) int``,
        repeats counted, -1 ignored).

        Each occurrence of a word in the query adds tf(w, i) * idf(w) to every indexed image
        i that contains w, and tf = 1 / n times idf(w) to the virtual image when w is one of
        its words. Returns ``(n_slots,) float64`` scores, one per slot (:attr:`image_ids`:
        insertion order when no image was removed; 0 for a free slot), and the virtual
        image's score.
        """
        w = np.asarray(words, np.int64)
        w = w[(w >= 0) & (w < self._df.n)]
        if not len(w) or not self.n_images:
            return np.zeros(self.n_slots, np.float64), 0.0
        uw, cq = np.unique(w, return_counts=True)
        df = self._df.view[uw]
        keep = df > 0
        uw, cq, df = uw[keep], cq[keep], df[keep]
        if not len(uw):
            return np.zeros(self.n_slots, np.float64), 0.0
        idf = np.log(self.n_images / df)
        postings, held = self._post.gather(uw)  # held: df, bar dropped postings
        packed = postings.astype(np.int64)
        slots = packed >> _COUNT_BITS
        n_wi = packed & _COUNT_MASK
        per_word = cq * idf
        weights = np.repeat(per_word, held) * n_wi / self._image_len.view[slots]
        # the sums themselves (one pass over the slots, not a zeroed array added to)
        scores: np.ndarray = np.bincount(slots, weights=weights, minlength=self.n_slots).astype(np.float64, copy=False)
        virt = self.virtual_image()
        in_virt = sorted_isin(uw, np.sort(virt))
        virtual = float((per_word[in_virt]).sum() / len(virt)) if len(virt) else 0.0
        return scores, virtual

    def memory_bytes(self) -> int:
        """Bytes held by the postings (their arrays, spare capacity included), the per-word
        and per-slot counters, the per-image slots, the virtual image's candidates, and the
        free slots' heap (a list of Python ints: its table and the ints, which a working
        memory's removals make)."""
        counters = sum(g.nbytes for g in (self._occ, self._image_len, self._image_ids, self._slot_at))
        virtual = self._v_cand.nbytes if self._v_cand is not None else 0
        return self._post.nbytes + counters + virtual + sys.getsizeof(self._free) + _INT_BYTES * len(self._free)
