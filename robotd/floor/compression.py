"""Steps 4 and 6 of the floor descriptor (:mod:`robotd.floor.descriptor`): the raw local
descriptors' fixed transform and ternary quantisation, and the global descriptor."""

from __future__ import annotations

import numpy as np

from robotd.floor.descparams import N_ELEMENTS, Learned

__all__ = ["global_vector", "hadamard_bits", "ternarise", "transform"]


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
    return np.asarray(raw @ _TRANSFORM.T)


def ternarise(raw: np.ndarray, learned: Learned, length: int) -> np.ndarray:
    """Steps 4a-b: the first ``length`` transformed elements in priority order as
    ``(n, length) int8`` trits."""
    o = learned.order[:length]
    e = raw @ _TRANSFORM[o].T
    return np.asarray((e > learned.tern_hi[o]).view(np.int8) - (e < learned.tern_lo[o]).view(np.int8))


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
    return np.asarray(out.ravel())


def hadamard_bits(vec: np.ndarray, signs: np.ndarray, bits: int) -> np.ndarray:
    """Signs of the first ``bits`` rows of the Walsh-Hadamard transform of ``signs * vec``."""
    h = vec * signs
    other = np.empty_like(h)
    step = len(h) // 2
    while step >= 1:  # fast Walsh-Hadamard transform, one vectorised butterfly per stage
        # Output j of a stage reads only its own block of 2 step inputs: once those blocks
        # cover the first ``bits``, the rest is never read again.
        m = min(len(h), -(-bits // (2 * step)) * 2 * step)
        a, o = h[:m].reshape(-1, 2, step), other[:m].reshape(-1, 2, step)
        np.add(a[:, 0], a[:, 1], out=o[:, 0])
        np.subtract(a[:, 0], a[:, 1], out=o[:, 1])
        h, other = other, h
        step //= 2
    return np.packbits(h[:bits] > 0)
