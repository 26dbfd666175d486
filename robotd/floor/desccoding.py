"""Step 5 of the floor descriptor and its bit coding (:mod:`robotd.floor.descriptor`):
positions on the coordinate grid as Rice-coded gaps, the byte budget a set of keypoints
needs, trits packed 5 per byte, and the bit planes of decoded ternary descriptors."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from robotd.floor.descparams import ANGLE_BITS, HEADER, POSITION_STEP_PX, ModeSpec

__all__ = ["bits_msb", "cells", "fit", "pack_planes", "pack_trits", "rice_k", "size", "trit_table",
           "unpack_planes"]


def rice_k(gaps: np.ndarray) -> tuple[int, int]:
    """Best Rice parameter for ``gaps`` (non-negative integers) and the unary bit count it
    costs: the smallest ``k`` in 0..16 minimising the unary bits plus ``k`` bits per gap.

    That cost, ``f(k) = sum(gaps >> k) + n (k + 1)``, is convex in ``k`` (its step
    ``n - sum(ceil((g >> k) / 2))`` never decreases), so a walk from the minimum of its
    continuous approximation ``sum(gaps) / 2**k + n k`` finds the first minimum in a few
    evaluations instead of all 17.
    """
    n = len(gaps)
    if n == 0:
        return 0, 0

    def cost(k: int) -> tuple[int, int]:
        u = int(np.add.reduce(np.right_shift(gaps, k), axis=None)) + n
        return u + k * n, u

    total = int(np.add.reduce(gaps, axis=None))
    k = min(16, max(0, round(math.log2(max(math.log(2) * total / n, 1.0)))))
    fk, uk = cost(k)
    moved = False
    while k > 0:  # left while not worse: the first of equal minima
        fl, ul = cost(k - 1)
        if fl > fk:
            break
        k, fk, uk, moved = k - 1, fl, ul, True
    while not moved and k < 16:  # else right while strictly better
        fr, ur = cost(k + 1)
        if fr >= fk:
            break
        k, fk, uk = k + 1, fr, ur
    return k, uk


def cells(xy: np.ndarray, grid_w: int, grid_h: int) -> np.ndarray:
    """``(n,) int64`` row-major index of each position's cell on the ``POSITION_STEP_PX``
    grid of ``grid_w x grid_h`` cells (clipped to it)."""
    # floor((x + 0.5) / 2) by a product: dividing by a power of two is exact, so this is
    # the floor division's value at a fraction of its cost.
    s = np.add(xy, 0.5, dtype=np.result_type(xy.dtype, np.float32))
    s *= 1.0 / POSITION_STEP_PX
    np.floor(s, out=s)
    rc = s.astype(np.int64)
    col = np.clip(rc[:, 0], 0, grid_w - 1)
    row = np.clip(rc[:, 1], 0, grid_h - 1)
    return row * grid_w + col


def size(spec: ModeSpec, cells_sorted: np.ndarray) -> int:
    n = len(cells_sorted)
    gaps = np.empty_like(cells_sorted)
    if n:
        gaps[0] = cells_sorted[0]
        np.subtract(cells_sorted[1:], cells_sorted[:-1], out=gaps[1:])
    k, unary = rice_k(gaps)
    return (HEADER.size + spec.global_bits // 8 + -(-n * k // 8) + -(-n * ANGLE_BITS // 8)
            + -(-n * spec.length // 5) + -(-unary // 8))


def fit(spec: ModeSpec, cells: np.ndarray, hint: int | None = None) -> int:
    """Largest prefix of ``cells`` (relevance order) whose encoding fits ``spec.bytes``.

    The size grows strictly with every keypoint added, so a search is exact: from
    ``hint`` (default: the count an average keypoint's bytes would give) it gallops to a
    bracket, then halves it.
    """
    top = min(len(cells), 65535)

    def ok(m: int) -> bool:
        return size(spec, np.sort(cells[:m])) <= spec.bytes

    if hint is None:
        hint = int((spec.bytes - HEADER.size - spec.global_bits // 8) * 8 / (1.6 * spec.length + ANGLE_BITS + 11))
    h = min(max(hint, 0), top)
    step = 4
    if ok(h):  # answer in [h, top]
        lo, hi = h, top
        while lo < top:
            probe = min(top, lo + step)
            if not ok(probe):
                hi = probe - 1
                break
            lo = probe
            step *= 2
    else:  # answer in [0, h - 1]
        lo, hi = 0, h - 1
        while hi > 0:
            probe = max(0, hi - step + 1)
            if ok(probe):
                lo = probe
                break
            hi = probe - 1
            step *= 2
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if ok(mid):
            lo = mid
        else:
            hi = mid - 1
    return lo


def pack_trits(t: np.ndarray) -> bytes:
    """``(m,)`` values in {0, 1, 2} -> ceil(m / 5) bytes, 5 base-3 digits per byte."""
    pad = (-len(t)) % 5
    d = np.concatenate([t.astype(np.uint8), np.zeros(pad, np.uint8)]).reshape(-1, 5)
    return (d @ np.array([1, 3, 9, 27, 81], np.uint8)).astype(np.uint8).tobytes()


@lru_cache(maxsize=1)
def trit_table() -> np.ndarray:
    v = np.arange(243)
    return np.stack([(v // 3**i) % 3 for i in range(5)], axis=1).astype(np.int8)


def bits_msb(values: np.ndarray, width: int) -> np.ndarray:
    """``(n,)`` ints -> ``(n * width,)`` bits, most significant first."""
    if width == 0:
        return np.zeros(0, np.uint8)
    return ((values[:, None] >> np.arange(width - 1, -1, -1)) & 1).astype(np.uint8).ravel()


def pack_planes(bits: np.ndarray) -> np.ndarray:
    """``(n, L) bool`` -> ``(n, ceil(L / 64)) uint64``, element j at word j // 64, bit j % 64."""
    n, length = bits.shape
    w = -(-length // 64)
    padded = np.zeros((n, w * 64), np.uint8)
    padded[:, :length] = bits
    return np.packbits(padded, axis=1, bitorder="little").view("<u8").astype(np.uint64)


def unpack_planes(planes: np.ndarray, length: int) -> np.ndarray:
    b = np.unpackbits(np.ascontiguousarray(planes).astype("<u8").view(np.uint8), axis=1, bitorder="little")
    return b[:, :length].astype(np.float32)
