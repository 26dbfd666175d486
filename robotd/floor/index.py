"""The map index: find earlier keyframes that look like a new one without scoring them all.

Paper 003 (Sec. V, Table V) matches the last of 7154 images against every earlier one with
the local score and reports 4 to 58 s per query; DESIGN.md ("Floor loop detector") asks for
a query that does not compare against every keyframe. A query here runs in two stages,
as in CDVS retrieval (paper 003 Sec. II-B: a global score, then a local score):

1. **Global shortlist.** Every keyframe's global descriptor (a packed binary vector) sits
   in one contiguous ``(words, capacity) uint64`` array that grows by doubling. The query's
   global descriptor is compared with all of them at once: XOR and popcount
   (``numpy.bitwise_count``), a similarity ``1 - hamming / bits`` in [0, 1]. This is
   linear in the map but costs well under a microsecond per keyframe. The ``shortlist``
   most similar keyframes that are not excluded go on.
2. **Local scoring** of the shortlist only: :func:`robotd.floor.match.local_score` (matches
   that survive the geometric consistency test), and the best ``k`` by local score are
   returned as :class:`Candidate`\\ s, each with its match result (inlier correspondences
   for the loop transform, and the reason a low-scoring one was dismissed).

The cost of a query is therefore ``shortlist`` local matches plus a vectorised scan, so it
grows far slower than the map (``bench/bench_floor_map.py`` measures it). Memory: the
global array plus the decoded descriptors (:attr:`FloorIndex.nbytes`), packed into shared
arrays (:class:`_PackedDescriptors`: about 21 bytes per keypoint in mode 4, no Python
object per keyframe) and rebuilt for the few keyframes a query scores.

The index holds descriptors of one mode: the first descriptor added fixes the global
descriptor's length, and a descriptor of another length is refused (ValueError).
"""

from __future__ import annotations

import collections
import logging
import math
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from robotd.base.errors import DescriptorError, RobotdError
from robotd.floor.descriptor import ANGLE_BITS, FloorDescriptor, PartialDescriptor, decode, decode_local
from robotd.floor.match import Matcher, MatchResult, local_score

__all__ = ["Candidate", "FloorIndex", "IndexParams", "LoadReport"]

log = logging.getLogger(__name__)

LocalScorer = Callable[[FloorDescriptor, FloorDescriptor], MatchResult]
"""``scorer(query, stored) -> MatchResult``: how a shortlisted keyframe is scored locally."""

Loader = Callable[[int], FloorDescriptor | PartialDescriptor]
"""``loader(keyframe_id)``: a descriptor kept out of RAM, read back (:class:`FloorIndex`)."""


@dataclass(frozen=True)
class IndexParams:
    """Parameters of :class:`FloorIndex`.

    Fields:
        k: candidates a query returns by default (the best by local score).
        shortlist: keyframes a query scores locally by default, taken in order of global
            similarity; the cost of a query is about ``shortlist`` local matches. 30 keeps
            the true overlapping keyframes of the office route among the candidates
            (``bench/bench_floor_map.py``) at well under 1 % of brute-force cost on a
            7154-keyframe map.
        initial_capacity: rows of the global-descriptor array before its first doubling.
        match_params: passed to :func:`robotd.floor.match.local_score` as ``params``
            (None: the matcher's defaults).
        resident: with a ``loader`` (:class:`FloorIndex`), how many decoded descriptors
            stay in RAM, the most recently used (the newest keyframes and the last
            shortlists'); the others are read again through the loader when a shortlist
            names them. Without a loader every descriptor stays in RAM.
        enough: with a ``min_score`` (:meth:`FloorIndex.query`), a query stops scoring its
            shortlist once ``k`` candidates have reached it: the loop detector declares a
            loop for every candidate at or above its threshold, so the query then returns
            ``k`` loops either way, the first ``k`` in order of global similarity instead of
            the best ``k`` by local score, and the rest of the shortlist is not matched. On
            ground driven many times most of the shortlist are true matches, each verified
            geometrically (the costly case): stopping there keeps the query's time near
            that of a first pass. False: every shortlisted keyframe is scored.
        resident_first: with a ``loader`` and ``enough`` stopping a query, the shortlisted
            keyframes whose descriptors are resident are scored first (each group in order
            of global similarity), so that a query that finds its ``k`` loops among them
            reads nothing back: over ground driven lap after lap the previous pass is
            resident, the older passes are not. The shortlist is the same, and so is every
            score; which ``k`` of the shortlist's loops are returned may differ (the previous
            pass's rather than the globally most similar). On the three office laps
            (``bench_daemon.py --residency``, 1,024 resident) the same 500 loops with no
            read per query instead of 2.4; measured on that one map only, so off by default
            (False: the shortlist in order of global similarity, as without a loader).
    """

    k: int = 5
    shortlist: int = 30
    initial_capacity: int = 256
    match_params: Any = None
    resident: int = 1024
    enough: bool = True
    resident_first: bool = False

    def __post_init__(self) -> None:
        if self.k < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        if self.shortlist < 1:
            raise ValueError(f"shortlist must be >= 1, got {self.shortlist}")
        if self.initial_capacity < 1:
            raise ValueError(f"initial_capacity must be >= 1, got {self.initial_capacity}")
        if self.resident < 1:
            raise ValueError(f"resident must be >= 1, got {self.resident}")


