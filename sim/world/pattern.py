"""Regular printed floors: planks or tiles whose few prints repeat all over the floor.

Paper 003 names printed wood the hardest floor for loop detection: laminate is a photo
printed on planks, and the same few prints recur every few planks, so distant places look
alike (perceptual aliasing). This floor reproduces that on purpose: ``prints`` crops of a
real photograph are laid on a regular grid of planks (staggered rows) or square tiles
with dark joints, the print of each plank chosen by a hash of its grid index. The prints
are disjoint crops, so two prints never share content. Ground truth
never comes from the image, so the detector must survive the repeats.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from robotd.base.errors import ConfigError


@dataclass(frozen=True)
class PatternParams:
    """Geometry of the pattern, metres. ``kind``: ``"planks"`` (rows of ``length_m`` x
    ``width_m`` planks, each row shifted by ``stagger`` of a plank) or ``"tiles"``
    (``width_m`` squares); ``joint_m``: width of the dark joints; ``prints``: how many
    distinct prints are cut from the photo and repeated."""

    kind: str = "planks"
    length_m: float = 0.45
    width_m: float = 0.12
    stagger: float = 1.0 / 3.0
    joint_m: float = 0.002
    joint_level: int = 45
    prints: int = 4

    def __post_init__(self) -> None:
        if self.kind not in ("planks", "tiles"):
            raise ConfigError(f"pattern kind must be 'planks' or 'tiles', not {self.kind!r}")
        if not (self.width_m > 0 and self.length_m > 0 and 0 <= self.joint_m < self.width_m / 2):
            raise ConfigError("pattern sizes must be positive and the joint narrower than half a plank")
        if self.prints < 1:
            raise ConfigError("pattern prints must be >= 1")


def _print_index(col: np.ndarray, row: np.ndarray, seed: int, prints: int) -> np.ndarray:
    """Which print a plank at grid index ``(col, row)`` gets: a well-mixed hash (the
    splitmix64 finaliser) modulo ``prints``, so the choice has no period. (Multiplying by
    odd constants and XOR-ing, then taking the value modulo a power of two, keeps only the
    low bits of ``col`` and ``row``: with 4 prints that floor repeats exactly every 4 planks
    and 4 rows, which makes every view appear again a couple of metres away.)"""
    with np.errstate(over="ignore"):
        z = (col.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             + row.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
             + np.uint64(seed & 0xFFFFFFFF) * np.uint64(0x165667B19E3779F9))
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z % np.uint64(prints)).astype(np.int64)


class PatternFloor:
    """A printed plank or tile floor (see the module docstring); a ``FloorSource``."""

    def __init__(self, photo: np.ndarray, params: PatternParams = PatternParams(),
                 metres_per_px: float = 0.001, seed: int = 0) -> None:
        grey = photo if photo.ndim == 2 else cv2.cvtColor(photo, cv2.COLOR_BGR2GRAY)
        self.params = params
        self._mpp = float(metres_per_px)
        self.seed = int(seed)
        p = params
        self._cell_m = (p.width_m, p.width_m) if p.kind == "tiles" else (p.length_m, p.width_m)
        cw = int(math.ceil(self._cell_m[0] / self._mpp))
        ch = int(math.ceil(self._cell_m[1] / self._mpp))
        # The prints are disjoint crops of the photo, like the distinct photos a laminate
        # maker prints: crops that overlapped would share their content at a shift, and the
        # floor would alias more than its print count says (with 0.45 m planks cut at random
        # from a 512 px photo, two of four prints once shared 78 % of their pixels).
        h, w = grey.shape
        scale = 1.0
        while (int(h * scale) // ch) * (int(w * scale) // cw) < p.prints:
            scale *= 1.05  # a photo too small for that many crops: stretch it (still real detail)
        if scale > 1.0:
            grey = cv2.resize(grey, (int(w * scale), int(h * scale)), interpolation=cv2.INTER_CUBIC)
            h, w = grey.shape
        rng = np.random.default_rng(seed)
        rows, cols = h // ch, w // cw
        y0 = int(rng.integers(0, h - rows * ch + 1))
        x0 = int(rng.integers(0, w - cols * cw + 1))
        slots = rng.choice(rows * cols, size=p.prints, replace=False)
        #: ``(prints, 4)`` crop boxes ``(y, x, height, width)`` in the (possibly stretched) photo.
        self.crop_boxes = np.array([(y0 + (k // cols) * ch, x0 + (k % cols) * cw, ch, cw) for k in slots])
        crops = [grey[y:y + hh, x:x + ww] for y, x, hh, ww in self.crop_boxes]
        self._prints = np.stack(crops).astype(np.uint8)  # (K, ch, cw)

    @property
    def metres_per_px(self) -> float:
        return self._mpp

    def _sample(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Grey level at world points (arrays of any shape)."""
        p = self.params
        cl, cw = self._cell_m
        row = np.floor(y_m / cw).astype(np.int64)
        shift = (row * p.stagger % 1.0) * cl if p.kind == "planks" else 0.0
        xs = x_m - shift
        col = np.floor(xs / cl).astype(np.int64)
        u = xs - col * cl          # metres along the plank, [0, cl)
        v = y_m - row * cw         # metres across, [0, cw)
        k = _print_index(col, row, self.seed, p.prints)
        ci = np.clip((u / self._mpp).astype(np.int64), 0, self._prints.shape[2] - 1)
        ri = np.clip(((cw - v) / self._mpp).astype(np.int64), 0, self._prints.shape[1] - 1)
        out = self._prints[k, ri, ci]
        j = p.joint_m / 2
        joint = (u < j) | (u > cl - j) | (v < j) | (v > cw - j)
        return np.where(joint, np.uint8(p.joint_level), out)

    def patch(self, x0_m: float, y0_m: float, x1_m: float, y1_m: float) -> tuple[np.ndarray, np.ndarray]:
        """See :class:`sim.world.floor.FloorSource`: pixels on the floor's own grid."""
        mpp = self._mpp
        col0 = math.floor(min(x0_m, x1_m) / mpp)
        col1 = math.ceil(max(x0_m, x1_m) / mpp)
        row0 = math.floor(-max(y0_m, y1_m) / mpp)
        row1 = math.ceil(-min(y0_m, y1_m) / mpp)
        xs = (np.arange(col0, col1 + 1) + 0.5) * mpp
        ys = -(np.arange(row0, row1 + 1) + 0.5) * mpp
        img = self._sample(xs[None, :], ys[:, None])
        affine = np.array([[1.0 / mpp, 0.0, -0.5 - col0], [0.0, -1.0 / mpp, -0.5 - row0]])
        return np.ascontiguousarray(img), affine

    def render_overview(self, x0_m: float, y0_m: float, x1_m: float, y1_m: float,
                        px_per_m: float) -> np.ndarray:
        """North-up picture of the floor, ``(H, W) uint8``, each pixel the mean of up to
        4 x 4 samples so a coarse picture does not alias."""
        xa, xb = sorted((x0_m, x1_m))
        ya, yb = sorted((y0_m, y1_m))
        w = max(int(round((xb - xa) * px_per_m)), 1)
        h = max(int(round((yb - ya) * px_per_m)), 1)
        n = int(min(4, max(1, math.ceil(1.0 / (px_per_m * self._mpp)))))
        sub = (np.arange(n) + 0.5) / (n * px_per_m)
        acc = np.zeros((h, w), np.float32)
        for dy in sub:
            ys = yb - np.arange(h) / px_per_m - dy
            for dx in sub:
                xs = xa + np.arange(w) / px_per_m + dx
                acc += self._sample(xs[None, :], ys[:, None])
        return np.clip(np.rint(acc / (n * n)), 0, 255).astype(np.uint8)
