"""Compact floor descriptor in the style of MPEG CDVS (paper 003, Sec. II-A).

``extract(image, mode) -> bytes`` never returns more than ``MODE_BYTES[mode]`` bytes;
``decode(bytes) -> FloorDescriptor`` gives what matching (:mod:`robotd.floor.match`)
needs. It follows the six steps of CDVS (ISO/IEC 15938-13, paper 003 Sec. II-A) and keeps
its trade-offs (more bytes: more and longer local descriptors), but is not
bitstream-compatible with the standard. It is built for a downward floor camera: the
floor's scale barely changes between views, its rotation changes all the time.

1. **Interest points.** One difference of Gaussians (sigma ``detect_sigma_px`` and
   ``dog_ratio`` times it) on the half-resolution image, instead of the CDVS/SIFT scale
   space: local extrema over 3x3 above ``min_contrast`` (the image is normalised by its
   standard deviation, so exposure drift does not matter), edge responses rejected by
   the Hessian ratio (Lowe 2004, Sec. 4.1), sub-pixel refinement by a quadratic fit.
   Orientation: the direction of the gradient of the image smoothed at
   ``orientation_sigma_px``, at the keypoint (the intensity centroid of ORB with a
   Gaussian window); its strength is a selection attribute.
2. **Selection.** CDVS ranks keypoints by the product of learned per-attribute
   probabilities that a keypoint matches. Ours: detector response, edge ratio, distance
   from the image centre and orientation strength, each binned; the log-probability
   tables were learned on virtual-robot pairs (``tools/train_selection.py``, shipped in
   ``selection.npz``). Keypoints that repeat within their own image are dropped first
   (:func:`drop_repeats`: a printed floor repeats its few prints every few planks, and a
   keypoint whose copy is in view is ambiguous to every other view of that floor). The
   budget is filled greedily in that order.
3. **Local descriptors** of the selected keypoints only: 4 x 4 cells x 8 orientation
   bins of gradients in a patch rotated to the keypoint's orientation (SIFT-like). The
   gradient orientation maps are pooled once over the image (as DAISY does) and one
   ``cv2.remap`` samples every keypoint's rotated 4 x 4 grid; the 8 bins are turned by
   the keypoint's orientation (linear interpolation between whole-bin shifts).
4. **Compression** (CDVS: a fixed transform of each cell's histogram, then ternary
   quantisation). Each cell's 8 bins become 8 Haar-like sums and differences of
   neighbouring bins (shifted by one bin in every other cell, as CDVS alternates two
   transforms); each element is quantised to {-1, 0, +1} with learned thresholds. Only
   the first ``MODES[mode].length`` elements of a learned priority order are kept (24 to
   128 trits, growing with the mode), packed 5 trits per byte (1.6 bits per trit).
5. **Coordinates.** Positions are quantised to a ``POSITION_STEP_PX`` grid; the sorted
   cell indices are coded as gaps with a Rice code (the unary parts in one stream, the
   ``k``-bit remainders in another), about 8-12 bits per keypoint, plus
   ``ANGLE_BITS`` = 5 bits of orientation (needed by the geometric check).
6. **Global descriptor.** A binarised VLAD (CDVS uses SCFV, a binarised Fisher vector):
   the keypoints' descriptors projected by a learned PCA to 32 dimensions, residuals to
   the nearest of 32 learned centroids summed, signed square root, per-centroid L2
   normalisation, then a random-sign Walsh-Hadamard projection whose signs are the
   ``MODES[mode].global_bits`` bits (SimHash: Hamming distance tracks the angle).

Byte layout (little endian), see :func:`_pack` and :func:`decode`::

    0  magic b"FD" | 2 version u8 | 3 mode u8 | 4 width u16 | 6 height u16
    8  work width u16 | 10 work height u16 | 12 n u16 | 14 rice k u8 | 15 reserved (0)
    16 CRC-32 u32 of every byte except these four
    20 global bits (global_bits / 8 bytes)
       Rice remainders (ceil(n k / 8) bytes) | angles (ceil(5 n / 8) bytes)
       trits (ceil(n L / 5) bytes) | Rice unary parts (to the end, padded with 1 bits)

Everything is counted in the budget; images wider or taller than 65535 px are refused.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from robotd.base.errors import DescriptorError

__all__ = ["ANGLE_BITS", "MODE_BYTES", "MODES", "POSITION_STEP_PX", "ExtractParams", "FloorDescriptor",
           "Learned", "decode", "describe", "drop_repeats", "extract", "load_learned"]

MODE_BYTES = {1: 512, 2: 1024, 3: 2048, 4: 4096, 5: 8192, 6: 16384}
MAGIC = b"FD"
VERSION = 1
HEADER = struct.Struct("<2sBBHHHHHBBI")  # 20 bytes
POSITION_STEP_PX = 2  # coordinate grid, pixels of the working image
ANGLE_BITS = 5
N_ELEMENTS = 128  # transformed elements per descriptor (16 cells x 8)
N_ATTRIBUTES = 4  # selection attributes: response, edge ratio, centre distance, orientation strength


class ModeSpec(NamedTuple):
    """Per mode: byte bound, trits kept per local descriptor, global descriptor bits."""

    bytes: int
    length: int
    global_bits: int


MODES = {1: ModeSpec(512, 24, 256), 2: ModeSpec(1024, 32, 256), 3: ModeSpec(2048, 48, 512),
         4: ModeSpec(4096, 64, 512), 5: ModeSpec(8192, 96, 1024), 6: ModeSpec(16384, 128, 1024)}


@dataclass(frozen=True)
class ExtractParams:
    """Extraction parameters (lengths in pixels of the half-resolution image).

    The shipped ``selection.npz`` was learned with the defaults; change them and retrain.

    Fields:
        max_side_px: inputs with a longer side are first downscaled (area averaging) to it.
        detect_sigma_px: inner Gaussian of the difference of Gaussians.
        dog_ratio: outer / inner sigma of the difference of Gaussians.
        min_contrast: smallest |DoG| kept, in units of the image's standard deviation.
        edge_ratio: Hessian ratio above which an extremum is an edge and dropped (Lowe: 10).
        orientation_sigma_px: smoothing of the image whose gradient gives the orientation.
        pool_sigma_px: Gaussian pooling of the gradient orientation maps (cell support).
        cell_px: distance between the centres of neighbouring descriptor cells.
        max_candidates: cap on the candidates ranked (strongest responses first).
        repeat_distance: a keypoint whose own image holds another keypoint (beyond the
            descriptor's patch, ``4 cell_px``) with a raw descriptor nearer than this (L2 of
            the unit-norm 128-D descriptors) is a repeat and is not coded. 0.3 is about the
            90th percentile of the distance between two views of one floor point (measured
            on the virtual robot's floors; unrelated keypoints are 0.7-1.0 apart): the copy
            is as alike as a re-observation. 0 keeps every keypoint.
        repeat_pool: how many of the most relevant candidates are checked for repeats
            (the pairwise distances cost ``repeat_pool**2 x 128`` multiply-adds); candidates
            after them are kept unchecked. Enough for the largest mode's budget.
        global_min_features: the global descriptor aggregates at least this many of the
            best keypoints, even when fewer are coded (low modes).
        learned: learned tables; None = the shipped ``selection.npz``.
    """

    max_side_px: int = 1280
    detect_sigma_px: float = 1.8
    dog_ratio: float = 1.6
    min_contrast: float = 0.03
    edge_ratio: float = 10.0
    orientation_sigma_px: float = 4.0
    pool_sigma_px: float = 2.5
    cell_px: float = 6.0
    max_candidates: int = 4000
    repeat_distance: float = 0.3
    repeat_pool: int = 1000
    global_min_features: int = 200
    learned: Learned | None = None

    def __post_init__(self) -> None:
        if not (self.max_side_px >= 32 and self.detect_sigma_px > 0 and self.dog_ratio > 1
                and self.edge_ratio > 1 and self.orientation_sigma_px > 0 and self.pool_sigma_px > 0
                and self.cell_px > 0 and self.max_candidates >= 1 and self.global_min_features >= 0
                and self.repeat_distance >= 0 and self.repeat_pool >= 0):
            raise ValueError(f"extraction parameters out of range: {self}")


@dataclass(frozen=True, eq=False)
class Learned:
    """The learned tables (``selection.npz``, made by ``tools/train_selection.py``).

    ``rel_edges (4, B-1)`` bin edges and ``rel_logp (4, B)`` log P(match | bin) of the
    selection attributes; ``tern_lo``, ``tern_hi (128,)`` ternary thresholds of the
    transformed elements; ``order (128,)`` element priority; ``pca_mean (128,)``,
    ``pca_basis (128, 32)``, ``centroids (32, 32)`` and ``signs (1024,)`` (+-1) of the
    global descriptor.
    """

    rel_edges: np.ndarray
    rel_logp: np.ndarray
    tern_lo: np.ndarray
    tern_hi: np.ndarray
    order: np.ndarray
    pca_mean: np.ndarray
    pca_basis: np.ndarray
    centroids: np.ndarray
    signs: np.ndarray


def load_learned(path: str | Path | None = None) -> Learned:
    """Read learned tables from ``path`` (default: the ``selection.npz`` shipped here)."""
    if path is None:
        return _shipped()
    with np.load(path) as z:
        return Learned(**{k: np.array(z[k]) for k in Learned.__dataclass_fields__})


@lru_cache(maxsize=1)
def _shipped() -> Learned:
    with resources.as_file(resources.files("robotd.floor") / "selection.npz") as p:
        return load_learned(p)


@dataclass(frozen=True, eq=False)
class FloorDescriptor:
    """A decoded descriptor. ``N`` keypoints, in the coded (position) order.

    Fields:
        mode: 1-6.
        width_px, height_px: size of the described image, pixels.
        xy_px: ``(N, 2) float32`` keypoint positions, pixels of that image (centre of the
            coded grid cell: within ``position_step_px / 2`` of the detected position).
        angle_rad: ``(N,) float32`` keypoint orientation in [0, 2 pi), quantised to
            ``2 pi / 2**ANGLE_BITS``; it turns with the image (counter-clockwise on screen
            is negative, as image y points down).
        local_pos, local_neg: ``(N, W) uint64`` bit planes of the ternary local
            descriptors: bit ``j`` (word ``j // 64``, bit ``j % 64``) is set where element
            ``j`` is +1, resp. -1. ``W = ceil(length / 64)``.
        length: ternary elements per local descriptor.
        global_bits: ``(global_bits / 8,) uint8`` the packed binary global descriptor.
        position_step_px: the coordinate grid step, pixels of the described image.
    """

    mode: int
    width_px: int
    height_px: int
    xy_px: np.ndarray
    angle_rad: np.ndarray
    local_pos: np.ndarray
    local_neg: np.ndarray
    length: int
    global_bits: np.ndarray
    position_step_px: float

    def __len__(self) -> int:
        return len(self.xy_px)

    def ternary(self) -> np.ndarray:
        """The local descriptors as ``(N, length) float32`` in {-1, 0, +1}."""
        return _unpack_planes(self.local_pos, self.length) - _unpack_planes(self.local_neg, self.length)

    def nonzero_trits(self) -> np.ndarray:
        """``(N,) float32``: the non-zero elements of each local descriptor (its squared norm)."""
        return np.bitwise_count(self.local_pos | self.local_neg).sum(axis=1, dtype=np.float32)


# ----------------------------------------------------------------------------- steps 1-3

class Candidates(NamedTuple):
    """Keypoint candidates of one image (working-image pixels, see :func:`candidates`).

    ``xy (C, 2) float32``; ``angle (C,)`` radians; ``attributes (C, 4) float32``:
    response, edge ratio, distance from the centre (0 centre, 1 corner), orientation
    strength; ``relevance (C,)`` log-probability of matching (``-inf`` when not learned).
    """

    xy: np.ndarray
    angle: np.ndarray
    attributes: np.ndarray
    relevance: np.ndarray
    pooled: tuple[np.ndarray, np.ndarray]  # pooled orientation maps, 2 x (h, w, 4) float32


def _grey(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    elif a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"image must be (H, W) grey or (H, W, 3) BGR with H, W >= 1, got shape {a.shape}")
    if max(a.shape) > 65535:
        raise ValueError(f"image sides must be at most 65535 px, got {a.shape[1]}x{a.shape[0]}")
    return np.ascontiguousarray(a)


def _working(grey: np.ndarray, params: ExtractParams) -> np.ndarray:
    h, w = grey.shape
    if max(h, w) > params.max_side_px:
        f = params.max_side_px / max(h, w)
        grey = cv2.resize(grey, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    return grey


def candidates(work: np.ndarray, params: ExtractParams, learned: Learned | None) -> Candidates:
    """Steps 1 and 2: keypoints of a working image ``(h, w) uint8`` with their attributes.

    Sorted by decreasing relevance (by response when ``learned`` is None).
    """
    h2, w2 = work.shape[0] // 2, work.shape[1] // 2
    empty = Candidates(np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
                       np.zeros((0, N_ATTRIBUTES), np.float32), np.zeros(0, np.float32),
                       (np.zeros((1, 1, 4), np.float32),) * 2)
    border = int(math.ceil(params.cell_px))  # keep the inner cells inside the image
    if min(h2, w2) < 2 * border + 3:
        return empty
    x = cv2.resize(work, (w2, h2), interpolation=cv2.INTER_AREA).astype(np.float32)
    x *= np.float32(1.0 / max(float(x.std()), 1.0))  # flat images: no keypoint passes
    s = params.detect_sigma_px
    g1 = cv2.GaussianBlur(x, (0, 0), s)
    d = g1 - cv2.GaussianBlur(g1, (0, 0), s * math.sqrt(params.dog_ratio**2 - 1.0))
    ext = (d == cv2.dilate(d, None)) | (d == cv2.erode(d, None))
    ext &= np.abs(d) > params.min_contrast
    ext[:border], ext[-border:], ext[:, :border], ext[:, -border:] = False, False, False, False
    ys, xs = np.nonzero(ext)
    dc = d[ys, xs]
    if len(dc) > params.max_candidates:
        keep = np.argpartition(-np.abs(dc), params.max_candidates - 1)[: params.max_candidates]
        ys, xs, dc = ys[keep], xs[keep], dc[keep]
    # Hessian of the DoG: edge rejection (Lowe 2004, Sec. 4.1) and sub-pixel offset.
    dxx = d[ys, xs + 1] + d[ys, xs - 1] - 2 * dc
    dyy = d[ys + 1, xs] + d[ys - 1, xs] - 2 * dc
    dxy = 0.25 * (d[ys + 1, xs + 1] - d[ys + 1, xs - 1] - d[ys - 1, xs + 1] + d[ys - 1, xs - 1])
    det = dxx * dyy - dxy * dxy
    edge = (dxx + dyy) ** 2 / np.where(det > 0, det, 1.0)
    ok = (det > 0) & (edge < (params.edge_ratio + 1) ** 2 / params.edge_ratio)
    ys, xs, dc, dxx, dyy, dxy, det, edge = (v[ok] for v in (ys, xs, dc, dxx, dyy, dxy, det, edge))
    if len(xs) == 0:
        return empty
    gx = 0.5 * (d[ys, xs + 1] - d[ys, xs - 1])
    gy = 0.5 * (d[ys + 1, xs] - d[ys - 1, xs])
    ox = np.clip((-dyy * gx + dxy * gy) / det, -0.5, 0.5)
    oy = np.clip((dxy * gx - dxx * gy) / det, -0.5, 0.5)
    xy_half = np.column_stack([xs + ox, ys + oy]).astype(np.float32)
    # Orientation: gradient of the image smoothed at orientation_sigma_px, at the keypoint.
    go = cv2.GaussianBlur(x, (0, 0), params.orientation_sigma_px)
    grad = cv2.merge([cv2.Sobel(go, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(go, cv2.CV_32F, 0, 1, ksize=1)])
    v = cv2.remap(grad, np.ascontiguousarray(xy_half[:, :1]), np.ascontiguousarray(xy_half[:, 1:]),
                  cv2.INTER_LINEAR).reshape(-1, 2)
    angle = np.arctan2(v[:, 1], v[:, 0]).astype(np.float32) % np.float32(2 * math.pi)
    xy = xy_half * 2 + 0.5  # half-resolution pixel centre -> working-image pixels
    hw = np.array([work.shape[1] - 1, work.shape[0] - 1], np.float32) * 0.5
    attributes = np.column_stack([np.abs(dc), edge, np.linalg.norm((xy - hw) / hw, axis=1) / math.sqrt(2),
                                  np.hypot(v[:, 0], v[:, 1])]).astype(np.float32)
    if learned is None:
        relevance = np.abs(dc).astype(np.float32)
    else:
        relevance = np.zeros(len(xy), np.float32)
        for a in range(N_ATTRIBUTES):
            relevance += learned.rel_logp[a][np.searchsorted(learned.rel_edges[a], attributes[:, a])]
    order = np.argsort(-relevance, kind="stable")
    pooled = _pooled_orientation_maps(g1, params.pool_sigma_px)
    return Candidates(xy[order], angle[order], attributes[order], relevance[order], pooled)


def _pooled_orientation_maps(g: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """8 gradient-orientation channels (each gradient's magnitude split linearly between
    the two nearest of 8 directions), Gaussian-pooled: two ``(h, w, 4) float32`` images
    (directions 0-3 and 4-7; OpenCV filters up to 4 channels fastest)."""
    mag, ang = cv2.cartToPolar(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=1))
    b = ang.ravel() * np.float32(8 / (2 * math.pi))
    b0 = b.astype(np.int32)
    hi = mag.ravel() * (b - b0)
    npx = len(b)
    # Direction d of pixel p goes to plane d // 4, slot p * 4 + d % 4; both planes contiguous.
    base = np.arange(0, 4 * npx, 4, dtype=np.int32)
    ch = np.zeros(8 * npx, np.float32)
    d0, d1 = b0 & 7, (b0 + 1) & 7
    ch[base + (d0 >> 2) * (4 * npx) + (d0 & 3)] = mag.ravel() - hi
    ch[base + (d1 >> 2) * (4 * npx) + (d1 & 3)] = hi  # never the slot just written
    ch = ch.reshape((2,) + g.shape + (4,))
    k = 2 * int(math.ceil(2 * sigma)) + 1
    return cv2.GaussianBlur(ch[0], (k, k), sigma), cv2.GaussianBlur(ch[1], (k, k), sigma)


_GRID = np.meshgrid(np.arange(4, dtype=np.float32) - 1.5, np.arange(4, dtype=np.float32) - 1.5)


def raw_descriptors(c: Candidates, n: int, params: ExtractParams) -> np.ndarray:
    """Step 3: SIFT-like ``(n, 128) float32`` descriptors of the first ``n`` candidates.

    Cell-major (16 cells row by row in the keypoint's frame) x 8 relative orientation
    bins; L2-normalised, clipped at 0.2 and renormalised (Lowe 2004, Sec. 6.1).
    """
    if n == 0:
        return np.zeros((0, N_ELEMENTS), np.float32)
    xy = (c.xy[:n] - 0.5) * 0.5  # back to half-resolution pixels
    ang = c.angle[:n]
    cs, sn = np.cos(ang)[:, None, None], np.sin(ang)[:, None, None]
    u, v = _GRID
    step = np.float32(params.cell_px)
    mx = (xy[:, 0, None, None] + step * (cs * u - sn * v)).reshape(n, 16)
    my = (xy[:, 1, None, None] + step * (sn * u + cs * v)).reshape(n, 16)
    smp = np.concatenate([cv2.remap(p, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
                          for p in c.pooled + c.pooled], axis=2)  # (n, 16, 16): directions 0-7 twice
    # Turn the 8 absolute directions into directions relative to the keypoint: relative
    # bin j is absolute direction angle + j * 45 deg, interpolated between whole bins.
    a = ang * np.float32(8 / (2 * math.pi))
    a0 = a.astype(np.intp) & 7
    f = (a - np.floor(a))[:, None, None]
    win = np.lib.stride_tricks.sliding_window_view(smp, 8, axis=2)  # (n, 16, 9, 8)
    rows = np.arange(n)
    d = win[rows, :, a0] * (1 - f) + win[rows, :, a0 + 1] * f
    d = d.reshape(n, N_ELEMENTS)
    d *= 1 / np.maximum(np.sqrt(np.einsum("ij,ij->i", d, d)), 1e-12)[:, None]
    np.minimum(d, 0.2, out=d)
    d *= 1 / np.maximum(np.sqrt(np.einsum("ij,ij->i", d, d)), 1e-12)[:, None]
    return d


def drop_repeats(c: Candidates, params: ExtractParams) -> tuple[Candidates, np.ndarray]:
    """Step 2b: drop the candidates that repeat within their own image.

    Of the first ``params.repeat_pool`` candidates (relevance order), each one whose raw
    descriptor (:func:`raw_descriptors`) lies within ``params.repeat_distance`` of another
    one's is dropped, both copies alike, unless the two are closer than the descriptor's
    patch (``4 cell_px``; two extrema on one blob share their patch, they are not a
    repeat). Which copy another view's keypoint is cannot be told from its descriptor, and
    when that view holds both, the matcher's ratio test rejects either (Lowe 2004,
    Sec. 7.1): a repeat spends budget and brings only false agreement.

    That false agreement is what makes a printed floor (paper 003's worst case) alias. Two
    views ``s`` apart, ``s`` a step of the plank lattice, see the same image at the same
    pixels wherever the planks ``s`` apart carry the same print, and the matcher finds the
    identity with most keypoints as inliers while the views are ``s`` apart. A keypoint at
    ``u`` agrees so only if the floor at ``u`` and at ``u + s`` is the same print; when
    ``u + s`` is in view too, the keypoint repeats in its own image and is dropped here. For
    ``s`` under half the view, that leaves only keypoints near the corners.

    Returns the kept candidates (same order) and the ``(K, 128) float32`` raw descriptors
    of the first ``K`` of them (the checked ones that were kept), for reuse.
    """
    k = min(params.repeat_pool, len(c.xy))
    raw = raw_descriptors(c, k, params)
    if params.repeat_distance <= 0 or k < 2:
        return c, raw
    repeat = np.zeros(len(c.xy), bool)
    repeat[:k] = _repeats(raw, c.xy[:k], 0, k, params)
    keep = ~repeat
    kept = Candidates(c.xy[keep], c.angle[keep], c.attributes[keep], c.relevance[keep], c.pooled)
    return kept, raw[keep[:k]]


def _repeats(raw: np.ndarray, xy: np.ndarray, start: int, stop: int, params: ExtractParams) -> np.ndarray:
    """``(stop - start,) bool``: which of the checked candidates ``start:stop`` repeat
    (:func:`drop_repeats`) among all ``K`` checked ones, given their ``(K, 128)`` raw
    descriptors and ``(K, 2)`` working-image positions. Rows are independent, so the
    rows can be decided a block at a time (:func:`extract` decides only as many as the
    budget reaches)."""
    sq = np.einsum("ij,ij->i", raw, raw)
    d2 = raw[start:stop] @ raw.T  # |a - b|^2 = |a|^2 + |b|^2 - 2 a.b, in place
    d2 *= -2.0
    d2 += sq[start:stop, None]
    d2 += sq[None, :]
    i, j = np.nonzero(d2 < params.repeat_distance**2)  # the diagonal, neighbours on one blob, repeats
    patch_px = 2 * 4 * params.cell_px  # the patch width, in working-image pixels (cells are half-resolution)
    far = np.sum((xy[start + i] - xy[j]) ** 2, axis=1) >= patch_px**2
    out = np.zeros(stop - start, bool)
    out[i[far]] = True
    return out


def _kept_for_budget(c: Candidates, params: ExtractParams, spec: ModeSpec, grid_w: int, grid_h: int,
                     block: int = 256) -> tuple[Candidates, np.ndarray, int]:
    """:func:`drop_repeats` and :func:`_fit` together, deciding only the rows needed.

    The coded keypoints are the first ``n`` kept candidates and the global descriptor
    aggregates the first ``max(n, global_min_features)``; whether a later candidate repeats
    changes neither. So the candidates are checked (each against the whole pool, as
    :func:`drop_repeats` does) a ``block`` at a time until the kept ones reach past what
    the budget codes. The result is the same as ``drop_repeats`` then ``_fit`` for
    everything :func:`extract` uses: the returned candidates are exact up to the first
    ``max(n + 1, global_min_features)`` kept ones, and end there when not all were checked.

    Returns the kept candidates, the raw descriptors of the first of them (the checked
    ones) and ``n``.
    """
    k = min(params.repeat_pool, len(c.xy))
    if params.repeat_distance <= 0 or k < 2:
        kept, raw = c, raw_descriptors(c, k, params)
        return kept, raw, _fit(spec, _cells(kept.xy, grid_w, grid_h))
    raw = raw_descriptors(c, k, params)
    repeat = np.zeros(k, bool)
    done = 0
    while True:
        stop = min(k, done + block)
        repeat[done:stop] = _repeats(raw, c.xy[:k], done, stop, params)
        done = stop
        keep = np.flatnonzero(~repeat[:done])
        if done == k:  # every checked row decided; unchecked candidates after the pool are kept
            keep = np.concatenate([keep, np.arange(k, len(c.xy))])
        n = _fit(spec, _cells(c.xy[keep], grid_w, grid_h))
        if done == k or (n < len(keep) and len(keep) >= params.global_min_features):
            break
    kept = Candidates(c.xy[keep], c.angle[keep], c.attributes[keep], c.relevance[keep], c.pooled)
    return kept, raw[keep[keep < k]], n


def _haar() -> np.ndarray:
    """``(2, 8, 8)`` the two per-cell transforms (the second on bins shifted by one)."""
    t = np.zeros((8, 8), np.float32)
    for k in range(4):  # differences of neighbouring bins
        t[k, 2 * k], t[k, 2 * k + 1] = 1, -1
    t[4, :4], t[4, 2:4] = 1, -1  # (h0 + h1) - (h2 + h3)
    t[5, 4:], t[5, 6:] = 1, -1  # (h4 + h5) - (h6 + h7)
    t[6, :4], t[6, 4:] = 1, -1  # first half - second half
    t[7, :] = 1  # the cell's energy
    return np.stack([t, np.roll(t, 1, axis=1)])


def _block_transform() -> np.ndarray:
    """``(128, 128)``: the per-cell transforms, alternating in a checkerboard of cells."""
    t = _haar()
    big = np.zeros((N_ELEMENTS, N_ELEMENTS), np.float32)
    for cell in range(16):
        r, c = divmod(cell, 4)
        big[8 * cell:8 * cell + 8, 8 * cell:8 * cell + 8] = t[(r + c) % 2]
    return big


_TRANSFORM = _block_transform()


def transform(raw: np.ndarray) -> np.ndarray:
    """Step 4a: ``(n, 128)`` raw descriptors -> ``(n, 128)`` transformed elements
    (cell-major, 8 per cell)."""
    return raw @ _TRANSFORM.T


def ternarise(raw: np.ndarray, learned: Learned, length: int) -> np.ndarray:
    """Steps 4a-b: the first ``length`` transformed elements in priority order as
    ``(n, length) int8`` trits."""
    o = learned.order[:length]
    e = raw @ _TRANSFORM[o].T
    return (e > learned.tern_hi[o]).view(np.int8) - (e < learned.tern_lo[o]).view(np.int8)


def global_vector(raw: np.ndarray, learned: Learned) -> np.ndarray:
    """Step 6: the real-valued ``(1024,)`` VLAD, before the Hadamard projection."""
    cen = learned.centroids
    if len(raw) == 0:
        return np.zeros(cen.size, np.float32)
    z = (raw - learned.pca_mean) @ learned.pca_basis
    a = np.argmin((cen * cen).sum(1) - 2 * z @ cen.T, axis=1)
    onehot = np.zeros((len(z), len(cen)), np.float32)
    onehot[np.arange(len(z)), a] = 1
    out = onehot.T @ z - onehot.sum(0)[:, None] * cen  # residual sums per centroid
    out = np.sign(out) * np.sqrt(np.abs(out))
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    return out.ravel()


def _hadamard_bits(vec: np.ndarray, signs: np.ndarray, bits: int) -> np.ndarray:
    """Signs of the first ``bits`` rows of the Walsh-Hadamard transform of ``signs * vec``."""
    h = vec * signs
    step = len(h) // 2
    while step >= 1:  # fast Walsh-Hadamard transform, one vectorised butterfly per stage
        h = h.reshape(-1, 2, step)
        h = np.stack([h[:, 0] + h[:, 1], h[:, 0] - h[:, 1]], axis=1)
        step //= 2
    return np.packbits(h.ravel()[:bits] > 0)


# ---------------------------------------------------------------------- steps 5 and coding

def _rice_k(gaps: np.ndarray) -> tuple[int, int]:
    """Best Rice parameter for ``gaps`` and the unary bit count it costs."""
    if len(gaps) == 0:
        return 0, 0
    ks = np.arange(17)
    unary = (gaps[None, :] >> ks[:, None]).sum(1) + len(gaps)
    k = int(np.argmin(unary + ks * len(gaps)))
    return k, int(unary[k])


def _cells(xy: np.ndarray, grid_w: int, grid_h: int) -> np.ndarray:
    col = np.clip(((xy[:, 0] + 0.5) // POSITION_STEP_PX).astype(np.int64), 0, grid_w - 1)
    row = np.clip(((xy[:, 1] + 0.5) // POSITION_STEP_PX).astype(np.int64), 0, grid_h - 1)
    return row * grid_w + col


def _size(spec: ModeSpec, cells_sorted: np.ndarray) -> int:
    n = len(cells_sorted)
    gaps = np.diff(cells_sorted, prepend=0)
    k, unary = _rice_k(gaps)
    return (HEADER.size + spec.global_bits // 8 + -(-n * k // 8) + -(-n * ANGLE_BITS // 8)
            + -(-n * spec.length // 5) + -(-unary // 8))


def _fit(spec: ModeSpec, cells: np.ndarray) -> int:
    """Largest prefix of ``cells`` (relevance order) whose encoding fits ``spec.bytes``.

    The size grows strictly with every keypoint added (binary search is exact).
    """
    lo, hi = 0, min(len(cells), 65535)
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if _size(spec, np.sort(cells[:mid])) <= spec.bytes:
            lo = mid
        else:
            hi = mid - 1
    return lo


def _pack_trits(t: np.ndarray) -> bytes:
    """``(m,)`` values in {0, 1, 2} -> ceil(m / 5) bytes, 5 base-3 digits per byte."""
    pad = (-len(t)) % 5
    d = np.concatenate([t.astype(np.uint8), np.zeros(pad, np.uint8)]).reshape(-1, 5)
    return (d @ np.array([1, 3, 9, 27, 81], np.uint8)).astype(np.uint8).tobytes()


@lru_cache(maxsize=1)
def _trit_table() -> np.ndarray:
    v = np.arange(243)
    return np.stack([(v // 3**i) % 3 for i in range(5)], axis=1).astype(np.int8)


def _bits_msb(values: np.ndarray, width: int) -> np.ndarray:
    """``(n,)`` ints -> ``(n * width,)`` bits, most significant first."""
    if width == 0:
        return np.zeros(0, np.uint8)
    return ((values[:, None] >> np.arange(width - 1, -1, -1)) & 1).astype(np.uint8).ravel()


def extract(image: np.ndarray, mode: int, params: ExtractParams | None = None) -> bytes:
    """Describe ``image`` (``(H, W) uint8`` grey or ``(H, W, 3)`` BGR) in at most
    ``MODE_BYTES[mode]`` bytes. A blank image gives a valid descriptor with no keypoints.

    Raises ``ValueError`` for an unknown mode or an image that is not uint8 2-D/BGR.
    """
    # 2.0 == 2 is in MODES too, but struct.pack refuses a float after all the work is done.
    if isinstance(mode, bool) or not isinstance(mode, (int, np.integer)) or mode not in MODES:
        raise ValueError(f"mode must be one of {sorted(MODES)}, got {mode!r}")
    mode = int(mode)
    params = params or ExtractParams()
    learned = params.learned or _shipped()
    spec = MODES[mode]
    grey = _grey(image)
    work = _working(grey, params)
    wh, ww = work.shape
    grid_w, grid_h = -(-ww // POSITION_STEP_PX), -(-wh // POSITION_STEP_PX)
    c, raw_checked, n = _kept_for_budget(candidates(work, params, learned), params, spec, grid_w, grid_h)
    cells = _cells(c.xy, grid_w, grid_h)
    m = min(len(c.xy), max(n, params.global_min_features))
    raw = raw_checked[:m] if m <= len(raw_checked) else raw_descriptors(c, m, params)
    trits = ternarise(raw[:n], learned, spec.length)
    gbits = _hadamard_bits(global_vector(raw, learned), learned.signs, spec.global_bits)
    order = np.argsort(cells[:n], kind="stable")
    cs = cells[:n][order]
    gaps = np.diff(cs, prepend=0)
    k, _ = _rice_k(gaps)
    q = np.round(c.angle[:n][order] * (2**ANGLE_BITS / (2 * math.pi))).astype(np.int64) % 2**ANGLE_BITS
    unary = np.ones(int((gaps >> k).sum()) + n, np.uint8)
    unary[np.cumsum((gaps >> k) + 1) - 1] = 0  # q_i ones then a zero
    unary = np.concatenate([unary, np.ones((-len(unary)) % 8, np.uint8)])
    body = b"".join([
        gbits.tobytes(),
        np.packbits(_bits_msb(gaps & ((1 << k) - 1), k)).tobytes(),
        np.packbits(_bits_msb(q, ANGLE_BITS)).tobytes(),
        _pack_trits((trits[order] + 1).ravel()),
        np.packbits(unary).tobytes(),
    ])
    head = HEADER.pack(MAGIC, VERSION, mode, grey.shape[1], grey.shape[0], ww, wh, n, k, 0, 0)
    crc = zlib.crc32(body, zlib.crc32(head[:16]))
    out = head[:16] + struct.pack("<I", crc) + body
    assert len(out) <= spec.bytes, "byte budget overrun"  # guaranteed by _fit
    return out


def _fail(msg: str) -> DescriptorError:
    return DescriptorError(f"floor descriptor: {msg}")


def decode(data: bytes) -> FloorDescriptor:
    """Parse :func:`extract`'s bytes. Raises :class:`DescriptorError` for anything else:
    bad magic, unknown version or mode, wrong length, checksum mismatch, bad codes."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise _fail(f"expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) < HEADER.size:
        raise _fail(f"truncated: {len(data)} bytes, the header alone has {HEADER.size}")
    magic, version, mode, width, height, ww, wh, n, k, reserved, crc = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise _fail(f"bad magic {magic!r} (not a floor descriptor)")
    if version != VERSION:
        raise _fail(f"unsupported version {version} (this build reads version {VERSION})")
    if mode not in MODES:
        raise _fail(f"bad mode {mode}")
    spec = MODES[mode]
    if len(data) > spec.bytes:
        raise _fail(f"{len(data)} bytes exceed mode {mode}'s bound of {spec.bytes}")
    if zlib.crc32(data[HEADER.size:], zlib.crc32(data[:16])) != crc:
        raise _fail("checksum mismatch (corrupt or truncated)")
    if reserved != 0 or k > 16 or not (0 < ww <= width and 0 < wh <= height):
        raise _fail("inconsistent header fields")
    sections = [spec.global_bits // 8, -(-n * k // 8), -(-n * ANGLE_BITS // 8), -(-n * spec.length // 5)]
    pos = HEADER.size
    parts = []
    for s in sections:
        parts.append(np.frombuffer(data, np.uint8, s, pos) if pos + s <= len(data) else None)
        pos += s
    if any(p is None for p in parts):
        raise _fail("truncated body")
    gbits, rem_b, ang_b, trit_b = parts
    unary = np.unpackbits(np.frombuffer(data, np.uint8, offset=pos))
    zeros = np.flatnonzero(unary == 0)
    if len(zeros) != n or (n and len(unary) - zeros[-1] - 1 >= 8) or (not n and len(unary)):
        raise _fail("bad position code")
    quot = np.diff(zeros, prepend=-1) - 1
    rem = np.unpackbits(rem_b)[: n * k].reshape(n, k) @ (1 << np.arange(k - 1, -1, -1)) if k else np.zeros(n, int)
    cells = np.cumsum((quot.astype(np.int64) << k) + rem)
    grid_w, grid_h = -(-ww // POSITION_STEP_PX), -(-wh // POSITION_STEP_PX)
    if n and cells[-1] >= grid_w * grid_h:
        raise _fail("keypoint position outside the image")
    q = np.unpackbits(ang_b)[: n * ANGLE_BITS].reshape(n, ANGLE_BITS) @ (1 << np.arange(ANGLE_BITS - 1, -1, -1))
    if np.any(trit_b > 242):
        raise _fail("bad descriptor code")
    trits = (_trit_table()[trit_b].ravel()[: n * spec.length] - 1).reshape(n, spec.length)
    sx, sy = width / ww, height / wh
    xy = np.column_stack([(cells % grid_w) * POSITION_STEP_PX + (POSITION_STEP_PX - 1) / 2,
                          (cells // grid_w) * POSITION_STEP_PX + (POSITION_STEP_PX - 1) / 2])
    xy = ((xy + 0.5) * [sx, sy] - 0.5).astype(np.float32)
    return FloorDescriptor(mode, width, height, xy, (q * (2 * math.pi / 2**ANGLE_BITS)).astype(np.float32),
                           _pack_planes(trits > 0), _pack_planes(trits < 0), spec.length, gbits.copy(),
                           POSITION_STEP_PX * max(sx, sy))


def describe(image: np.ndarray, mode: int, params: ExtractParams | None = None) -> FloorDescriptor:
    """``decode(extract(image, mode, params))``."""
    return decode(extract(image, mode, params))


def _pack_planes(bits: np.ndarray) -> np.ndarray:
    """``(n, L) bool`` -> ``(n, ceil(L / 64)) uint64``, element j at word j // 64, bit j % 64."""
    n, length = bits.shape
    w = -(-length // 64)
    padded = np.zeros((n, w * 64), np.uint8)
    padded[:, :length] = bits
    return np.packbits(padded, axis=1, bitorder="little").view("<u8").astype(np.uint64)


def _unpack_planes(planes: np.ndarray, length: int) -> np.ndarray:
    b = np.unpackbits(np.ascontiguousarray(planes).astype("<u8").view(np.uint8), axis=1, bitorder="little")
    return b[:, :length].astype(np.float32)