@dataclass(frozen=True, eq=False)
class Candidate:
    """An earlier keyframe that may show the same floor as the query.

    ``global_score``: global similarity in [0, 1] (``1 - hamming / bits``); ``local``: the
    local match of the query (side ``a``) against this keyframe (side ``b``):
    ``local.score``, the inlier correspondences (``xy_a`` in the query image, ``xy_b`` in
    the keyframe's) and ``local.reason`` when it was dismissed.
    """

    keyframe_id: int
    global_score: float
    local: MatchResult

    @property
    def score(self) -> float:
        """The local score, which orders the candidates."""
        return float(self.local.score)


@dataclass(frozen=True)
class LoadReport:
    """What :meth:`FloorIndex.from_store` did: keyframes indexed, ids skipped because their
    descriptor did not decode (or did not fit the index), and keyframes without a
    descriptor of the wanted mode (not an error: other modes, or not yet described)."""

    loaded: int
    corrupt_ids: tuple[int, ...]
    other_mode: int


def _global_bytes(descriptor: FloorDescriptor | PartialDescriptor) -> np.ndarray:
    """The packed global descriptor as ``(B,) uint8`` (bool arrays are packed first)."""
    bits = np.asarray(descriptor.global_bits)
    if bits.dtype == np.bool_:
        bits = np.packbits(bits.ravel())
    return np.ascontiguousarray(bits).view(np.uint8).ravel()


def _descriptor_nbytes(descriptor: FloorDescriptor | PartialDescriptor) -> int:
    """Bytes held by a decoded descriptor's arrays (and byte strings)."""
    if isinstance(descriptor, PartialDescriptor):
        return descriptor.nbytes
    total = 0
    for f in fields(descriptor):
        value = getattr(descriptor, f.name)
        if isinstance(value, np.ndarray):
            total += value.nbytes
        elif isinstance(value, (bytes, bytearray)):
            total += len(value)
    return total


_BATCH = 8
"""Most shortlisted keyframes a query scores in one :meth:`~robotd.floor.match.Matcher.score_many`
(its temporaries grow with the pairs: about 0.3 MB each in mode 4)."""

_ON_DEMAND = np.iinfo(np.int64).min
"""``FloorIndex._slot`` of a keyframe whose descriptor is read through the loader."""

_EXCLUDED = np.iinfo(np.int64).max
"""The shortlist's rank key of an excluded row (:meth:`FloorIndex._ranked`): after every other."""

_ANGLE_STEP = 2 * math.pi / 2**ANGLE_BITS
_ANGLES = (np.arange(2**ANGLE_BITS) * _ANGLE_STEP).astype(np.float32)  # code -> radians, as decode gives them


