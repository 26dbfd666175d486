"""The incremental visual vocabulary and its inverted index (paper 000 Sec. III, IV-B).

**Vocabulary** (:class:`Vocabulary`). Words are created online, as in Filliat 2007 (the
paper's ref. [7]): a descriptor is quantised to its nearest word when that word lies
within ``word_radius``; otherwise it becomes a new word (its descriptor is the word's
centre, which never moves afterwards). Descriptors of one image that found no word are
grouped greedily among themselves first, so one image does not mint two words for one
scene point. The nearest-word search is an HNSW graph (usearch): insertion and search are
logarithmic in the number of words, where a flat search would be linear. The paper used a
tree of its own (Sec. III); usearch is a kept library with incremental insertion, a
Hamming metric for ORB and removal of keys (what a later working memory needs), so we do
not write a tree.

**Inverted index** (:class:`InvertedIndex`). For every word, the images it was seen in and
how often; for every image, its number of words. Nothing else is stored: the tf-idf weight
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
from array import array
from dataclasses import dataclass

import numpy as np

__all__ = ["InvertedIndex", "Vocabulary", "VocabularyParams"]


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
            many images have come after it (iBoW-LCD's purging, issue 24): most words of an
            image never recur, and they would otherwise fill the search structure; 0 =
            never (the paper). A purged word keeps its id and its place in the inverted
            index (it still counts for its one image) but no later descriptor can find it.
    """

    word_radius_l2: float = 0.4
    word_radius_bits: int = 40
    connectivity: int = 12
    expansion_add: int = 40
    expansion_search: int = 24
    purge_after: int = 0


class Vocabulary:
    """Visual words created online with a logarithmic-time nearest-word search.

    ``binary``: descriptors are packed bits (``(N, 32) uint8``, Hamming distance) instead of
    unit-length floats (``(N, dim) float32``, Euclidean distance). Word ids are 0, 1, 2, ...
    in creation order.
    """

    def __init__(self, dim: int = 128, binary: bool = False,
                 params: VocabularyParams = VocabularyParams()) -> None:
        from usearch.index import Index

        self.params = params
        self.binary = binary
        self.dim = dim
        if binary:
            self._index = Index(ndim=dim * 8, metric="hamming", dtype="b1",
                                connectivity=params.connectivity,
                                expansion_add=params.expansion_add,
                                expansion_search=params.expansion_search)
            # usearch's Hamming distance is in bits; compare with the radius as is.
            self._radius = float(params.word_radius_bits)
        else:
            self._index = Index(ndim=dim, metric="l2sq", dtype="f32",
                                connectivity=params.connectivity,
                                expansion_add=params.expansion_add,
                                expansion_search=params.expansion_search)
            self._radius = float(params.word_radius_l2) ** 2  # usearch returns squared L2
        self._n_words = 0
        self._images = 0                        # add() calls so far (one per image)
        self._born = _GrowingInts()             # per word: the image (add() call) that made it
        self._seen = _GrowingInts()             # per word: images it was found in
        self._unpurged_from = 0                 # words below this id were all examined
        self.purged = 0
        # What the last add() changed, for a store to write (robotd.io.store, issue 24):
        self.last_new: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros((0, dim)))
        self.last_purged = np.zeros(0, np.int64)

    def __len__(self) -> int:
        """Words made so far (purged ones included: ids are never reused)."""
        return self._n_words

    def memory_bytes(self) -> int:
        """Bytes of the word search (usearch's own figure, its reserved capacity included)
        and the per-word counters."""
        return int(self._index.memory_usage) + 16 * self._n_words

    @property
    def n_searchable(self) -> int:
        """Words the search can still find (made minus purged)."""
        return self._n_words - self.purged

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
        if self.binary:  # |a xor b| = |a| + |b| - 2 a.b over the bits: one float32 product,
            # far faster than an (N, N, 32) xor array; exact (integers below 2^24)
            bits = np.unpackbits(d, axis=1).astype(np.float32)
            ones = bits.sum(axis=1)
            return (ones[:, None] + ones[None, :] - 2.0 * (bits @ bits.T)).astype(np.float64)
        sq = np.einsum("ij,ij->i", d, d).astype(np.float64)
        return np.maximum(sq[:, None] + sq[None, :] - 2.0 * (d.astype(np.float64) @ d.T.astype(np.float64)), 0.0)

    def add(self, descriptors: np.ndarray) -> tuple[np.ndarray, int]:
        """Quantise one image's descriptors, creating words for those that found none.

        Returns the word of each descriptor, ``(N,) int64`` (never -1), and how many words
        were created. Unmatched descriptors are taken in order; each one that no earlier
        new word of this image covers founds a word that also takes every later unmatched
        descriptor within the radius.
        """
        d = self._check(descriptors)
        words = self.quantize(d)
        self._images += 1
        self.last_new = (np.zeros(0, np.int64), d[:0])
        self.last_purged = np.zeros(0, np.int64)
        found = np.unique(words[words >= 0])
        self._seen.view[found] += 1
        new = np.flatnonzero(words < 0)
        if not len(new):
            self._purge()
            return words, 0
        dist = self._pairwise(d[new])
        owner = np.full(len(new), -1, np.int64)
        founders: list[int] = []
        for k in range(len(new)):
            if owner[k] >= 0:
                continue
            wid = self._n_words + len(founders)
            founders.append(k)
            claim = (owner < 0) & (dist[k] <= self._radius)
            claim[:k] = False
            owner[claim] = wid
            owner[k] = wid
        keys = np.arange(self._n_words, self._n_words + len(founders), dtype=np.int64)
        self._index.add(keys, d[new[founders]], threads=1)
        self._n_words += len(founders)
        n0 = self._born.n
        self._born.resize(n0 + len(founders))
        self._born.view[n0:] = self._images - 1
        self._seen.resize(n0 + len(founders))
        self._seen.view[n0:] = 1
        words[new] = owner
        self.last_new = (keys, d[new[founders]])
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
        if len(keep):
            self._index.add(keep.astype(np.int64), d[keep], threads=1)
        self._n_words = n
        self._born.resize(n)
        self._born.view[:] = born
        self._seen.resize(n)
        self._seen.view[:] = np.asarray(seen, np.int64)
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
        lo = self._unpurged_from
        hi = lo + int(np.searchsorted(self._born.view[lo:], limit, side="right"))
        if hi <= lo:
            return
        gone = lo + np.flatnonzero(self._seen.view[lo:hi] <= 1)
        if len(gone):
            self._index.remove(gone.astype(np.int64))
            self.purged += len(gone)
            self.last_purged = gone.astype(np.int64)
        self._unpurged_from = hi


