"""A working memory of places for the forward detector (after RTAB-Map's
working / long-term memory, Labbe and Michaud 2013). Algorithm layer: no I/O.

The paper's detector (000) compares each image with every past image: the inverted index,
the votes and the Bayes filter grow with the run. :class:`WorkingMemory` bounds that part:

- **Working memory (WM)**: the places (past images) whose words are in the inverted index.
  Only they vote and only they are hypotheses of the Bayes filter.
- **Long-term memory (LTM)**: places moved out of WM when it holds more than
  ``max_places``. Their postings leave the inverted index (N, df, the occurrence counts and
  the virtual image no longer count them), but their words are kept here (and their
  features by the detector), so they can come back.
- **Transfer**: the least recently used place goes first; among equally recent ones the
  lowest weight, then the oldest. "Used" means added, retrieved, or in the neighbourhood
  the filter believed most (above ``retrieve_threshold``); the weight counts the verified
  loops a place took part in. The last ``protect_recent`` images (the p images that are not
  hypotheses yet, and the filter's neighbourhood beyond them) and the places used at this
  image are never transferred. (RTAB-Map ranks by weight first; with weights from loops
  that moves freshly retrieved places, weight 0, straight back out while places that
  closed a loop once stay for ever, so recency comes first here.)
- **Retrieval**: when the filter's best neighbourhood holds at least
  ``retrieve_threshold`` of the posterior (a place is being recognised, before it reaches
  the loop threshold), up to ``max_retrieved`` LTM places near it come back into WM: the
  places it closed verified loops with first, then its neighbours in time within
  ``retrieve_radius`` images, nearest first. They are hypotheses from the next image on,
  where the filter's diffusion from the recognised neighbour gives them mass at once
  (:func:`robotd.forward.filter.predict_ids`).

- **Time budget** (optional, as RTAB-Map's time threshold): when the stages the working
  memory bounds (the vote and the filter) took longer than ``time_budget_s`` for an image,
  that share of the places over the budget leaves at once: ``ceil(n * (1 - budget /
  time))`` of the ``n`` places, with the same ranking. The memory then grows again by one
  place per image until the next image over the budget (or ``max_places``).

With neither bound (the default) nothing ever leaves WM and the detector is exactly the
paper's. The vocabulary itself (the word centres in its search structure) is not bounded:
its search time grows with the logarithm of the number of words (paper Fig. 7), and the
words of LTM places must still be found when those places come back.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import numpy as np

from robotd.forward.vocabulary import InvertedIndex, _GrowingInts

__all__ = ["MemoryParams", "WorkingMemory"]


@dataclass(frozen=True)
class MemoryParams:
    """Parameters of the working memory.

    Fields:
        max_places: at most this many places in WM after each image (None: no bound, the
            paper's detector).
        retrieve_threshold: retrieve around the best neighbourhood when it holds at least
            this much of the posterior (below the loop threshold, so retrieval comes first).
        retrieve_radius: LTM places within this many images of the recognised place are
            its neighbours in time.
        max_retrieved: at most this many places come back per image (RTAB-Map: 2).
        time_budget_s: seconds the vote and the filter may take per image (None: no time
            budget); over it, places leave in proportion (see the module's note).
    """

    max_places: int | None = None
    retrieve_threshold: float = 0.5
    retrieve_radius: int = 5
    max_retrieved: int = 3
    time_budget_s: float | None = None

    @property
    def bounded(self) -> bool:
        """True when places can leave the working memory (a size bound or a time budget)."""
        return self.max_places is not None or self.time_budget_s is not None

    def __post_init__(self) -> None:
        if self.time_budget_s is not None and not self.time_budget_s > 0:
            raise ValueError(f"time_budget_s must be positive or None, got {self.time_budget_s}")
        if self.max_places is not None and self.max_places < 1:
            raise ValueError(f"max_places must be >= 1 or None, got {self.max_places}")
        if not 0.0 <= self.retrieve_threshold <= 1.0:
            raise ValueError(f"retrieve_threshold must be in [0, 1], got {self.retrieve_threshold}")
        if self.retrieve_radius < 0 or self.max_retrieved < 0:
            raise ValueError("retrieve_radius and max_retrieved must be >= 0")


class WorkingMemory:
    """Which places are in the inverted index, and moving them in and out of it.

    ``index``: the detector's inverted index (this class adds and removes its images);
    ``protect_recent``: the last images that are never transferred; ``neighbours``: the
    filter's neighbourhood half-width (the places :meth:`touch` marks per image). Place ids
    are image ids, added in increasing order.
    """

    def __init__(self, index: InvertedIndex, params: MemoryParams = MemoryParams(),
                 protect_recent: int = 12, neighbours: int = 2) -> None:
        # Never transferred at one image: the recent ones, the retrieved ones, the touched ones.
        pinned = protect_recent + params.max_retrieved + 2 * neighbours + 1
        if params.max_places is not None and params.max_places <= pinned:
            raise ValueError(f"max_places ({params.max_places}) must exceed {pinned}: the "
                             f"{protect_recent} recent images, {params.max_retrieved} retrieved and "
                             f"{2 * neighbours + 1} recognised places are never transferred at once")
        self.index = index
        self.params = params
        self.protect_recent = protect_recent
        # per place, in arrays (not lists of Python ints and a set: about 100 bytes a place)
        self._words: list[np.ndarray] = []      # its words (int32, repeats kept); bounded only
        self._weight = _GrowingInts()           # verified loops it took part in
        self._used = _GrowingInts()             # last image at which it was used
        self._in_wm = _GrowingInts(np.uint8)    # 1 while in WM
        self._n_wm = 0
        self._links: dict[int, set[int]] = {}   # place -> places it closed verified loops with
        self._wm_sorted: np.ndarray | None = np.zeros(0, np.int64)
        self.transferred = 0                    # places moved to LTM, in all
        self.retrieved = 0                      # places brought back, in all

    # --- state ----------------------------------------------------------------------------
    def __len__(self) -> int:
        """Places in WM."""
        return self._n_wm

    @property
    def n_places(self) -> int:
        """Places known (WM and LTM)."""
        return self._used.n

    @property
    def n_ltm(self) -> int:
        return self.n_places - self._n_wm

    @property
    def dense(self) -> bool:
        """True while WM holds every place (nothing ever left, or all came back)."""
        return self._n_wm == self.n_places

    def __contains__(self, place: int) -> bool:
        return 0 <= place < self.n_places and bool(self._in_wm.view[place])

    def ids(self) -> np.ndarray:
        """``(n,) int64``: the places in WM, sorted."""
        if self._wm_sorted is None:
            self._wm_sorted = np.flatnonzero(self._in_wm.view).astype(np.int64)
        return self._wm_sorted

    def weight(self, place: int) -> int:
        return int(self._weight.view[place])

    def memory_bytes(self) -> int:
        """Bytes of the stored words (a bounded memory's, all places: arrays with their
        headers, and their list) and the per-place arrays (their spare capacity included,
        and the sorted ids when they are kept)."""
        words = sum(sys.getsizeof(w) for w in self._words) + (sys.getsizeof(self._words) if self._words else 0)
        ids = self._wm_sorted.nbytes if self._wm_sorted is not None else 0
        return words + self._weight.nbytes + self._used.nbytes + self._in_wm.nbytes + ids

    # --- changes --------------------------------------------------------------------------
    def add(self, place: int, words: np.ndarray, now: int) -> None:
        """A new place (image ``place``) with its words joins WM and the index."""
        if place != self.n_places:
            raise ValueError(f"places are added in order: expected {self.n_places}, got {place}")
        w = np.asarray(words, np.int64)
        self.index.add_image(place, w)
        if self.params.bounded:  # without a bound nothing ever leaves: no copy of the words
            self._words.append(w.astype(np.int32))
        for a in (self._weight, self._used, self._in_wm):
            a.resize(place + 1)
        self._used.view[place] = now
        self._in_wm.view[place] = 1
        self._n_wm += 1
        self._wm_sorted = None

    def touch(self, places: np.ndarray | list[int], now: int) -> None:
        """Mark WM places as used at image ``now``."""
        self._used.view[np.asarray(places, np.int64)] = now

    def link(self, a: int, b: int) -> None:
        """A verified loop between places ``a`` and ``b``: both weigh one more and each
        becomes a retrieval neighbour of the other."""
        for x, y in ((a, b), (b, a)):
            self._weight.view[x] += 1
            self._links.setdefault(x, set()).add(y)

    def retrieve_around(self, place: int, now: int) -> list[int]:
        """Bring back up to ``max_retrieved`` LTM places near ``place`` (its loop links,
        then its neighbours in time, nearest first); returns them."""
        p = self.params
        if not p.max_retrieved or self.dense:
            return []
        want: list[int] = sorted(x for x in self._links.get(place, ()) if x not in self)
        for d in range(1, p.retrieve_radius + 1):
            for q in (place - d, place + d):
                if 0 <= q < self.n_places and q not in self:
                    want.append(q)
        out: list[int] = []
        for q in want:
            if len(out) == p.max_retrieved:
                break
            if q in self:
                continue
            self.index.add_image(q, self._words[q])
            self._in_wm.view[q] = 1
            self._n_wm += 1
            self._used.view[q] = now
            out.append(q)
        if out:
            self._wm_sorted = None
            self.retrieved += len(out)
        return out

    def enforce_bound(self, now: int, over_budget: float = 0.0) -> list[int]:
        """Move places to LTM until WM holds at most ``max_places``, and, when the image
        took ``over_budget`` times the time budget (> 1), that share of the places more;
        returns them (least recently used, then lowest weight, then oldest first; never the
        last ``protect_recent`` images nor a place used at ``now``)."""
        n_wm = self._n_wm
        cap = self.params.max_places if self.params.max_places is not None else n_wm
        if over_budget > 1.0:
            cap = min(cap, n_wm - math.ceil(n_wm * (1.0 - 1.0 / over_budget)))
        if n_wm <= cap:
            return []
        ids = self.ids()
        movable = ids[ids <= now - self.protect_recent]
        used = self._used.view[movable].astype(np.int64)
        movable, used = movable[used < now], used[used < now]
        weight = self._weight.view[movable].astype(np.int64)
        n_out = n_wm - cap  # fewer when not enough may move (a time budget)
        order = np.lexsort((movable, weight, used))[:n_out]
        out = sorted(movable[order].tolist())
        for q in out:
            self.index.remove_image(q, self._words[q])
            self._in_wm.view[q] = 0
            self._n_wm -= 1
        self._wm_sorted = None
        self.transferred += len(out)
        return out
