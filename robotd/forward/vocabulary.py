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

import itertools
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
    """

    word_radius_l2: float = 0.4
    word_radius_bits: int = 40
    connectivity: int = 12
    expansion_add: int = 40
    expansion_search: int = 24


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

    def __len__(self) -> int:
        return self._n_words

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
        if self.binary:
            return np.bitwise_count(d[:, None, :] ^ d[None, :, :]).sum(axis=2).astype(np.float64)
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
        new = np.flatnonzero(words < 0)
        if not len(new):
            return words, 0
        dist = self._pairwise(d[new])
        owner = np.full(len(new), -1, np.int64)
        founders = []
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
        words[new] = owner
        return words, len(founders)


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


class InvertedIndex:
    """Word -> images it was seen in (with counts), and the tf-idf statistics.

    Images are added with increasing ids (the detector's image numbers); scores come back
    as one value per indexed image, in insertion order (:attr:`image_ids`).
    """

    def __init__(self) -> None:
        self._post_slots: list[list[int]] = []   # per word: slots of the images containing it
        self._post_counts: list[list[int]] = []  # per word: n(w, i) for those images
        self._df = _GrowingInts()                # per word: images containing it
        self._occ = _GrowingInts()               # per word: total occurrences
        self._image_len = _GrowingInts()         # per slot: n(i), words (with repeats) in the image
        self._image_ids: list[int] = []
        self._total = 0                          # sum of n(i)

    @property
    def n_images(self) -> int:
        """N: images indexed."""
        return len(self._image_ids)

    @property
    def image_ids(self) -> np.ndarray:
        """``(N,) int64``: the id of each indexed image, in insertion order (= score order)."""
        return np.asarray(self._image_ids, np.int64)

    @property
    def n_words(self) -> int:
        """Words the index knows (the highest word id added + 1)."""
        return self._df.n

    def add_image(self, image_id: int, words: np.ndarray) -> None:
        """Index image ``image_id`` with its words (``(K,) int``, repeats counted)."""
        if self._image_ids and image_id <= self._image_ids[-1]:
            raise ValueError(f"image ids must increase: {image_id} after {self._image_ids[-1]}")
        w = np.asarray(words, np.int64)
        if len(w) and w.min() < 0:
            raise ValueError("word ids must be >= 0")
        slot = len(self._image_ids)
        self._image_ids.append(int(image_id))
        self._image_len.resize(slot + 1)
        self._image_len.view[slot] = len(w)
        self._total += len(w)
        if not len(w):
            return
        uw, cnt = np.unique(w, return_counts=True)
        top = int(uw[-1]) + 1
        if top > self._df.n:
            for _ in range(top - len(self._post_slots)):
                self._post_slots.append([])
                self._post_counts.append([])
            self._df.resize(top)
            self._occ.resize(top)
        for wid, c in zip(uw.tolist(), cnt.tolist()):
            self._post_slots[wid].append(slot)
            self._post_counts[wid].append(c)
        self._df.view[uw] += 1
        self._occ.view[uw] += cnt

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
        slot = self._image_ids.index(image_id)
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
        occ = self._occ.view
        n = min(n, len(occ))
        # Stable sort on -occurrences: equal counts keep word-id order.
        part = np.argpartition(-occ, n - 1)[:n] if n < len(occ) else np.arange(len(occ))
        kth = occ[part].min()
        cand = np.flatnonzero(occ >= kth)
        order = cand[np.lexsort((cand, -occ[cand]))]
        return order[:n].astype(np.int64)

    def vote(self, words: np.ndarray) -> tuple[np.ndarray, float]:
        """The voting scores of Sec. IV-B for a query image with ``words`` (``(K,) int``,
        repeats counted, -1 ignored).

        Each occurrence of a word in the query adds tf(w, i) * idf(w) to every indexed image
        i that contains w, and tf = 1 / n times idf(w) to the virtual image when w is one of
        its words. Returns ``(N,) float64`` scores in insertion order and the virtual
        image's score.
        """
        scores = np.zeros(self.n_images, np.float64)
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
        lists = [self._post_slots[k] for k in uw.tolist()]
        slots = np.fromiter(itertools.chain.from_iterable(lists), np.int64, int(df.sum()))
        n_wi = np.fromiter(itertools.chain.from_iterable(self._post_counts[k] for k in uw.tolist()),
                           np.int64, int(df.sum()))
        per_word = cq * idf
        weights = np.repeat(per_word, df) * n_wi / self._image_len.view[slots]
        scores += np.bincount(slots, weights=weights, minlength=self.n_images)
        virt = self.virtual_image()
        in_virt = np.isin(uw, virt)
        virtual = float((per_word[in_virt]).sum() / len(virt)) if len(virt) else 0.0
        return scores, virtual

    def memory_bytes(self) -> int:
        """Approximate bytes held by the postings (8 per slot and count entry) and counters."""
        entries = sum(len(p) for p in self._post_slots)
        return 16 * entries + 8 * (2 * self._df.n + self._image_len.n)
