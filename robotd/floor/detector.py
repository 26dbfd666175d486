"""The floor loop detector as the daemon uses it: describe each keyframe, query the map.

Each new keyframe's floor image is described (compact descriptor, mode from the config),
the map index is queried for earlier keyframes that look alike, excluding those taken in
the last ``exclude_recent_s`` seconds (they overlap trivially), and the keyframe is added
to the index. Which candidates are loops is decided later from the trained
P(loop | score) thresholds (paper 003 Sec. III-B, IV-C).
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from robotd.floor.descriptor import decode, extract
from robotd.floor.index import Candidate, FloorIndex

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FloorDetectorParams:
    """``mode``: descriptor mode 1-6 (512 B .. 16 kB per image); ``candidates``: how many
    candidates a query returns; ``shortlist``: keyframes scored locally per query after the
    global shortlist; ``exclude_recent_s``: keyframes younger than this are not queried."""

    mode: int = 4
    candidates: int = 5
    shortlist: int = 30
    exclude_recent_s: float = 20.0


@dataclass(frozen=True, eq=False)
class KeyframeQuery:
    """What one keyframe's query found: its descriptor bytes and the candidates."""

    keyframe_id: int
    stamp_ns: int
    descriptor: bytes
    candidates: list[Candidate]


class FloorLoopDetector:
    """Describes keyframes and finds earlier look-alikes through a :class:`FloorIndex`."""

    def __init__(self, params: FloorDetectorParams, index: FloorIndex | None = None,
                 stamps: list[tuple[int, int]] | None = None) -> None:
        self.params = params
        self.index = index if index is not None else FloorIndex()
        # (stamp_ns, keyframe_id) in time order, for the recent-keyframe exclusion.
        self._stamps: list[tuple[int, int]] = sorted(stamps or [])

    @classmethod
    def from_store(cls, store: Any, params: FloorDetectorParams) -> "FloorLoopDetector":
        """Rebuild the index from a map's stored descriptors of the same mode (a restart
        continues the same map). Descriptors that do not decode are skipped and counted."""
        index = FloorIndex.from_store(store, params.mode)
        stamps = [(k.stamp_ns, k.id) for k in store.keyframes()
                  if k.descriptor is not None and k.descriptor_mode == params.mode]
        if len(index):
            log.info("floor index: %d keyframes loaded from the map", len(index))
        return cls(params, index, stamps)

    def describe(self, image: np.ndarray) -> bytes:
        """The keyframe's compact descriptor (at most the mode's byte budget)."""
        return extract(image, self.params.mode)

    def query_and_add(self, keyframe_id: int, stamp_ns: int, descriptor: bytes) -> KeyframeQuery:
        """Query the map with a stored keyframe's descriptor, then add it to the index."""
        desc = decode(descriptor)
        cutoff = stamp_ns - int(self.params.exclude_recent_s * 1e9)
        # Keyframe ids grow with time: everything after the last keyframe older than the
        # cutoff is recent and excluded.
        i = bisect.bisect_left(self._stamps, (cutoff, -1))
        candidates: list[Candidate] = []
        if i > 0:
            last_old_id = self._stamps[i - 1][1]
            candidates = self.index.query(desc, k=self.params.candidates,
                                          exclude_after_id=last_old_id,
                                          shortlist=self.params.shortlist)
        self.index.add(keyframe_id, desc)
        self._stamps.append((stamp_ns, keyframe_id))
        return KeyframeQuery(keyframe_id, stamp_ns, descriptor, candidates)
