"""Step 5 of the floor descriptor and its bit coding (:mod:`robotd.floor.descriptor`):
positions on the coordinate grid as Rice-coded gaps, the byte budget a set of keypoints
needs, trits packed 5 per byte, and the bit planes of decoded ternary descriptors."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from robotd.floor.descparams import ANGLE_BITS, HEADER, POSITION_STEP_PX, ModeSpec

__all__ = ["bits_msb", "cells", "fit", "pack_planes", "pack_trits", "rice_k", "size", "trit_table",
           "unpack_planes"]


def rice_k(gaps: np.ndarray) -> tuple[int, int]:
    """Best Rice parameter for ``gaps`` and the unary bit count it costs."""
    if len(gaps) == 0:
        return 0, 0
    ks = np.arange(17)
    unary = (gaps[None, :] >> ks[:, None]).sum(1) + len(gaps)
    k = int(np.argmin(unary + ks * len(gaps)))
    return k, int(unary[k])


def cells(xy: np.ndarray, grid_w: int, grid_h: int) -> np.ndarray:
    col = np.clip(((xy[:, 0] + 0.5) // POSITION_STEP_PX).astype(np.int64), 0, grid_w - 1)
    row = np.clip(((xy[:, 1] + 0.5) // POSITION_STEP_PX).astype(np.int64), 0, grid_h - 1)
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
