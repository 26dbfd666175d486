"""Compact floor descriptor in the style of MPEG CDVS (paper 003, Sec. II-A).

``extract(image, mode) -> bytes`` never returns more than ``MODE_BYTES[mode]`` bytes;
``decode(bytes) -> FloorDescriptor`` gives what matching (:mod:`robotd.floor.match`)
needs (``decode_local``: the same in two steps, the positions last, for the floor index's
read back). It follows the six steps of CDVS (ISO/IEC 15938-13, paper 003 Sec. II-A) and keeps
its trade-offs (more bytes: more and longer local descriptors), but is not
bitstream-compatible with the standard. It is built for a downward floor camera: the
floor's scale barely changes between views, its rotation changes all the time.

1. **Interest points.** One difference of Gaussians (sigma ``detect_sigma_px`` and
   ``dog_ratio`` times it) on the half-resolution image (``detect_step`` 2: on that image
   halved, the selectable :data:`QUARTER`), instead of the CDVS/SIFT scale space: local
   extrema over 3x3 above ``min_contrast`` (the image is normalised by its standard
   deviation, so exposure drift does not matter), edge responses rejected by
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
   gradient orientation maps are pooled once over the image (as DAISY does; by default at
   a quarter of the half-resolution image's pixels, ``pool_step`` 2: each pixel's gradient
   is split between the two nearest directions, the channels are halved by area
   averaging, then pooled; they are smooth at the pooling scale), and one ``cv2.remap``
   samples every keypoint's rotated 4 x 4 grid; the 8 bins
   are turned by the keypoint's orientation (linear interpolation between whole-bin
   shifts).
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
from typing import Any

import numpy as np

from robotd.base.errors import DescriptorError
from robotd.floor.compression import global_vector, hadamard_bits, ternarise
from robotd.floor.desccoding import bits_msb, cells, pack_trits, rice_k, trit_table, unpack_planes
from robotd.floor.descparams import (
    ANGLE_BITS,
    FULL_RESOLUTION,
    HEADER,
    MAGIC,
    MODE_BYTES,
    MODES,
    N_ELEMENTS,
    POSITION_STEP_PX,
    QUARTER,
    VERSION,
    ExtractParams,
    Learned,
    load_learned,
    shipped_learned,
)
from robotd.floor.keypoints import (candidates, drop_repeats, grey, kept_for_budget, raw_descriptors, working,
                                    workspace)

__all__ = ["ANGLE_BITS", "FULL_RESOLUTION", "MODE_BYTES", "MODES", "POSITION_STEP_PX", "QUARTER", "ExtractParams", "FloorDescriptor",
           "Learned", "PartialDescriptor", "decode", "decode_local", "describe", "drop_repeats", "extract",
           "extract_with_positions", "load_learned"]


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
        return np.asarray(unpack_planes(self.local_pos, self.length) - unpack_planes(self.local_neg, self.length))

    def nonzero_trits(self) -> np.ndarray:
        """``(N,) float32``: the non-zero elements of each local descriptor (its squared norm)."""
        return np.asarray(np.bitwise_count(self.local_pos | self.local_neg).sum(axis=1, dtype=np.float32))


def extract(image: np.ndarray, mode: int, params: ExtractParams | None = None) -> bytes:
    """Describe ``image`` (``(H, W) uint8`` grey or ``(H, W, 3)`` BGR) in at most
    ``MODE_BYTES[mode]`` bytes. A blank image gives a valid descriptor with no keypoints.

    Raises ``ValueError`` for an unknown mode or an image that is not uint8 2-D/BGR.
    """
    return _extract(image, mode, params)[0]


def extract_with_positions(image: np.ndarray, mode: int,
                           params: ExtractParams | None = None) -> tuple[bytes, np.ndarray]:
    """:func:`extract`, and its keypoints' positions as the detector found them (sub-pixel,
    before the coordinate grid): ``(N, 2) float32`` pixels of the described image, in the
    coded order, so row ``i`` belongs to keypoint ``i`` of ``decode(bytes)``.

    The bytes are :func:`extract`'s to the bit; the positions are not part of them (the
    byte budget holds the grid's), so whoever keeps them keeps them beside the descriptor.
    """
    return _extract(image, mode, params)


def _extract(image: np.ndarray, mode: int, params: ExtractParams | None) -> tuple[bytes, np.ndarray]:
    # 2.0 == 2 is in MODES too, but struct.pack refuses a float after all the work is done.
    if isinstance(mode, bool) or not isinstance(mode, (int, np.integer)) or mode not in MODES:
        raise ValueError(f"mode must be one of {sorted(MODES)}, got {mode!r}")
    mode = int(mode)
    params = params or ExtractParams()
    learned = params.learned or shipped_learned()
    spec = MODES[mode]
    grey_img = grey(image)
    work = working(grey_img, params)
    wh, ww = work.shape
    grid_w, grid_h = -(-ww // POSITION_STEP_PX), -(-wh // POSITION_STEP_PX)
    ws = workspace(wh // 2, ww // 2)
    c, raw_checked, n = kept_for_budget(candidates(work, params, learned, ws), params, spec, grid_w, grid_h,
                                         basis=_orthonormal_basis(learned), ws=ws)
    coded = cells(c.xy[:n], grid_w, grid_h)
    m = min(len(c.xy), max(n, params.global_min_features))
    raw = raw_checked[:m] if m <= len(raw_checked) else raw_descriptors(c, m, params)
    trits = ternarise(raw[:n], learned, spec.length)
    gbits = hadamard_bits(global_vector(raw, learned), learned.signs, spec.global_bits)
    order = np.argsort(coded, kind="stable")
    cs = coded[order]
    gaps = np.diff(cs, prepend=0)
    k, _ = rice_k(gaps)
    q = np.round(c.angle[:n][order] * (2**ANGLE_BITS / (2 * math.pi))).astype(np.int64) % 2**ANGLE_BITS
    unary = np.ones(int((gaps >> k).sum()) + n, np.uint8)
    unary[np.cumsum((gaps >> k) + 1) - 1] = 0  # q_i ones then a zero
    unary = np.concatenate([unary, np.ones((-len(unary)) % 8, np.uint8)])
    body = b"".join([
        gbits.tobytes(),
        np.packbits(bits_msb(gaps & ((1 << k) - 1), k)).tobytes(),
        np.packbits(bits_msb(q, ANGLE_BITS)).tobytes(),
        pack_trits((trits[order] + 1).ravel()),
        np.packbits(unary).tobytes(),
    ])
    head = HEADER.pack(MAGIC, VERSION, mode, grey_img.shape[1], grey_img.shape[0], ww, wh, n, k, 0, 0)
    crc = zlib.crc32(body, zlib.crc32(head[:16]))
    out = head[:16] + struct.pack("<I", crc) + body
    assert len(out) <= spec.bytes, "byte budget overrun"  # guaranteed by _fit
    # The detected positions in the described image's pixels, as decode maps a cell's centre.
    xy = (c.xy[:n][order] + np.float32(0.5)) * np.array([grey_img.shape[1] / ww, grey_img.shape[0] / wh], np.float32)
    return out, np.asarray(xy - np.float32(0.5), np.float32)


@lru_cache(maxsize=8)
def _orthonormal_basis(learned: Learned) -> np.ndarray | None:
    """The learned PCA basis when its columns are orthonormal (an SVD's are), else None:
    only then does it prefilter the repeat check exactly (:func:`kept_for_budget`)."""
    b = np.asarray(learned.pca_basis, np.float64)
    ok = b.ndim == 2 and b.shape[0] == N_ELEMENTS and np.allclose(b.T @ b, np.eye(b.shape[1]), atol=1e-4)
    return np.asarray(learned.pca_basis, np.float32) if ok else None


def _fail(msg: str) -> DescriptorError:
    return DescriptorError(f"floor descriptor: {msg}")


_ANGLE_WEIGHTS = 1 << np.arange(ANGLE_BITS - 1, -1, -1)  # an angle code's bits, most significant first
_ANGLE_RAD = (np.arange(2**ANGLE_BITS) * (2 * math.pi / 2**ANGLE_BITS)).astype(np.float32)  # code -> radians


@lru_cache(maxsize=4)
def _cell_centres(width: int, height: int, ww: int, wh: int) -> tuple[np.ndarray, np.ndarray]:
    """The coordinate grid's column and row centres in pixels of the described image
    (``width`` x ``height``, described at ``ww`` x ``wh``), ``(grid_w,)`` and ``(grid_h,)
    float32`` (read-only): computed in float64 as the coordinates are defined and rounded
    to float32 once, so that decode looks them up instead of computing every keypoint's."""
    grid_w, grid_h = -(-ww // POSITION_STEP_PX), -(-wh // POSITION_STEP_PX)
    out = []
    for count, scale in ((grid_w, width / ww), (grid_h, height / wh)):
        c = ((np.arange(count) * POSITION_STEP_PX + (POSITION_STEP_PX - 1) / 2 + 0.5) * scale - 0.5).astype(np.float32)
        c.flags.writeable = False
        out.append(c)
    return out[0], out[1]


@lru_cache(maxsize=1)
def _trit_bits() -> np.ndarray:
    """``(2, 256, 5) uint8``: per trit byte (5 base-3 digits, as
    :func:`~robotd.floor.desccoding.pack_trits` packs them), which of its 5 elements are
    +1 (``[0]``) and which are -1 (``[1]``); bytes above 242 are refused before a look-up."""
    digits = trit_table()  # (243, 5): element + 1
    out = np.zeros((2, 256, 5), np.uint8)
    out[0, :243] = digits == 2
    out[1, :243] = digits == 0
    return out


def _bit_planes(trit_bytes: np.ndarray, n: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``(n, ceil(length / 64)) uint64`` bit planes of the +1 and of the -1 elements
    (as :func:`~robotd.floor.desccoding.pack_planes` packs them) straight from the packed
    trit bytes: one table look-up gives both planes' bits, one ``packbits`` packs them
    (every mode's length is a whole number of bytes), without a ternary array between."""
    bits = np.take(_trit_bits(), trit_bytes, axis=1).reshape(2, -1)[:, : n * length]
    packed = np.packbits(bits, axis=1, bitorder="little").reshape(2, n, length // 8)
    words = -(-length // 64)
    if length != 64 * words:
        padded = np.zeros((2, n, 8 * words), np.uint8)
        padded[:, :, : length // 8] = packed
        packed = padded
    planes = packed.view("<u8").astype(np.uint64, copy=False)
    return planes[0], planes[1]


def _parse(data: bytes) -> tuple[Any, ...]:
    """:func:`decode`'s checks of the header, checksum and section lengths; the header's
    fields and the sections as ``uint8`` views of ``data`` (the unary parts: to its end)."""
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
    if pos + sum(sections) > len(data):
        raise _fail("truncated body")
    parts = []
    for s in sections:
        parts.append(np.frombuffer(data, np.uint8, s, pos))
        pos += s
    parts.append(np.frombuffer(data, np.uint8, offset=pos))
    return (mode, width, height, ww, wh, n, k, *parts)


def _positions(width: int, height: int, ww: int, wh: int, n: int, k: int, rem_b: np.ndarray, ang_b: np.ndarray,
               unary_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The keypoints' positions ``(n, 2) float32`` and orientation codes ``(n,)`` from the
    Rice remainders, the angle bits and the Rice unary parts (:func:`decode`'s sections)."""
    # The unary parts: q_i one bits then a zero each, padded with ones to a whole byte.
    zeros = np.flatnonzero(np.unpackbits(~unary_b))
    n_unary = 8 * len(unary_b)
    if len(zeros) != n or (n and n_unary - zeros[-1] - 1 >= 8) or (not n and n_unary):
        raise _fail("bad position code")
    gaps = np.empty(n, np.int64)  # quotients, then the whole gaps
    if n:
        gaps[0] = zeros[0]
        np.subtract(zeros[1:], zeros[:-1] + 1, out=gaps[1:])
    if k:
        gaps <<= k
        gaps += np.unpackbits(rem_b, count=n * k).reshape(n, k) @ (1 << np.arange(k - 1, -1, -1))
    cell_ids = np.cumsum(gaps)
    grid_w, grid_h = -(-ww // POSITION_STEP_PX), -(-wh // POSITION_STEP_PX)
    if n and cell_ids[-1] >= grid_w * grid_h:
        raise _fail("keypoint position outside the image")
    q = np.unpackbits(ang_b, count=n * ANGLE_BITS).reshape(n, ANGLE_BITS) @ _ANGLE_WEIGHTS
    col_x, row_y = _cell_centres(width, height, ww, wh)
    row, col = np.divmod(cell_ids, grid_w)
    xy = np.empty((n, 2), np.float32)
    xy[:, 0], xy[:, 1] = col_x[col], row_y[row]
    return xy, q


def _check_trits(trit_b: np.ndarray, n: int) -> None:
    """Refuse packed trits that are not 5 base-3 digits (a byte above 242)."""
    if n and int(trit_b.max()) > 242:
        raise _fail("bad descriptor code")


def decode(data: bytes) -> FloorDescriptor:
    """Parse :func:`extract`'s bytes. Raises :class:`DescriptorError` for anything else:
    bad magic, unknown version or mode, wrong length, checksum mismatch, bad codes."""
    mode, width, height, ww, wh, n, k, gbits, rem_b, ang_b, trit_b, unary_b = _parse(data)
    xy, q = _positions(width, height, ww, wh, n, k, rem_b, ang_b, unary_b)
    _check_trits(trit_b, n)
    length = MODES[mode].length
    return FloorDescriptor(mode, width, height, xy, _ANGLE_RAD[q], *_bit_planes(trit_b, n, length), length,
                           gbits.copy(), POSITION_STEP_PX * max(width / ww, height / wh))


class PartialDescriptor:
    """A stored descriptor decoded in two steps (:func:`decode_local`, the floor index's
    read back): every check and the header, the global bits and the packed trits at once,
    which is all the local score's descriptor distances and its ``min_score`` bound read
    (:func:`robotd.floor.match.local_score` builds its side of the distance straight from
    the trits); the keypoints' positions and orientations only when :meth:`positions` is
    called, by the geometric check of a pair that passed the bound. Most read-back
    candidates of a query fail the bound: their positions are never decoded, nor their
    bit planes built.

    Attributes: ``mode``, ``width_px``, ``height_px``, ``length``, ``global_bits`` and
    ``position_step_px`` as :class:`FloorDescriptor`'s; ``trits``: ``(ceil(N length / 5),)
    uint8`` the local descriptors' elements as stored, 5 base-3 digits (element + 1) per
    byte, keypoint after keypoint (read-only). :meth:`full` gives the
    :class:`FloorDescriptor` :func:`decode` gives for the same bytes, array for array.
    """

    __slots__ = ("mode", "width_px", "height_px", "length", "global_bits", "position_step_px", "trits", "_n",
                 "_rest", "_positions")

    def __init__(self, data: bytes) -> None:
        mode, width, height, ww, wh, n, k, gbits, rem_b, ang_b, trit_b, unary_b = _parse(data)
        _check_trits(trit_b, n)
        self.mode, self.width_px, self.height_px, self._n = mode, width, height, n
        self.length: int = MODES[mode].length
        self.global_bits: np.ndarray = gbits.copy()
        self.position_step_px = POSITION_STEP_PX * max(width / ww, height / wh)
        self.trits: np.ndarray = trit_b.copy()
        self.trits.flags.writeable = False
        # The positions' sections copied out of ``data`` (a few hundred bytes: the rest is let go).
        self._rest: tuple[Any, ...] | None = (ww, wh, k, rem_b.copy(), ang_b.copy(), unary_b.copy())
        self._positions: tuple[np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return self._n

    @property
    def positions_decoded(self) -> bool:
        """Whether :meth:`positions` has run (they are then kept)."""
        return self._positions is not None

    def positions(self) -> tuple[np.ndarray, np.ndarray]:
        """``(xy_px, angle_rad)`` as :class:`FloorDescriptor`'s (decoded once, then kept and
        the positions' code let go). Raises :class:`DescriptorError` if that code is bad
        (bytes forged with a valid checksum)."""
        if self._positions is None:
            assert self._rest is not None
            ww, wh, k, rem_b, ang_b, unary_b = self._rest
            xy, q = _positions(self.width_px, self.height_px, ww, wh, self._n, k, rem_b, ang_b, unary_b)
            self._positions = (xy, _ANGLE_RAD[q])
            self._rest = None
        return self._positions

    def full(self) -> FloorDescriptor:
        """The whole descriptor, as :func:`decode` gives it (built anew: not kept)."""
        xy, angle = self.positions()
        return FloorDescriptor(self.mode, self.width_px, self.height_px, xy, angle,
                               *_bit_planes(self.trits, self._n, self.length), self.length, self.global_bits,
                               self.position_step_px)

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays: the trits, the global bits, and the positions' code or
        the decoded positions and orientations."""
        held = self.trits.nbytes + self.global_bits.nbytes
        if self._rest is not None:
            held += sum(a.nbytes for a in self._rest[3:])
        if self._positions is not None:
            held += self._positions[0].nbytes + self._positions[1].nbytes
        return int(held)


def decode_local(data: bytes) -> PartialDescriptor:
    """:func:`decode` in two steps (:class:`PartialDescriptor`): every check but the
    positions' code now, the positions when :meth:`~PartialDescriptor.positions` is called.
    Raises :class:`DescriptorError` as :func:`decode` does."""
    return PartialDescriptor(data)


def describe(image: np.ndarray, mode: int, params: ExtractParams | None = None) -> FloorDescriptor:
    """``decode(extract(image, mode, params))``."""
    return decode(extract(image, mode, params))