class _PackedDescriptors:
    """Decoded descriptors of one mode kept in a few shared arrays, not one object each.

    Keypoints sit in chunks of at least ``CHUNK`` rows (a keyframe never straddles two),
    so growing copies nothing and wastes under one chunk: bit planes as decoded, positions
    as float16 and orientations as their ``ANGLE_BITS``-bit code while every descriptor
    added is exactly so representable (a 640 x 480 image's grid positions are, to 1024 px;
    otherwise float32 for all), and per keyframe its chunk, first row, keypoint count and
    header fields. :meth:`get` rebuilds a :class:`FloorDescriptor` equal, array for array,
    to the one added: 21 bytes per keypoint in mode 4 against 28, and no Python objects
    per keyframe.
    """

    CHUNK = 1 << 16

    def __init__(self) -> None:
        self.words = -1  # uint64 words per bit plane, fixed by the first descriptor
        self.xy_dtype: type = np.float16
        self.angle_coded = True
        self.chunks: list[dict[str, np.ndarray]] = []
        self.used = 0  # rows used in the last chunk
        self.where = np.zeros((0, 3), np.int64)  # per keyframe: chunk, first row, count
        self.head = np.zeros((0, 4), np.int64)  # per keyframe: mode, width, height, length
        self.step = np.zeros(0, np.float64)  # per keyframe: position_step_px
        self.gbytes = np.zeros((0, 0), np.uint8)  # per keyframe: packed global bits
        self.n = 0

    def fits(self, d: FloorDescriptor) -> bool:
        """Whether ``d`` can be packed (a decoded descriptor of this store's plane width)."""
        return (isinstance(d, FloorDescriptor) and d.local_pos.ndim == 2 and d.local_pos.dtype == np.uint64
                and d.local_neg.shape == d.local_pos.shape and d.local_neg.dtype == np.uint64
                and self.words in (-1, d.local_pos.shape[1]) and np.asarray(d.global_bits).dtype == np.uint8
                and (self.n == 0 or np.asarray(d.global_bits).size == self.gbytes.shape[1]))

    def _chunk(self, words: int, rows: int) -> dict[str, np.ndarray]:
        return {"pos": np.zeros((rows, words), np.uint64), "neg": np.zeros((rows, words), np.uint64),
                "xy": np.zeros((rows, 2), self.xy_dtype),
                "angle": np.zeros(rows, np.uint8 if self.angle_coded else np.float32)}

    def _widen(self, xy: bool, angle: bool) -> None:
        """Positions to float32, resp. orientations to radians, for every chunk."""
        if xy:
            self.xy_dtype = np.float32
        for c in self.chunks:
            if xy:
                c["xy"] = c["xy"].astype(np.float32)
            if angle:
                c["angle"] = (c["angle"] * _ANGLE_STEP).astype(np.float32)
        if angle:
            self.angle_coded = False

    def add(self, d: FloorDescriptor) -> int:
        """Pack ``d`` (:meth:`fits` must hold); returns its row."""
        k, words = len(d.xy_px), d.local_pos.shape[1]
        self.words = words
        xy = np.asarray(d.xy_px, np.float32)
        angle = np.asarray(d.angle_rad, np.float32)
        code = np.rint(angle / np.float32(_ANGLE_STEP)).astype(np.int64)
        widen_xy = self.xy_dtype == np.float16 and not np.array_equal(xy.astype(np.float16).astype(np.float32), xy)
        widen_angle = self.angle_coded and not (
            np.all((code >= 0) & (code < 2**ANGLE_BITS))
            and np.array_equal((code * _ANGLE_STEP).astype(np.float32), angle))
        if widen_xy or widen_angle:
            self._widen(widen_xy, widen_angle)
        if not self.chunks or self.used + k > len(self.chunks[-1]["pos"]):
            self.chunks.append(self._chunk(words, max(self.CHUNK, k)))
            self.used = 0
        c, r = self.chunks[-1], self.used
        c["pos"][r:r + k] = d.local_pos
        c["neg"][r:r + k] = d.local_neg
        c["xy"][r:r + k] = xy
        c["angle"][r:r + k] = code if self.angle_coded else angle
        self.used += k
        g = np.asarray(d.global_bits).ravel()
        if self.n == len(self.where):
            cap = max(256, 2 * self.n)
            self.where = np.resize(self.where, (cap, 3))
            self.head = np.resize(self.head, (cap, 4))
            self.step = np.resize(self.step, cap)
            self.gbytes = np.resize(self.gbytes, (cap, g.size))
        row = self.n
        self.where[row] = (len(self.chunks) - 1, r, k)
        self.head[row] = (d.mode, d.width_px, d.height_px, d.length)
        self.step[row] = d.position_step_px
        self.gbytes[row] = g
        self.n += 1
        return row

    def get(self, row: int) -> FloorDescriptor:
        """The descriptor of ``row``, rebuilt (its bit planes are read-only views of the
        shared arrays; a query rebuilds only the keyframes it scores)."""
        ci, r, k = self.where[row].tolist()
        c = self.chunks[ci]
        pos, neg = c["pos"][r:r + k], c["neg"][r:r + k]
        pos.flags.writeable = neg.flags.writeable = False
        xy = c["xy"][r:r + k].astype(np.float32)
        a = c["angle"][r:r + k]
        angle = _ANGLES[a] if self.angle_coded else a.copy()
        mode, width, height, length = self.head[row].tolist()
        return FloorDescriptor(mode, width, height, xy, angle, pos, neg, length, self.gbytes[row].copy(),
                               float(self.step[row]))

    @property
    def nbytes(self) -> int:
        """Bytes of every array held (chunks whole)."""
        return int(sum(a.nbytes for c in self.chunks for a in c.values()) + self.where.nbytes + self.head.nbytes
                   + self.step.nbytes + self.gbytes.nbytes)


