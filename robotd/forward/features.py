"""Local features of a forward-camera image: SIFT by default (paper 000 Sec. III), ORB for
small CPUs.

SIFT descriptors are scaled to unit Euclidean length (OpenCV returns them with a norm of
about 512), so the vocabulary's word radius is a plain number independent of OpenCV's
scaling: two views of one scene point are typically 0.2-0.35 apart, unrelated points 0.5
or more. ORB descriptors stay packed 256-bit strings compared by Hamming distance.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal, Protocol

import cv2
import numpy as np

__all__ = ["CompactFeatures", "FeatureExtractor", "FeatureParams", "Features", "LentFeatures", "compact", "extract_features",
           "lend", "without_words", "to_gray"]

FeatureKind = Literal["sift", "orb"]


@dataclass(frozen=True)
class FeatureParams:
    """How features are extracted.

    Fields:
        kind: ``"sift"`` (128 float32 per keypoint, L2 distance; the paper's choice) or
            ``"orb"`` (256 bits packed in 32 uint8, Hamming distance; about 4x faster).
        max_features: keep at most this many keypoints per image, the strongest
            (0 = no limit for SIFT; ORB always needs a cap and uses 1000 then).
        sift_contrast_threshold: OpenCV's SIFT ``contrastThreshold`` (default 0.04); lower
            finds more keypoints on bare corridor walls.
        orb_levels, orb_scale_factor, orb_fast_threshold: OpenCV's ORB ``nlevels``,
            ``scaleFactor`` and ``fastThreshold`` (its defaults 8, 1.2, 20): fewer or
            coarser pyramid levels take less time, and lost recall on the real corridor
            (docs/forward.md, "Time and memory").
        image_scale: the image is resized by this factor (area interpolation) before
            detection, and the keypoints scaled back to the full image's pixels (1.0: as
            it is).
    """

    kind: FeatureKind = "sift"
    max_features: int = 0
    sift_contrast_threshold: float = 0.04
    orb_levels: int = 8
    orb_scale_factor: float = 1.2
    orb_fast_threshold: int = 20
    image_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("sift", "orb"):
            raise ValueError(f"feature kind must be 'sift' or 'orb', got {self.kind!r}")
        if self.max_features < 0:
            raise ValueError(f"max_features must be >= 0, got {self.max_features}")
        if self.orb_levels < 1 or not self.orb_scale_factor > 1.0 or self.orb_fast_threshold < 1:
            raise ValueError("ORB needs orb_levels >= 1, orb_scale_factor > 1 and orb_fast_threshold >= 1")
        if not 0.1 <= self.image_scale <= 1.0:
            raise ValueError(f"image_scale must lie in 0.1 .. 1, got {self.image_scale}")

    @property
    def binary(self) -> bool:
        """True for packed binary descriptors compared by Hamming distance."""
        return self.kind == "orb"

    @property
    def descriptor_size(self) -> int:
        """Elements per descriptor: 128 floats (SIFT) or 32 bytes (ORB)."""
        return 32 if self.binary else 128


@dataclass(frozen=True, eq=False)
class Features:
    """The keypoints of one image.

    ``keypoints_px (N, 2) float32``: keypoint positions (x right, y down), pixels;
    ``descriptors``: ``(N, 128) float32`` unit-length (SIFT) or ``(N, 32) uint8`` (ORB);
    ``image_size_px``: ``(width, height)``.
    """

    keypoints_px: np.ndarray
    descriptors: np.ndarray
    image_size_px: tuple[int, int]

    def __len__(self) -> int:
        return len(self.keypoints_px)


class FeatureSet(Protocol):
    """What the verification reads of one image's keypoints: :class:`Features` or
    :class:`CompactFeatures`."""

    @property
    def keypoints_px(self) -> np.ndarray: ...

    @property
    def descriptors(self) -> np.ndarray: ...

    @property
    def image_size_px(self) -> tuple[int, int]: ...

    def __len__(self) -> int: ...


#: Keypoint positions are kept in fixed point, 1/16 pixel (error at most 1/32 px, far below
#: the verification's 1 px RANSAC threshold), as uint16: images up to 4095 px wide.
KEYPOINT_SCALE = 16.0


@dataclass(frozen=True, eq=False)
class CompactFeatures:
    """What the detector keeps of one past image for voting and verification:
    ``words (N,) uint32`` (the vocabulary word of each keypoint), ``keypoints_q (N, 2)
    uint16`` (positions in 1/16 px), ``descriptors`` as extracted (``(N, 32) uint8`` ORB;
    SIFT stays ``(N, 128) float32``, the paper's reference), ``image_size_px``. It reads
    like :class:`Features` (``keypoints_px``, ``descriptors``, ``len``), so the
    verification takes it as is. 300 ORB keypoints: 12,000 bytes; 10,800 once the words
    are dropped (:func:`without_words`: a detector keeps the word ids of its latest image
    only, the inverted index and the map file hold them for the others)."""

    words: np.ndarray
    keypoints_q: np.ndarray
    descriptors: np.ndarray
    image_size_px: tuple[int, int]

    def __len__(self) -> int:
        return len(self.keypoints_q)

    @property
    def keypoints_px(self) -> np.ndarray:
        """``(N, 2) float32`` keypoint positions, pixels."""
        return self.keypoints_q.astype(np.float32) / np.float32(KEYPOINT_SCALE)

    @property
    def nbytes(self) -> int:
        """Bytes of the three arrays."""
        return int(self.words.nbytes + self.keypoints_q.nbytes + self.descriptors.nbytes)


def compact(feats: Features, words: np.ndarray) -> CompactFeatures:
    """``feats`` and their ``words`` (``(N,)`` int) as :class:`CompactFeatures`."""
    w, h = feats.image_size_px
    if max(w, h) * KEYPOINT_SCALE > np.iinfo(np.uint16).max:
        raise ValueError(f"images up to {int(np.iinfo(np.uint16).max / KEYPOINT_SCALE)} px wide are kept, got {w}x{h}")
    q = np.rint(np.clip(feats.keypoints_px, 0.0, None) * KEYPOINT_SCALE).astype(np.uint16)
    return CompactFeatures(np.asarray(words, np.uint32), q, feats.descriptors, feats.image_size_px)


_NO_WORDS = np.zeros(0, np.uint32)


def without_words(f: CompactFeatures) -> CompactFeatures:
    """``f`` without its word ids (``words`` empty; keypoints and descriptors, which the
    verification reads, are the same arrays)."""
    return replace(f, words=_NO_WORDS)


@dataclass(frozen=True, eq=False, slots=True)
class LentFeatures:
    """A past image's features whose *founding* descriptors (those that made a word the
    word search still holds: the word's descriptor is that very descriptor) are left to
    the word search, so that the two do not both keep them.

    One buffer ``data`` (bytes: one object rather than four arrays, and a bytes object's
    own header is a third of an array's, about a hundred bytes): the descriptors of the
    keypoints not lent (``(n - k)`` x 32, in keypoint order), the keypoints (``n`` x 2
    uint16, 1/16 px, as :attr:`CompactFeatures.keypoints_q`), the lent keypoints' indices
    (``k`` uint16, increasing), and, when ``ranked``, their words' ranks among the words
    the image made (``k`` uint16: word id minus the image's first word id; without, the
    ranks are 0 .. k - 1: an image lends every word it made until the words seen once are
    purged).
    ``n`` keypoints, ``k`` lent. :meth:`with_descriptors` puts the image together again
    given the lent words' descriptors."""

    data: bytes
    n: int
    k: int
    image_size_px: tuple[int, int]
    ranked: bool = True

    def __len__(self) -> int:
        return self.n

    @property
    def own(self) -> np.ndarray:
        """``(n - k, 32) uint8``: the descriptors of the keypoints not lent, in keypoint order."""
        return np.frombuffer(self.data, np.uint8, 32 * (self.n - self.k)).reshape(self.n - self.k, 32)

    @property
    def keypoints_q(self) -> np.ndarray:
        """``(n, 2) uint16`` keypoint positions, 1/16 px (a read-only view)."""
        o = 32 * (self.n - self.k)
        return np.frombuffer(self.data, np.uint16, 2 * self.n, o).reshape(self.n, 2)

    @property
    def lent_at(self) -> np.ndarray:
        """``(k,) uint16``: the lent keypoints, increasing (a read-only view)."""
        o = 32 * (self.n - self.k) + 4 * self.n
        return np.frombuffer(self.data, np.uint16, self.k, o)

    @property
    def lent_rank(self) -> np.ndarray:
        """``(k,) uint16``: each lent keypoint's word, as its id minus the image's first word id."""
        if not self.ranked:
            return np.arange(self.k, dtype=np.uint16)
        o = 32 * (self.n - self.k) + 4 * self.n + 2 * self.k
        return np.frombuffer(self.data, np.uint16, self.k, o)

    @property
    def nbytes(self) -> int:
        """Bytes of the buffer."""
        return len(self.data)

    def _rows(self, lent: np.ndarray) -> np.ndarray:
        """All ``n`` descriptors as ``(n, 4) uint64`` rows, ``lent (k, 32) uint8`` in :attr:`lent_at` order."""
        at = self.lent_at
        mine = np.ones(self.n, bool)
        mine[at] = False
        d = np.empty((self.n, 4), np.uint64)
        d[np.flatnonzero(mine)] = np.frombuffer(self.data, np.uint64, 4 * (self.n - self.k)).reshape(-1, 4)
        d[at] = np.ascontiguousarray(lent, np.uint8).view(np.uint64).reshape(-1, 4)
        return d

    def with_descriptors(self, lent: np.ndarray) -> CompactFeatures:
        """The image as :class:`CompactFeatures` (no word ids), ``lent (k, 32) uint8`` the
        lent keypoints' descriptors in :attr:`lent_at` order."""
        return CompactFeatures(_NO_WORDS, self.keypoints_q, self._rows(lent).view(np.uint8), self.image_size_px)

    def give_back(self, ranks: np.ndarray, descriptors: np.ndarray) -> LentFeatures | CompactFeatures:
        """The record once the words of ``ranks`` (``(K,) int``) leave the word search with
        their ``descriptors`` (``(K, 32) uint8``): those keypoints keep their descriptors
        again (the others stay lent; :class:`CompactFeatures` without words when none is
        left lent). Ranks the record did not lend are ignored."""
        rank = self.lent_rank.astype(np.int64)
        r = np.asarray(ranks, np.int64)
        r_ok = (r >= 0) & (r < 65536)
        if not r_ok.any():
            return self
        which = np.full(max(int(r[r_ok].max()), int(rank.max(initial=0))) + 1, -1, np.int64)
        which[r[r_ok]] = np.flatnonzero(r_ok)       # rank -> its row in ``descriptors``
        row = which[rank]
        back = row >= 0
        if not back.any():
            return self
        lent = np.zeros((self.k, 32), np.uint8)
        lent[back] = np.asarray(descriptors, np.uint8)[row[back]]
        d = self._rows(lent)
        kq = self.keypoints_q
        if back.all():
            return CompactFeatures(_NO_WORDS, kq.copy(), d.view(np.uint8), self.image_size_px)
        return _pack(kq, d, self.lent_at[~back], rank[~back], self.image_size_px)


def _pack(keypoints_q: np.ndarray, rows: np.ndarray, at: np.ndarray, rank: np.ndarray,
          size: tuple[int, int]) -> LentFeatures:
    """A :class:`LentFeatures` of ``keypoints_q (n, 2) uint16``, descriptors ``rows (n, 4)
    uint64``, lending keypoints ``at`` (``(k,)`` increasing) as words of ranks ``rank``
    (not stored when they are 0 .. k - 1)."""
    n, k = len(keypoints_q), len(at)
    mine = np.ones(n, bool)
    mine[at] = False
    r = np.asarray(rank, np.uint16)
    ranked = not np.array_equal(r, np.arange(k))
    parts = [np.compress(mine, rows, axis=0).view(np.uint8).reshape(-1),
             np.ascontiguousarray(keypoints_q, np.uint16).reshape(-1).view(np.uint8), np.asarray(at, np.uint16).view(np.uint8)]
    return LentFeatures(b"".join(p.tobytes() for p in (parts + [r.view(np.uint8)] if ranked else parts)), n, k, size,
                        ranked)


def lend(f: CompactFeatures, at: np.ndarray, rank: np.ndarray,
         size: tuple[int, int] | None = None) -> LentFeatures | CompactFeatures:
    """``f`` (binary descriptors, ``(N, 32) uint8``) with the descriptors of keypoints
    ``at`` (``(k,) int``, distinct) left to the word search, which holds them as the words
    of ranks ``rank`` (``(k,) int``, below 65,536: the word's id minus the first id the
    image made); ``f`` without words when ``at`` is empty. ``size``: the image size to
    keep (an equal tuple shared by many images; default ``f``'s)."""
    size = f.image_size_px if size is None else size
    if not len(at):
        return replace(f, words=_NO_WORDS, image_size_px=size)
    at = np.asarray(at, np.int64)
    rank = np.asarray(rank, np.int64)
    if np.any(at[1:] <= at[:-1]):
        order = np.argsort(at)
        at, rank = at[order], rank[order]
    if len(f) > 65535 or int(rank.max()) > 65535:
        raise ValueError("an image lends at most 65,536 keypoints")
    rows = np.ascontiguousarray(f.descriptors, np.uint8).view(np.uint64).reshape(len(f), 4)
    return _pack(f.keypoints_q, rows, at, rank, size)


def to_gray(image: np.ndarray) -> np.ndarray:
    """An 8-bit single-channel view of ``image`` (``(H, W)`` or ``(H, W, 3)`` BGR, uint8)."""
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim != 2:
        raise ValueError(f"expected an (H, W) or (H, W, 3) image, got shape {image.shape}")
    return image


class FeatureExtractor:
    """Holds one OpenCV detector so it is not rebuilt per image (not thread-safe: one per
    thread)."""

    def __init__(self, params: FeatureParams = FeatureParams()) -> None:
        self.params = params
        self._detector: cv2.Feature2D
        if params.kind == "sift":
            self._detector = cv2.SIFT.create(nfeatures=params.max_features,
                                              contrastThreshold=params.sift_contrast_threshold)
        else:
            self._detector = cv2.ORB.create(nfeatures=params.max_features or 1000, scaleFactor=params.orb_scale_factor,
                                            nlevels=params.orb_levels, fastThreshold=params.orb_fast_threshold)

    def __call__(self, image: np.ndarray) -> Features:
        gray = to_gray(image)
        size = (int(gray.shape[1]), int(gray.shape[0]))
        scale = self.params.image_scale
        if scale != 1.0:
            gray = cv2.resize(gray, (max(1, round(size[0] * scale)), max(1, round(size[1] * scale))),
                              interpolation=cv2.INTER_AREA)
        kps, desc = self._detector.detectAndCompute(gray, None)
        if desc is None or not kps:
            shape = (0, self.params.descriptor_size)
            return Features(np.zeros((0, 2), np.float32),
                            np.zeros(shape, np.uint8 if self.params.binary else np.float32), size)
        xy = np.asarray(cv2.KeyPoint.convert(kps), np.float32).reshape(-1, 2)
        if scale != 1.0:  # back to the full image's pixels (pixel centres at integers)
            back = np.array([size[0] / gray.shape[1], size[1] / gray.shape[0]], np.float32)
            xy = (xy + np.float32(0.5)) * back - np.float32(0.5)
        if self.params.binary:
            return Features(xy, np.ascontiguousarray(desc, np.uint8), size)
        d = np.asarray(desc, np.float32)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return Features(xy, d, size)


def extract_features(image: np.ndarray, params: FeatureParams = FeatureParams()) -> Features:
    """Keypoints and descriptors of ``image`` (one-off; a detector loop should keep a
    :class:`FeatureExtractor`)."""
    return FeatureExtractor(params)(image)