class _GrowingInts:
    """An int64 array that grows by doubling (amortised O(1) append)."""

    def __init__(self) -> None:
        self._a = np.zeros(64, np.int64)
        self.n = 0

    def resize(self, n: int) -> None:
        if n > len(self._a):
            b = np.zeros(max(n, 2 * len(self._a)), np.int64)
            b[:self.n] = self._a[:self.n]
            self._a = b
        self.n = max(self.n, n)

    @property
    def view(self) -> np.ndarray:
        return self._a[:self.n]


_NO_POSTINGS = array("i")  # shared by the words whose postings were dropped (never appended to)


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
        # Postings as C int arrays (4 bytes an entry, not a Python int object each).
        self._post_slots: list[array[int]] = []  # per word: slots of the images containing it
        self._post_counts: list[array[int]] = []  # per word: n(w, i) for those images
        self._df = _GrowingInts()                # per word: images containing it
        self._occ = _GrowingInts()               # per word: total occurrences
        self._image_len = _GrowingInts()         # per slot: n(i), words (with repeats) in the image
        self._image_ids: list[int] = []          # per slot: the image in it, -1 when free
        self._slot_of: dict[int, int] = {}       # image id -> slot
        self._free: list[int] = []               # free slots (a min-heap)
        self._last_added = -1                    # the highest image id added
        self._removed: set[int] = set()          # ids removed (they may be added again)
        self._total = 0                          # sum of n(i) over the indexed images
        # Words with df > 0, packed (the virtual image is chosen among them only, so its
        # cost follows the indexed images' words, not every word ever made).
        self._active = _GrowingInts()            # the words with df > 0, in no order
        self._active_pos = _GrowingInts()        # per word: its position in _active, or -1

    @property
    def n_images(self) -> int:
        """N: images indexed."""
        return len(self._slot_of)

    @property
    def n_slots(self) -> int:
        """Slots (the length of :meth:`vote`'s scores): indexed images plus free slots."""
        return len(self._image_ids)

    @property
    def image_ids(self) -> np.ndarray:
        """``(n_slots,) int64``: the id of the image in each slot (= score order), -1 when
        free; the insertion order when no image was removed."""
        return np.asarray(self._image_ids, np.int64)

    @property
    def n_words(self) -> int:
        """Words the index knows (the highest word id added + 1)."""
        return self._df.n

    def __contains__(self, image_id: int) -> bool:
        return image_id in self._slot_of

    def add_image(self, image_id: int, words: np.ndarray) -> None:
        """Index image ``image_id`` with its words (``(K,) int``, repeats counted).

        A new image must have a higher id than every image added before; an image removed
        earlier may come back with its old id (and the same words)."""
        image_id = int(image_id)
        if image_id in self._slot_of:
            raise ValueError(f"image {image_id} is indexed already")
        if image_id <= self._last_added and image_id not in self._removed:
            raise ValueError(f"image ids must increase: {image_id} after {self._last_added}")
        w = np.asarray(words, np.int64)
        if len(w) and w.min() < 0:
            raise ValueError("word ids must be >= 0")
        if self._free:
            slot = heapq.heappop(self._free)
            self._image_ids[slot] = image_id
        else:
            slot = len(self._image_ids)
            self._image_ids.append(image_id)
            self._image_len.resize(slot + 1)
        self._slot_of[image_id] = slot
        self._removed.discard(image_id)
        self._last_added = max(self._last_added, image_id)
        self._image_len.view[slot] = len(w)
        self._total += len(w)
        if not len(w):
            return
        uw, cnt = np.unique(w, return_counts=True)
        top = int(uw[-1]) + 1
        if top > self._df.n:
            for _ in range(top - len(self._post_slots)):
                self._post_slots.append(array("i"))
                self._post_counts.append(array("i"))
            old = self._df.n
            self._df.resize(top)
            self._occ.resize(top)
            self._active_pos.resize(top)
            self._active_pos.view[old:] = -1
        for wid, c in zip(uw.tolist(), cnt.tolist()):
            if self._post_slots[wid] is _NO_POSTINGS:
                self._post_slots[wid], self._post_counts[wid] = array("i"), array("i")
            self._post_slots[wid].append(slot)
            self._post_counts[wid].append(c)
        born = uw[self._df.view[uw] == 0]
        self._df.view[uw] += 1
        self._occ.view[uw] += cnt
        if len(born):
            a = self._active.n
            self._active.resize(a + len(born))
            self._active.view[a:] = born
            self._active_pos.view[born] = np.arange(a, a + len(born))

    def remove_image(self, image_id: int, words: np.ndarray) -> None:
        """Take image ``image_id`` out of the index, given the words it was added with
        (``(K,) int``, repeats counted; the caller keeps them to add the image back).
        Costs the length of its words' posting lists, not the index's size."""
        image_id = int(image_id)
        slot = self._slot_of.get(image_id)
        if slot is None:
            raise ValueError(f"image {image_id} is not indexed")
        w = np.asarray(words, np.int64)
        if len(w) != int(self._image_len.view[slot]):
            raise ValueError(f"image {image_id} was indexed with {int(self._image_len.view[slot])} "
                             f"words, not {len(w)}")
        uw, cnt = np.unique(w, return_counts=True)
        if len(uw) and (uw[0] < 0 or uw[-1] >= self._df.n):
            raise ValueError(f"image {image_id}: word ids outside 0 .. {self._df.n - 1}")
        where = []
        for wid, c in zip(uw.tolist(), cnt.tolist()):
            ps = self._post_slots[wid]
            k = ps.index(slot) if slot in ps else -1
            if k < 0 or self._post_counts[wid][k] != c:
                raise ValueError(f"image {image_id} was not indexed with word {wid} x {c}")
            where.append(k)
        for wid, k in zip(uw.tolist(), where):
            self._post_slots[wid].pop(k)
            self._post_counts[wid].pop(k)
        del self._slot_of[image_id]
        if len(uw):
            self._df.view[uw] -= 1
            self._occ.view[uw] -= cnt
            for wid in uw[self._df.view[uw] == 0].tolist():  # swap-remove from the active list
                pos = int(self._active_pos.view[wid])
                last = int(self._active.view[self._active.n - 1])
                self._active.view[pos] = last
                self._active_pos.view[last] = pos
                self._active_pos.view[wid] = -1
                self._active.n -= 1
        self._total -= len(w)
        self._image_len.view[slot] = 0
        self._image_ids[slot] = -1
        heapq.heappush(self._free, slot)
        self._removed.add(image_id)

    def drop_postings(self, words: np.ndarray) -> None:
        """Free the postings of ``words`` that no query can contain any more (words purged
        from the vocabulary's search): their images keep their word counts and the words
        their document frequencies, so every other score stays as it was. Not for an index
        whose images may be removed again (a bounded working memory checks postings)."""
        for wid in np.asarray(words, np.int64).tolist():
            if 0 <= wid < len(self._post_slots):
                self._post_slots[wid] = _NO_POSTINGS
                self._post_counts[wid] = _NO_POSTINGS

    def document_frequency(self, word: int) -> int:
        """df(w): indexed images that contain ``word``."""
        return int(self._df.view[word]) if word < self._df.n else 0

    def occurrences(self) -> np.ndarray:
        """``(n_words,) int64``: total occurrences of each word over the indexed images."""
        return self._occ.view.copy()

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
        slot = self._slot_of[image_id]
        if word >= len(self._post_slots) or slot not in self._post_slots[word]:
            return 0.0
        n_wi = self._post_counts[word][self._post_slots[word].index(slot)]
        return n_wi / int(self._image_len.view[slot]) * float(self.idf(np.array([word]))[0])

    def virtual_image(self) -> np.ndarray:
        """The words of the virtual "no loop" image I_-1: the ``n`` most frequently seen
        words, ``n`` = round(mean words per image); ``(n,) int64``, most frequent first
        (ties: the older word first). Empty before the first word."""
        if not self.n_images or not self._total:
            return np.zeros(0, np.int64)
        n = max(1, int(round(self._total / self.n_images)))
        act = self._active.view              # the words with df > 0 (occurrences > 0)
        occ = self._occ.view[act]
        n = min(n, len(act))
        # Stable sort on -occurrences: equal counts keep word-id order.
        part = np.argpartition(-occ, n - 1)[:n] if n < len(occ) else np.arange(len(occ))
        kth = occ[part].min()
        cand = act[occ >= kth]
        occ_c = self._occ.view[cand]
        order = cand[np.lexsort((cand, -occ_c))]
        return order[:n].astype(np.int64)

    def vote(self, words: np.ndarray) -> tuple[np.ndarray, float]:
        """The voting scores of Sec. IV-B for a query image with ``words`` (``(K,) int``,
        repeats counted, -1 ignored).

        Each occurrence of a word in the query adds tf(w, i) * idf(w) to every indexed image
        i that contains w, and tf = 1 / n times idf(w) to the virtual image when w is one of
        its words. Returns ``(n_slots,) float64`` scores, one per slot (:attr:`image_ids`:
        insertion order when no image was removed; 0 for a free slot), and the virtual
        image's score.
        """
        scores = np.zeros(self.n_slots, np.float64)
        w = np.asarray(words, np.int64)
        w = w[(w >= 0) & (w < self._df.n)]
        if not len(w) or not self.n_images:
            return scores, 0.0
        uw, cq = np.unique(w, return_counts=True)
        df = self._df.view[uw]
        keep = df > 0
        uw, cq, df = uw[keep], cq[keep], df[keep]
        if not len(uw):
            return scores, 0.0
        idf = np.log(self.n_images / df)
        ids = uw.tolist()
        slots = np.concatenate([np.frombuffer(self._post_slots[k], np.int32) for k in ids]).astype(np.int64)
        n_wi = np.concatenate([np.frombuffer(self._post_counts[k], np.int32) for k in ids])
        held = np.fromiter((len(self._post_slots[k]) for k in ids), np.int64, len(ids))  # df, bar dropped postings
        per_word = cq * idf
        weights = np.repeat(per_word, held) * n_wi / self._image_len.view[slots]
        scores += np.bincount(slots, weights=weights, minlength=self.n_slots)
        virt = self.virtual_image()
        in_virt = np.isin(uw, virt)
        virtual = float((per_word[in_virt]).sum() / len(virt)) if len(virt) else 0.0
        return scores, virtual

    def memory_bytes(self) -> int:
        """Bytes held by the postings (the int arrays with their object overhead, and the
        lists holding them) and the per-word and per-slot counters."""
        posting = sum(sys.getsizeof(a) for a in self._post_slots if a is not _NO_POSTINGS) + sum(
            sys.getsizeof(a) for a in self._post_counts if a is not _NO_POSTINGS)
        lists = sys.getsizeof(self._post_slots) + sys.getsizeof(self._post_counts)
        return posting + lists + 8 * (4 * self._df.n + self._image_len.n)