class FloorIndex:
    """Keyframe descriptors of one mode, queried by global shortlist then local score.

    ``scorer`` replaces the local matcher (default :func:`robotd.floor.match.local_score`
    with ``params.match_params``); :attr:`local_matches` counts every local match the
    index has made, so the cost of queries can be checked.

    ``loader(keyframe_id)`` (the map's stored descriptor, decoded, or decoded in two steps:
    a :class:`~robotd.floor.descriptor.PartialDescriptor`, whose positions the local score
    decodes only for a pair that passes its ``min_score`` bound) keeps
    the local descriptors out of RAM: the index then holds the global descriptors (all a
    shortlist needs) and the ``params.resident`` most recently used decoded descriptors,
    and reads a shortlisted keyframe's through the loader when it is not among them
    (:attr:`loads` counts those reads). A keyframe whose descriptor cannot be read then
    (the loader raises a :class:`RobotdError`, KeyError or ValueError) is left out of that
    query's candidates, logged and counted (:attr:`load_failures`). The candidates are the
    same as with every descriptor in RAM: the loader gives back what was added.
    """

    def __init__(self, params: IndexParams | None = None, scorer: LocalScorer | None = None,
                 loader: Loader | None = None) -> None:
        self.params = params if params is not None else IndexParams()
        if scorer is None:
            match_params = self.params.match_params

            def scorer(a: FloorDescriptor, b: FloorDescriptor) -> MatchResult:
                return local_score(a, b, match_params)

            self._default_scorer = True
        else:
            self._default_scorer = False
        self._scorer: LocalScorer = scorer
        self._words = 0  # uint64 words per global descriptor, fixed by the first add
        self._bits = 0  # global descriptor length, bits
        # (words, capacity): word w of every keyframe's global descriptor in one row, so that
        # the scan's popcounts are summed across rows (whole-row adds, not a short axis).
        self._global = np.zeros((0, 0), np.uint64)
        self._ids = np.zeros(0, np.int64)  # (capacity,)
        # row -> packed row (>= 0), or -1 - i for the i-th descriptor kept as it is
        # (stand-ins and descriptors the packed store does not take).
        self._slot = np.zeros(0, np.int64)
        self._packed = _PackedDescriptors()
        self._objects: list[Any] = []
        self._n = 0
        self._row_of: dict[int, int] = {}
        self._ids_increasing = True  # every id added larger than the one before (rows found by bisection)
        self._local_nbytes = 0  # of the descriptors kept as they are
        self._loader = loader
        # keyframe id -> (decoded descriptor, its bytes), least recently used first
        self._recent: collections.OrderedDict[int, tuple[FloorDescriptor | PartialDescriptor, int]] = \
            collections.OrderedDict()
        self._recent_nbytes = 0  # of the descriptors in _recent
        self.loads = 0
        self.load_failures = 0
        self.local_matches = 0
        self.load_report: LoadReport | None = None

    # ------------------------------------------------------------------ building

    def __len__(self) -> int:
        return self._n

    def __contains__(self, keyframe_id: object) -> bool:
        return keyframe_id in self._row_of

    @property
    def ids(self) -> np.ndarray:
        """Keyframe ids in the order they were added, ``(N,) int64`` (a copy)."""
        return self._ids[: len(self)].copy()

    @property
    def capacity(self) -> int:
        """Rows allocated in the global-descriptor array (doubles when full)."""
        return int(self._global.shape[1])

    @property
    def nbytes(self) -> int:
        """Memory held by the index: the global array (whole capacity), the id array and
        the decoded descriptors' arrays (packed: :class:`_PackedDescriptors`, whole
        chunks; with a loader, the resident ones'). Python object overhead is not counted."""
        return int(self._global.nbytes + self._ids.nbytes + self._slot.nbytes + self.descriptors_nbytes)

    @property
    def descriptors_nbytes(self) -> int:
        """The part of :attr:`nbytes` held by the decoded descriptors (local features)."""
        return int(self._packed.nbytes + self._local_nbytes + self._recent_nbytes)

    @property
    def on_demand(self) -> bool:
        """Whether the local descriptors are read through a loader (see the class)."""
        return self._loader is not None

    def add(self, keyframe_id: int, descriptor: FloorDescriptor | PartialDescriptor) -> None:
        """Index a keyframe's decoded descriptor (or one decoded in two steps, a
        :class:`~robotd.floor.descriptor.PartialDescriptor`, kept as it is).

        Raises ValueError if ``keyframe_id`` is already indexed or the global descriptor's
        length differs from the first one added (another mode).
        """
        keyframe_id = int(keyframe_id)
        if keyframe_id in self._row_of:
            raise ValueError(f"keyframe {keyframe_id} is already in the index")
        g = _global_bytes(descriptor)
        if not self._n and self._words == 0:
            self._bits = 8 * g.size
            self._words = max(1, -(-g.size // 8))
            cap = self.params.initial_capacity
            self._global = np.zeros((self._words, cap), np.uint64)
            self._ids = np.zeros(cap, np.int64)
            self._slot = np.zeros(cap, np.int64)
        elif 8 * g.size != self._bits:
            raise ValueError(
                f"keyframe {keyframe_id}: global descriptor of {8 * g.size} bits, the index holds"
                f" {self._bits}-bit descriptors (one mode per index)"
            )
        row = self._n
        if row == self._global.shape[1]:
            self._grow()
        padded = np.zeros(8 * self._words, np.uint8)
        padded[: g.size] = g
        self._global[:, row] = padded.view(np.uint64)
        if row and keyframe_id < self._ids[row - 1]:
            self._ids_increasing = False
        self._ids[row] = keyframe_id
        if self._loader is not None:
            self._slot[row] = _ON_DEMAND
            self._remember(keyframe_id, descriptor)
        elif isinstance(descriptor, FloorDescriptor) and self._packed.fits(descriptor):
            self._slot[row] = self._packed.add(descriptor)
        else:
            self._slot[row] = -1 - len(self._objects)
            self._objects.append(descriptor)
            self._local_nbytes += _descriptor_nbytes(descriptor)
        self._row_of[keyframe_id] = row
        self._n += 1

    def _stored(self, row: int) -> Any:
        slot = int(self._slot[row])
        if slot == _ON_DEMAND:
            return self._on_demand(int(self._ids[row]))
        return self._packed.get(slot) if slot >= 0 else self._objects[-1 - slot]

    def _remember(self, keyframe_id: int, descriptor: FloorDescriptor | PartialDescriptor) -> None:
        """Keep ``descriptor`` among the resident ones, the least recently used let go."""
        nbytes = _descriptor_nbytes(descriptor)
        self._recent[keyframe_id] = (descriptor, nbytes)
        self._recent_nbytes += nbytes
        while len(self._recent) > self.params.resident:
            _kf, (_old, old_nbytes) = self._recent.popitem(last=False)
            self._recent_nbytes -= old_nbytes

    def _on_demand(self, keyframe_id: int) -> FloorDescriptor | PartialDescriptor:
        """A descriptor kept out of RAM: the resident copy, else the loader's (then kept)."""
        kept = self._recent.get(keyframe_id)
        if kept is not None:
            self._recent.move_to_end(keyframe_id)
            return kept[0]
        assert self._loader is not None
        d = self._loader(keyframe_id)
        self.loads += 1
        self._remember(keyframe_id, d)
        return d

    def _resize(self, keyframe_id: int, descriptor: PartialDescriptor) -> None:
        """Count a resident read-back descriptor's bytes again (its positions may have been
        decoded since)."""
        kept = self._recent.get(keyframe_id)
        if kept is not None and kept[0] is descriptor and kept[1] != descriptor.nbytes:
            nbytes = descriptor.nbytes
            self._recent_nbytes += nbytes - kept[1]
            self._recent[keyframe_id] = (descriptor, nbytes)

    def _grow(self) -> None:
        cap = 2 * self._global.shape[1]
        bigger = np.zeros((self._words, cap), np.uint64)
        bigger[:, : self._global.shape[1]] = self._global
        ids = np.zeros(cap, np.int64)
        ids[: self._ids.shape[0]] = self._ids
        slot = np.zeros(cap, np.int64)
        slot[: self._slot.shape[0]] = self._slot
        self._global, self._ids, self._slot = bigger, ids, slot

    @classmethod
    def from_store(cls, store: Any, mode: int, params: IndexParams | None = None,
                   scorer: LocalScorer | None = None, on_demand: bool = True) -> FloorIndex:
        """Rebuild the index from the descriptors of ``mode`` stored in a
        :class:`~robotd.io.store.MapStore`, in keyframe-id order.

        ``on_demand`` (default): the local descriptors stay in the map and are read back
        (``store.keyframe_descriptor(id)``, decoded in two steps:
        :func:`~robotd.floor.descriptor.decode_local`, the positions only for a pair that
        passes the local score's bound) when a shortlist names one that is not resident
        (the class's ``loader``); the store must then stay open as long as the index is
        queried, and every keyframe added later must be in the store by then. Otherwise
        every descriptor is kept in RAM.

        With ``on_demand`` the load itself decodes each stored descriptor in the same two
        steps (:func:`~robotd.floor.descriptor.decode_local`): the index needs only the
        global bits of most of them, and the ``params.resident`` newest stay resident as
        the query reads them back, their positions decoded the first time a pair passes
        the local score's bound. The candidates and scores are those of the whole decode.

        A stored descriptor that does not decode (or whose global descriptor does not fit
        the index) is skipped, logged with its keyframe id and counted in
        :attr:`load_report`; it never stops the load. With ``on_demand`` the positions'
        code is not decoded at load: a position code forged with a valid checksum is found
        by the query that reads it (left out, logged and counted as the class says).
        """

        def load(keyframe_id: int) -> PartialDescriptor:
            blob, blob_mode = store.keyframe_descriptor(keyframe_id)
            if blob is None or blob_mode != mode:
                raise KeyError(f"keyframe {keyframe_id} has no mode-{mode} descriptor in the map")
            return decode_local(blob)

        index = cls(params, scorer, load if on_demand else None)
        corrupt: list[int] = []
        other = 0
        for rec in store.keyframes():
            if rec.descriptor is None or rec.descriptor_mode != mode:
                other += 1
                continue
            try:
                index.add(rec.id, decode_local(rec.descriptor) if on_demand else decode(rec.descriptor))
            except (DescriptorError, ValueError) as exc:
                log.warning("floor index: keyframe %d skipped, its descriptor is unusable: %s", rec.id, exc)
                corrupt.append(int(rec.id))
        index.load_report = LoadReport(len(index), tuple(corrupt), other)
        if corrupt:
            log.warning("floor index: %d of %d stored mode-%d descriptors skipped",
                        len(corrupt), len(corrupt) + len(index), mode)
        return index

    # ------------------------------------------------------------------ querying

    def global_scores(self, descriptor: FloorDescriptor) -> np.ndarray:
        """Global similarity of ``descriptor`` to every indexed keyframe, ``(N,) float64``
        in [0, 1], in the order of :attr:`ids`: ``1 - hamming / bits``."""
        return np.asarray(1.0 - self._hamming(descriptor) / float(self._bits)) if len(self) else np.zeros(0)

    def _hamming(self, descriptor: FloorDescriptor) -> np.ndarray:
        """Hamming distance of ``descriptor``'s global bits to every indexed keyframe's,
        ``(N,)`` integers (uint16, or int64 for descriptors of 65,536 bits or more) in the
        order of :attr:`ids` (the index must not be empty)."""
        g = _global_bytes(descriptor)
        if 8 * g.size != self._bits:
            raise ValueError(f"query global descriptor has {8 * g.size} bits, the index holds {self._bits}")
        padded = np.zeros(8 * self._words, np.uint8)
        padded[: g.size] = g
        q = padded.view(np.uint64)
        return np.bitwise_count(np.bitwise_xor(self._global[:, : len(self)], q[:, None])).sum(
            axis=0, dtype=np.uint16 if self._bits < 1 << 16 else np.int64)

    def shortlist(self, descriptor: FloorDescriptor, size: int | None = None,
                  exclude_ids: Callable[[int], bool] | Collection[int] | None = None,
                  exclude_after_id: int | None = None) -> list[tuple[int, float]]:
        """The ``size`` keyframes most similar by global score that are not excluded, as
        ``(keyframe_id, global_score)``, best first (ties: earlier keyframe first).

        ``exclude_ids``: ids to leave out, as a collection or a predicate ``f(id) -> True``
        to exclude; ``exclude_after_id``: leave out every keyframe with a larger id (the
        most recent ones, which overlap the query trivially).
        """
        size = self.params.shortlist if size is None else int(size)
        n = len(self)
        if n == 0 or size < 1:
            return []
        # Ranked by Hamming distance, the global score's order (1 - hamming / bits).
        dist = self._hamming(descriptor)
        if not callable(exclude_ids):
            return self._ranked(dist, size, exclude_ids, exclude_after_id)
        predicate: Callable[[int], bool] = exclude_ids
        bits = float(self._bits)
        ids = self._ids[:n]
        valid: np.ndarray | None = None
        if exclude_after_id is not None:
            valid = ids <= int(exclude_after_id)
        rows = np.arange(n) if valid is None else np.flatnonzero(valid)
        if rows.size == 0:
            return []
        d = dist if valid is None else dist[rows]
        # Best first; ties broken by row (= insertion order) through the stable sort.
        # Only the top of the list is sorted unless the predicate rejects many of it.
        want = 2 * size
        if rows.size > want:
            top = np.argpartition(d, want - 1)[:want]
            top = np.flatnonzero(d <= d[top].max())  # keep every tie at the cut
            ordered = rows[top[np.argsort(d[top], kind="stable")]]
        else:
            ordered = rows[np.argsort(d, kind="stable")]
        out: list[tuple[int, float]] = []
        for row in ordered:
            kf = int(ids[row])
            if predicate(kf):
                continue
            out.append((kf, float(1.0 - dist[row] / bits)))
            if len(out) == size:
                return out
        if len(ordered) < rows.size:
            # The predicate rejected too many of the top rows: walk the rest in order.
            seen = set(ordered.tolist())
            rest = [r for r in rows[np.argsort(d, kind="stable")] if int(r) not in seen]
            for row in rest:
                kf = int(ids[row])
                if predicate(kf):
                    continue
                out.append((kf, float(1.0 - dist[row] / bits)))
                if len(out) == size:
                    break
        return out

    def _ranked(self, dist: np.ndarray, size: int, exclude_ids: Collection[int] | None,
                exclude_after_id: int | None) -> list[tuple[int, float]]:
        """:meth:`shortlist` without a predicate: the ``size`` smallest of one int64 key per
        row, the distance above the row (unique, so that one partition finds them, ties in
        row order), excluded rows keyed above every other."""
        n = len(dist)
        ids = self._ids[:n]
        key = dist.astype(np.int64)
        key <<= 32
        key |= np.arange(n, dtype=np.int64)
        if exclude_after_id is not None:
            if self._ids_increasing:
                key[int(np.searchsorted(ids, int(exclude_after_id), side="right")):] = _EXCLUDED
            else:
                key[ids > int(exclude_after_id)] = _EXCLUDED
        if exclude_ids is not None:
            if isinstance(exclude_ids, np.ndarray):  # no Python loop over a large array of ids
                excluded = exclude_ids.ravel().astype(np.int64, copy=False)
            else:
                excluded = np.fromiter((int(i) for i in exclude_ids), np.int64)
            if self._ids_increasing:
                at = np.searchsorted(ids, excluded)
                inside = at < n
                at = at[inside]
                key[at[ids[at] == excluded[inside]]] = _EXCLUDED
            else:
                key[np.isin(ids, excluded)] = _EXCLUDED
        top = np.argpartition(key, size - 1)[:size] if n > size else np.arange(n)
        top = top[np.argsort(key[top])]
        bits = float(self._bits)
        return [(int(ids[r]), 1.0 - int(dist[r]) / bits) for r in top.tolist() if key[r] != _EXCLUDED]

    def query(self, descriptor: FloorDescriptor, k: int | None = None,
              exclude_ids: Callable[[int], bool] | Collection[int] | None = None,
              exclude_after_id: int | None = None, shortlist: int | None = None,
              min_score: float = 0.0, match_params: Any = None) -> list[Candidate]:
        """The best ``k`` earlier keyframes for ``descriptor``, by local score (best first;
        ties by global score, then by id).

        Only the ``shortlist`` keyframes of :meth:`shortlist` are scored locally; defaults
        come from :attr:`params`. Exclusions as in :meth:`shortlist`. ``min_score`` (the
        default matcher only): shortlisted keyframes that provably cannot reach it are not
        checked geometrically and come back with score 0 and reason ``BELOW_MIN_SCORE``
        (:func:`robotd.floor.match.local_score`); a candidate at or above it is scored
        exactly as without it. The query's own side of the descriptor distance is prepared
        once for the whole shortlist (:class:`robotd.floor.match.Matcher`). With
        ``params.enough`` and a ``min_score``, the shortlist is scored in order of global
        similarity (with ``params.resident_first`` the resident descriptors first) only until
        ``k`` candidates reach ``min_score`` (:class:`IndexParams`). ``match_params`` (the
        default matcher only): the local scores' parameters for this query (None:
        ``params.match_params``).
        """
        k = self.params.k if k is None else int(k)
        short = self.shortlist(descriptor, shortlist, exclude_ids, exclude_after_id)
        candidates = []
        matcher = (Matcher(descriptor, self.params.match_params if match_params is None else match_params)
                   if self._default_scorer and short else None)
        stop_at = k if self.params.enough and min_score > 0 else None
        if stop_at is not None and self._loader is not None and self.params.resident_first:
            recent = self._recent  # resident first: a query that finds enough there reads nothing
            short = [c for c in short if c[0] in recent] + [c for c in short if c[0] not in recent]
        reached = 0
        pos = 0
        while pos < len(short) and (stop_at is None or reached < stop_at):
            # The next pairs in turn, scored together (Matcher.score_many: the same results
            # as one by one): as many as could all be scored before the query stops (each
            # pair adds at most one to ``reached``), at most _BATCH.
            take = min(_BATCH, len(short) - pos) if stop_at is None else min(_BATCH, stop_at - reached)
            chunk, pos = short[pos: pos + take], pos + take
            loaded = []
            for kf, g in chunk:
                try:
                    loaded.append((kf, g, self._stored(self._row_of[kf])))
                except (RobotdError, KeyError, ValueError) as exc:
                    if self._loader is None:
                        raise
                    self._left_out(kf, exc)
            results: list[MatchResult | DescriptorError]
            if matcher is not None:
                results = matcher.score_many([stored for _kf, _g, stored in loaded], min_score)
            else:
                results = []
                for _kf, _g, stored in loaded:
                    try:
                        results.append(self._scorer(descriptor, stored.full() if isinstance(stored, PartialDescriptor)
                                                    else stored))
                    except DescriptorError as exc:
                        results.append(exc)
            for (kf, g, stored), result in zip(loaded, results):
                if isinstance(result, DescriptorError):  # a read-back descriptor's positions (decoded last)
                    if not isinstance(stored, PartialDescriptor):
                        raise result
                    self._left_out(kf, result)
                    continue
                if isinstance(stored, PartialDescriptor):
                    self._resize(kf, stored)
                self.local_matches += 1
                candidates.append(Candidate(kf, g, result))
                if result.score >= min_score:
                    reached += 1
        candidates.sort(key=lambda c: (-c.score, -c.global_score, c.keyframe_id))
        return candidates[:k]

    def _left_out(self, kf: int, exc: Exception) -> None:
        """A keyframe whose stored descriptor could not be read, left out of a query: counted, logged."""
        self.load_failures += 1
        log.warning("floor index: keyframe %d left out of a query, its descriptor could not be read: %s", kf, exc)

    def brute_force(self, descriptor: FloorDescriptor, k: int | None = None,
                    exclude_ids: Callable[[int], bool] | Collection[int] | None = None,
                    exclude_after_id: int | None = None) -> list[Candidate]:
        """Like :meth:`query` but scoring every non-excluded keyframe locally (paper 003
        Table V's brute force); the reference the shortlist is measured against."""
        return self.query(descriptor, k, exclude_ids, exclude_after_id, shortlist=max(len(self), 1))

    def descriptor(self, keyframe_id: int) -> FloorDescriptor:
        """The indexed descriptor of a keyframe; KeyError if it is not indexed."""
        d = self._stored(self._row_of[int(keyframe_id)])
        if isinstance(d, PartialDescriptor):
            full = d.full()
            self._resize(int(keyframe_id), d)
            return full
        return d

    def extend(self, items: Iterable[tuple[int, FloorDescriptor]]) -> None:
        """:meth:`add` each ``(keyframe_id, descriptor)``."""
        for kf, desc in items:
            self.add(kf, desc)
