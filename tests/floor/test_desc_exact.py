"""The floor descriptor's cheaper steps give the same values as the arithmetic they replace.

Each faster formulation in extraction (the Rice parameter's search, the Hadamard butterflies,
the grid cells, the raw descriptors' turning matrices) is held here to the straightforward
formulation, value for value, so the descriptor's bytes do not move with it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.floor.compression import hadamard_bits
from robotd.floor.desccoding import cells, rice_k
from robotd.floor.keypoints import _LEVEL_SHIFTS, _SHIFTS, _level_table, _split_table, _turns


def _rice_k_all(gaps: np.ndarray) -> tuple[int, int]:
    """Every Rice parameter 0..16 tried: the first with the fewest bits."""
    if len(gaps) == 0:
        return 0, 0
    ks = np.arange(17)
    unary = (gaps[None, :] >> ks[:, None]).sum(1) + len(gaps)
    k = int(np.argmin(unary + ks * len(gaps)))
    return k, int(unary[k])


def test_rice_k_is_the_first_best_of_all_seventeen() -> None:
    rng = np.random.default_rng(5)
    cases = [np.zeros(0, np.int64), np.zeros(7, np.int64), np.array([0], np.int64), np.array([2**40], np.int64),
             np.full(3, 2**17, np.int64), np.array([1, 1, 2, 2], np.int64)]
    for t in range(3000):
        n = int(rng.integers(1, 400))
        kind = t % 4
        if kind == 0:
            g = rng.integers(0, 76800, n)
        elif kind == 1:  # gaps of sorted grid cells, as the coder sees them
            g = np.diff(np.sort(rng.choice(76800, n, replace=False)), prepend=0)
        elif kind == 2:  # ties between neighbouring k are common with tiny gaps
            g = rng.integers(0, 4, n)
        else:
            g = rng.exponential(2.0 ** rng.uniform(0, 18), n)
        cases.append(np.asarray(g, np.int64))
    for g in cases:
        assert rice_k(g) == _rice_k_all(g), g


def _hadamard_full(vec: np.ndarray, signs: np.ndarray, bits: int) -> np.ndarray:
    """Every butterfly of every stage on the whole vector."""
    h = vec * signs
    step = len(h) // 2
    while step >= 1:
        h = h.reshape(-1, 2, step)
        h = np.stack([h[:, 0] + h[:, 1], h[:, 0] - h[:, 1]], axis=1)
        step //= 2
    return np.packbits(h.ravel()[:bits] > 0)


@pytest.mark.parametrize("bits", [8, 24, 256, 512, 1024])
def test_hadamard_bits_equal_the_full_butterflies_and_the_matrix(bits: int) -> None:
    rng = np.random.default_rng(bits)
    n = 1024
    sylvester = np.ones((1, 1))
    while len(sylvester) < n:
        sylvester = np.block([[sylvester, sylvester], [sylvester, -sylvester]])
    for t in range(40):
        v = rng.normal(size=n).astype(np.float32)
        if t % 3 == 0:
            v[rng.random(n) < 0.5] = 0
        s = rng.choice([-1.0, 1.0], n).astype(np.float32)
        got = hadamard_bits(v, s, bits)
        assert np.array_equal(got, _hadamard_full(v, s, bits))
        exact = sylvester[:bits] @ (v.astype(np.float64) * s)
        clear = np.abs(exact) > 1e-4 * np.linalg.norm(v)  # rounding decides only signs of near-zero values
        assert np.array_equal(np.unpackbits(got)[:bits][clear], (exact > 0)[clear])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_cells_equal_the_floor_division(dtype: type) -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        xy = (rng.random((500, 2)) * 700 - 30).astype(dtype)
        xy[:50] = np.round(xy[:50] * 2) / 2  # on the cell boundaries (x + 0.5 even)
        xy[50:60] = np.nextafter(xy[50:60], np.inf)
        xy[60:70] = np.nextafter(xy[:10], -np.inf)
        xy[70:80] = -0.5
        col = np.clip(((xy[:, 0] + 0.5) // 2).astype(np.int64), 0, 319)
        row = np.clip(((xy[:, 1] + 0.5) // 2).astype(np.int64), 0, 239)
        assert np.array_equal(cells(xy, 320, 240), row * 320 + col)


def test_turning_matrices_are_the_blend_of_two_shifts_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    ang = (rng.random(2000) * 2 * math.pi).astype(np.float32)
    ang[:16] = np.arange(16, dtype=np.float32) * np.float32(math.pi / 8)  # whole and half bins: f = 0
    ang[16] = np.float32(2 * math.pi)  # a = 8.0 wraps to bin 0
    a = ang * np.float32(8 / (2 * math.pi))
    a0 = a.astype(np.intp) & 7
    f = (a - np.floor(a))[:, None, None]
    blend = _SHIFTS[a0] * (1 - f)
    blend += _SHIFTS[a0 + 1] * f
    got = _turns(ang)
    assert got.view(np.uint32).tolist() == blend.view(np.uint32).tolist()  # signs of zeros included
    buf = np.full((len(ang), 8, 8), 7.0, np.float32)
    assert _turns(ang, buf) is buf and np.array_equal(buf, blend)


def test_one_level_table_serves_every_direction() -> None:
    """The pooled maps look every direction's share up in direction 0's table at the level
    shifted by 32 per direction (mod 256): the same values as a table per direction."""
    split = _split_table()
    table = _level_table()
    q = np.arange(256)
    for d in range(8):
        shifted = (q + _LEVEL_SHIFTS[d].astype(np.int64)) % 256
        assert np.array_equal(table[shifted], split[d // 4][q, 0, d % 4]), d
