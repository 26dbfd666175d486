"""The virtual robot's floor: unbounded, made lazily from real photographs, never tiled.

Why this design (DESIGN.md, "The virtual robot", floor resolution): real floor photos
are 512 to 2048 px across, a driven floor is 10 x 10 m, and the floor camera needs
about one texture pixel per image pixel (1 mm at the default camera). Upsampling one
photo blurs it, tiling it repeats places the ground truth calls different. So the floor
is synthesised the way image quilting does it (Efros and Freeman 2001, Sec. 2): from
many blocks cut out of the photos, each at its native pixel scale (or within +-15 %),
randomly placed, rotated by any angle and mirrored, and joined along irregular seams.

Layout
------
* The plane is cut into *regions* about ``region_size_m`` across (a jittered grid whose
  cell borders wobble, so borders are irregular curves); each region uses one source
  photo (with a single photo, all regions use it).
* Within a region, *blocks* sit on a jittered grid of spacing ``block_px`` floor pixels.
  A block is a disc cut from its region's photo at a random place, rotation, mirror and
  mild scale. Block ``(i, j)``'s parameters come from a hash of ``(seed, i, j)`` only, so
  any part of the floor can be generated in any order and is always the same.
* Seams: every floor point belongs to the block with the highest score,
  ``seam(block content) - falloff * (distance to block centre / spacing)^2``, where the
  seam term is a fixed random field attached to the *photo* (a smoothed copy of the photo's
  own brightness plus smooth noise): it is different for every block because every
  block cuts a different, rotated piece of it. Seams thus follow the texture (bright
  stones, bricks and leaves tend to stay whole) and wander, instead of running straight.
  The hand-over between blocks is a softmax over the scores that is only a couple of
  pixels wide: no wide averaging that would wash the texture out. This replaces the
  paper's minimum-error boundary cut (Sec. 2.1), which needs neighbouring blocks in a
  fixed generation order; here no block depends on another.

Generated pixels are cut into square tiles (``tile_px``), made on demand and kept in a
bounded LRU cache. Ground truth never comes from image content: where two places look
alike it is perceptual aliasing, but no view-sized region is an exact copy of another.

Pixel convention: floor pixel ``(col, row)`` has its centre at world
``(x, y) = (col * metres_per_px, -row * metres_per_px)``: columns run east (+x), rows
run south (-y), so an image of the floor has north up.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Protocol, Sequence

import cv2
import numpy as np

from robotd.base.errors import ConfigError

logger = logging.getLogger(__name__)

__all__ = ["Floor", "FloorParams", "FloorSource", "ImageFloor", "load_floor_photo"]


class FloorSource(Protocol):
    """Anything the floor camera can look at: floor pixels covering a world rectangle."""

    @property
    def metres_per_px(self) -> float:
        """Size of one floor pixel, metres."""
        ...

    def patch(self, x0_m: float, y0_m: float, x1_m: float, y1_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Floor pixels covering ``[x0_m, x1_m] x [y0_m, y1_m]`` and their ``(2, 3)`` affine.

        The affine maps world metres ``(x, y, 1)`` to ``(col, row)`` pixel coordinates of
        the returned ``(H, W) uint8`` image (pixel centres at integers).
        """
        ...


@dataclass(frozen=True)
class FloorParams:
    """How the floor is assembled from photos. Defaults give a believable 1 mm/px floor.

    Fields:
        metres_per_px: size of one photo pixel on the floor, metres (default 1 mm).
        seed: the floor's identity; same seed and photos -> same floor everywhere.
        region_size_m: side of the regions that each use one photo, metres.
        region_wobble_m: amplitude of the wobble of region borders, metres.
        block_px: spacing of quilting blocks, floor pixels. Blocks must fit in the photos
            (a block disc is ``2 * block_support * block_px`` px across); reduced
            automatically for small photos.
        block_jitter: random offset of block centres, as a fraction of ``block_px`` (< 0.5).
        block_support: radius of a block's disc, in units of ``block_px`` (must cover the
            jittered grid: > sqrt(2) * (0.5 + block_jitter)).
        scale_range: (min, max) scale of a block's photo content; 1 = native pixels.
        seam_falloff: weight of the squared distance to the block centre in the seam score.
        seam_content: weight of the photo's own smoothed brightness in the seam score.
        seam_content_sigma_px: smoothing of that brightness, photo pixels; it must exceed
            the width of thin bright lines (mortar, blades) or they grow into spikes.
        seam_noise: weight of smooth random noise in the seam score.
        seam_noise_sigma_px: correlation length of that noise, photo pixels.
        seam_sharpness: softmax inverse temperature; higher = narrower hand-over.
        flatten_illumination: fraction (0..1) of each photo's slow brightness gradient
            removed before use, so block borders do not show lighting steps.
        target_mean, target_std: grey level mean and contrast each photo is pulled towards.
        contrast_pull: 0 keeps each photo's contrast, 1 forces ``target_std``; in between
            is the geometric blend (mild normalisation).
        tile_px: side of a cached tile, floor pixels.
        cache_mb: upper bound of the tile cache, MiB.
    """

    metres_per_px: float = 0.001
    seed: int = 0
    region_size_m: float = 3.0
    region_wobble_m: float = 0.6
    block_px: int = 128
    block_jitter: float = 0.3
    block_support: float = 1.25
    scale_range: tuple[float, float] = (0.87, 1.15)
    seam_falloff: float = 4.0
    seam_content: float = 0.3
    seam_content_sigma_px: float = 5.0
    seam_noise: float = 0.6
    seam_noise_sigma_px: float = 10.0
    seam_sharpness: float = 12.0
    flatten_illumination: float = 0.8
    target_mean: float = 118.0
    target_std: float = 36.0
    contrast_pull: float = 0.5
    tile_px: int = 256
    cache_mb: float = 128.0

    def __post_init__(self) -> None:
        checks = [
            ("metres_per_px", self.metres_per_px > 0 and math.isfinite(self.metres_per_px)),
            ("region_size_m", self.region_size_m > 0),
            ("region_wobble_m", self.region_wobble_m >= 0),
            ("block_px", self.block_px >= 8),
            ("block_jitter", 0 <= self.block_jitter < 0.5),
            ("block_support", self.block_support > math.sqrt(2.0) * (0.5 + self.block_jitter)),
            ("scale_range", 0 < self.scale_range[0] <= self.scale_range[1]),
            ("seam_sharpness", self.seam_sharpness > 0),
            ("flatten_illumination", 0 <= self.flatten_illumination <= 1),
            ("contrast_pull", 0 <= self.contrast_pull <= 1),
            ("tile_px", self.tile_px >= 16),
            ("cache_mb", self.cache_mb > 0),
        ]
        for name, ok in checks:
            if not ok:
                raise ConfigError(f"floor parameter {name} out of range: {getattr(self, name)!r}")


# ---------------------------------------------------------------------- hashing


def _splitmix(z: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on a uint64 array (wrapping arithmetic)."""
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _hash_u01(seed: int, i: np.ndarray, j: np.ndarray, stream: int) -> np.ndarray:
    """Uniform [0, 1) numbers that depend only on ``(seed, i, j, stream)``; vectorised."""
    i64 = np.atleast_1d(np.asarray(i, dtype=np.int64)).view(np.uint64)
    j64 = np.atleast_1d(np.asarray(j, dtype=np.int64)).view(np.uint64)
    h = _splitmix(np.full(i64.shape, (seed * 0x632BE59BD9B4E019 + stream) & 0xFFFFFFFFFFFFFFFF, dtype=np.uint64))
    h = _splitmix(h ^ i64)
    h = _splitmix(h ^ (j64 * np.uint64(0xD6E8FEB86659FD93)))
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def _value_noise(seed: int, stream: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth noise in [-1, 1] on a unit lattice (smoothstep-interpolated hashes).

    ``stream`` (int array broadcast with ``x``) selects independent noise functions.
    """
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    sx = fx * fx * (3.0 - 2.0 * fx)
    sy = fy * fy * (3.0 - 2.0 * fy)
    xi = x0.astype(np.int64)
    yi = y0.astype(np.int64)
    # Fold the stream into the lattice index so each stream is its own function.
    key = np.broadcast_to(stream, xi.shape).astype(np.int64) * 1_000_003

    def h(dx: int, dy: int) -> np.ndarray:
        return _hash_u01(seed, xi + dx + key, yi + dy, 7) * 2.0 - 1.0

    top = h(0, 0) * (1 - sx) + h(1, 0) * sx
    bottom = h(0, 1) * (1 - sx) + h(1, 1) * sx
    return top * (1 - sy) + bottom * sy


# ---------------------------------------------------------------------- sources


def load_floor_photo(path: str | os.PathLike[str]) -> np.ndarray:
    """Read an image file as ``(H, W) uint8`` grey; colour is converted to grey.

    Raises :class:`~robotd.base.errors.ConfigError` naming the file when it cannot be read.
    """
    name = os.fspath(path)
    img = cv2.imread(name, cv2.IMREAD_GRAYSCALE) if os.path.isfile(name) else None
    if img is None or img.size == 0:
        raise ConfigError(f"cannot read floor image {name!r} (missing, unreadable or not an image)")
    return img


def _as_grey_u8(image: np.ndarray, name: str) -> np.ndarray:
    """Arrays: grey as is, colour taken as RGB(A) (numpy / scikit-image order)."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        if a.dtype != np.uint8:
            a = _to_u8(a, name)
        a = cv2.cvtColor(np.ascontiguousarray(a[:, :, :3]), cv2.COLOR_RGB2GRAY)
    if a.ndim != 2:
        raise ConfigError(f"floor image {name} must be 2-D grey or RGB, got shape {a.shape}")
    return _to_u8(a, name)


def _to_u8(a: np.ndarray, name: str) -> np.ndarray:
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"floor image {name} has non-finite values")
    if np.issubdtype(a.dtype, np.floating) and a.max(initial=0) <= 1.0:
        a = a * 255.0
    elif a.dtype == np.uint16:
        a = a / 257.0
    return np.clip(np.rint(a), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class _Source:
    """One photo prepared for quilting: a pyramid of (value, seam score) float32 images."""

    name: str
    pyramid: tuple[np.ndarray, ...]  # level L: (H / 2^L, W / 2^L, 2) float32

    @property
    def size(self) -> tuple[int, int]:
        h, w = self.pyramid[0].shape[:2]
        return w, h


def _prepare_source(grey: np.ndarray, name: str, params: FloorParams, seed: int) -> _Source:
    v = grey.astype(np.float32)
    h, w = v.shape
    # Slow illumination (photos are rarely evenly lit) would show as brightness steps at
    # block borders once pieces are rotated and moved: remove most of it.
    sigma_low = max(h, w) / 8.0
    low = cv2.GaussianBlur(v, (0, 0), sigma_low, borderType=cv2.BORDER_REFLECT)
    v = v - params.flatten_illumination * (low - float(low.mean()))
    # Mild mean/contrast normalisation so regions of different photos are comparable.
    std = float(v.std()) or 1.0
    gain = (params.target_std / std) ** params.contrast_pull
    v = params.target_mean + (v - float(v.mean())) * gain
    v = np.clip(v, 0.0, 255.0)
    # Seam score attached to the photo (see the module docstring).
    content = cv2.GaussianBlur(v, (0, 0), params.seam_content_sigma_px)
    content = (content - float(content.mean())) / (float(content.std()) or 1.0)
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5EA3])
    noise: np.ndarray = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0),
                                         params.seam_noise_sigma_px)
    noise /= float(noise.std()) or 1.0
    seam = params.seam_content * np.clip(content, -2.5, 2.5) + params.seam_noise * noise
    stack = np.dstack([v, seam]).astype(np.float32)
    levels: list[np.ndarray] = [stack]
    while min(levels[-1].shape[:2]) >= 16:
        levels.append(cv2.pyrDown(levels[-1]))
    for lv in levels:
        lv.setflags(write=False)
    return _Source(name=name, pyramid=tuple(levels))


def _default_photos() -> list[tuple[str, np.ndarray]]:
    import skimage.data  # real texture photographs shipped in the scikit-image wheel

    return [(f"skimage:{n}", getattr(skimage.data, n)()) for n in ("brick", "grass", "gravel")]


# ------------------------------------------------------------------------ floor


@dataclass(frozen=True)
class _Blocks:
    """Parameters of a set of quilting blocks (all arrays ``(K,)``)."""

    cx_m: np.ndarray
    cy_m: np.ndarray
    source: np.ndarray  # int index into the floor's sources
    to_src: np.ndarray  # (K, 2, 2): world offset (m) -> source pixel offset (level 0)
    src_cx: np.ndarray  # source pixel coordinates of the block centre (level 0)
    src_cy: np.ndarray


class Floor:
    """An unbounded floor quilted from real photographs, generated tile by tile on demand.

    Build with :meth:`default` (the scikit-image texture photos) or :meth:`from_photos`.
    Tile lookups may come from several threads: the cache is locked, and two threads
    that miss the same tile both generate it, with identical results.
    """

    def __init__(self, sources: Sequence[tuple[str, np.ndarray]], params: FloorParams) -> None:
        if not sources:
            raise ConfigError("a floor needs at least one photo")
        self.params = params
        grey = [(name, _as_grey_u8(img, name)) for name, img in sources]
        smallest = min(min(g.shape) for _, g in grey)
        # A block disc must fit inside every photo at the largest scale.
        fit_px = (smallest - 4) / (2.0 * params.block_support * params.scale_range[1])
        self.block_px = int(min(params.block_px, math.floor(fit_px)))
        if self.block_px < 8:
            raise ConfigError(
                f"floor photo too small ({smallest} px): need at least "
                f"{int(math.ceil(16 * params.block_support * params.scale_range[1] + 4))} px per side"
            )
        if self.block_px < params.block_px:
            logger.info("floor blocks reduced to %d px to fit a %d px photo", self.block_px, smallest)
        self._sources = [
            _prepare_source(g, name, params, params.seed * 1000 + k) for k, (name, g) in enumerate(grey)
        ]
        self._tiles: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._cache_bytes = 0
        self._lock = threading.Lock()
        self.tiles_generated = 0

    # ------------------------------------------------------------- builders

    @classmethod
    def from_photos(
        cls,
        photos: Sequence[str | os.PathLike[str] | np.ndarray],
        metres_per_px: float = 0.001,
        seed: int = 0,
        region_size_m: float = 3.0,
        **params: object,
    ) -> Floor:
        """A floor made from image files and/or arrays.

        ``photos``: paths (read as grey) or arrays (grey, or RGB converted to grey).
        Further keyword arguments set :class:`FloorParams` fields. Unreadable files raise
        :class:`~robotd.base.errors.ConfigError` naming the file.
        """
        if isinstance(photos, (str, os.PathLike, np.ndarray)):
            photos = [photos]
        sources = []
        for k, p in enumerate(photos):
            if isinstance(p, np.ndarray):
                sources.append((f"array{k}", p))
            else:
                sources.append((os.fspath(p), load_floor_photo(p)))
        fp = FloorParams(
            metres_per_px=metres_per_px, seed=seed, region_size_m=region_size_m, **params  # type: ignore[arg-type]
        )
        return cls(sources, fp)

    @classmethod
    def default(cls, seed: int = 0, metres_per_px: float = 0.001, **params: object) -> Floor:
        """Distinct patches of brick, grass and gravel (scikit-image's real photos)."""
        fp = FloorParams(metres_per_px=metres_per_px, seed=seed, **params)  # type: ignore[arg-type]
        return cls(_default_photos(), fp)

    # ------------------------------------------------------------ properties

    @property
    def metres_per_px(self) -> float:
        """Size of one floor pixel, metres."""
        return self.params.metres_per_px

    @property
    def source_names(self) -> list[str]:
        """Names of the photos the floor is made of (file paths or ``skimage:<name>``)."""
        return [s.name for s in self._sources]

    @property
    def cache_bytes(self) -> int:
        """Bytes currently held by the tile cache."""
        return self._cache_bytes

    def cached_tiles(self) -> list[tuple[int, int]]:
        """Indices ``(tx, ty)`` of the tiles in the cache, least recently used first."""
        with self._lock:
            return list(self._tiles.keys())

    def clear_cache(self) -> None:
        """Drop every cached tile (the floor itself does not change)."""
        with self._lock:
            self._tiles.clear()
            self._cache_bytes = 0

    # --------------------------------------------------------------- layout

    def region_source_at(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Index of the photo used at world points (same shape as ``x_m``)."""
        x = np.asarray(x_m, dtype=np.float64)
        y = np.asarray(y_m, dtype=np.float64)
        n = len(self._sources)
        if n == 1:
            return np.zeros(x.shape, dtype=np.int64)
        p = self.params
        rs = p.region_size_m
        gi = np.floor(x / rs).astype(np.int64)
        gj = np.floor(y / rs).astype(np.int64)
        best = np.full(x.shape, np.inf)
        best_src = np.zeros(x.shape, dtype=np.int64)
        wob_scale = 1.0 / max(0.25 * rs, 1e-9)  # wobble wavelength ~ a quarter region
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                ci, cj = gi + di, gj + dj
                jx = _hash_u01(p.seed, ci, cj, 101).reshape(x.shape) - 0.5
                jy = _hash_u01(p.seed, ci, cj, 102).reshape(x.shape) - 0.5
                rcx = (ci + 0.5 + 0.7 * jx) * rs
                rcy = (cj + 0.5 + 0.7 * jy) * rs
                stream = (ci * 7919 + cj) % 100_000
                wob = _value_noise(p.seed, stream, x * wob_scale, y * wob_scale)
                d = np.hypot(x - rcx, y - rcy) + p.region_wobble_m * wob
                src = np.minimum((_hash_u01(p.seed, ci, cj, 103).reshape(x.shape) * n).astype(np.int64), n - 1)
                better = d < best
                best = np.where(better, d, best)
                best_src = np.where(better, src, best_src)
        return best_src

    def _blocks_in(self, xmin: float, ymin: float, xmax: float, ymax: float) -> _Blocks:
        """Blocks whose disc may reach the world rectangle."""
        p = self.params
        s_m = self.block_px * p.metres_per_px
        reach = (p.block_support + p.block_jitter + 1.0) * s_m
        i = np.arange(math.floor((xmin - reach) / s_m), math.floor((xmax + reach) / s_m) + 1)
        j = np.arange(math.floor((ymin - reach) / s_m), math.floor((ymax + reach) / s_m) + 1)
        grid_i, grid_j = np.meshgrid(i, j, indexing="ij")
        ii = grid_i.ravel()
        jj = grid_j.ravel()
        seed = p.seed
        cx = (ii + 0.5 + p.block_jitter * (2.0 * _hash_u01(seed, ii, jj, 1) - 1.0)) * s_m
        cy = (jj + 0.5 + p.block_jitter * (2.0 * _hash_u01(seed, ii, jj, 2) - 1.0)) * s_m
        r_m = p.block_support * s_m
        keep = (cx + r_m >= xmin) & (cx - r_m <= xmax) & (cy + r_m >= ymin) & (cy - r_m <= ymax)
        ii, jj, cx, cy = ii[keep], jj[keep], cx[keep], cy[keep]
        theta = 2.0 * math.pi * _hash_u01(seed, ii, jj, 3)
        mirror = _hash_u01(seed, ii, jj, 4) < 0.5
        lo, hi = p.scale_range
        scale = np.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * _hash_u01(seed, ii, jj, 5))
        source = self.region_source_at(cx, cy)
        # world offset -> source pixel offset: rotate by -theta, metres -> px, y flips
        # (source rows grow downwards), optional mirror of the source's x axis.
        c, s = np.cos(theta), np.sin(theta)
        k = 1.0 / (scale * p.metres_per_px)
        sx = np.where(mirror, -1.0, 1.0) * k
        to_src = np.empty((len(ii), 2, 2))
        to_src[:, 0, 0] = sx * c
        to_src[:, 0, 1] = sx * s
        to_src[:, 1, 0] = -(-s) * k
        to_src[:, 1, 1] = -c * k
        # Where in the photo the block is cut: its disc must stay inside the photo.
        sizes = np.array([src.size for src in self._sources], dtype=np.float64)  # (n, 2) w, h
        radius_src = r_m * k + 2.0
        w = sizes[source, 0]
        h = sizes[source, 1]
        src_cx = radius_src + (w - 1.0 - 2.0 * radius_src) * _hash_u01(seed, ii, jj, 6)
        src_cy = radius_src + (h - 1.0 - 2.0 * radius_src) * _hash_u01(seed, ii, jj, 8)
        return _Blocks(cx, cy, source, to_src, src_cx, src_cy)

    # ------------------------------------------------------------ synthesis

    def _synthesise(self, x_origin_m: float, y_origin_m: float, mpp_out: float, width: int, height: int) -> np.ndarray:
        """Floor grey values on an axis-aligned grid, ``(height, width) float32``.

        Output pixel ``(c, r)`` has its centre at world ``(x_origin_m + c * mpp_out,
        y_origin_m - r * mpp_out)``. Coarser grids (``mpp_out`` > ``metres_per_px``)
        cut the blocks from a photo pyramid, so the result is the same floor, low-passed.
        """
        p = self.params
        xmin, xmax = x_origin_m, x_origin_m + (width - 1) * mpp_out
        ymax, ymin = y_origin_m, y_origin_m - (height - 1) * mpp_out
        blocks = self._blocks_in(xmin, ymin, xmax, ymax)
        ratio = mpp_out / p.metres_per_px
        level_float = math.log2(ratio / p.scale_range[0]) if ratio > 1.0 else 0.0
        s_px_out = self.block_px * p.metres_per_px / mpp_out  # block spacing in output px
        r_out = p.block_support * s_px_out
        d2_scale = 1.0 / (s_px_out * s_px_out)
        support2 = p.block_support**2
        best = np.full((height, width), -np.inf, dtype=np.float32)
        pieces = []
        flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
        for k in range(len(blocks.cx_m)):
            cu = (blocks.cx_m[k] - x_origin_m) / mpp_out
            cv_ = (y_origin_m - blocks.cy_m[k]) / mpp_out
            c0 = max(int(math.floor(cu - r_out)), 0)
            c1 = min(int(math.ceil(cu + r_out)) + 1, width)
            r0 = max(int(math.floor(cv_ - r_out)), 0)
            r1 = min(int(math.ceil(cv_ + r_out)) + 1, height)
            if c1 <= c0 or r1 <= r0:
                continue
            src = self._sources[blocks.source[k]]
            level = min(max(int(math.floor(level_float)), 0), len(src.pyramid) - 1)
            div = float(2**level)
            b = blocks.to_src[k]
            # output px (c, r) -> world -> source px (level 0) -> pyramid level.
            lin = b @ np.array([[mpp_out, 0.0], [0.0, -mpp_out]])
            off_world = np.array(
                [x_origin_m + c0 * mpp_out - blocks.cx_m[k], y_origin_m - r0 * mpp_out - blocks.cy_m[k]]
            )
            t = np.array([blocks.src_cx[k], blocks.src_cy[k]]) + b @ off_world
            m = np.hstack([lin, t[:, None]]) / div
            piece = cv2.warpAffine(
                src.pyramid[level], m, (c1 - c0, r1 - r0), flags=flags, borderMode=cv2.BORDER_REFLECT_101
            )
            dc = (np.arange(c0, c1, dtype=np.float32) - np.float32(cu)) ** 2
            dr = (np.arange(r0, r1, dtype=np.float32) - np.float32(cv_)) ** 2
            d2 = (dr[:, None] + dc[None, :]) * np.float32(d2_scale)
            score = piece[:, :, 1] - np.float32(p.seam_falloff) * d2
            score[d2 > support2] = -np.inf
            view = best[r0:r1, c0:c1]
            np.maximum(view, score, out=view)
            pieces.append((r0, r1, c0, c1, piece[:, :, 0], score))
        num = np.zeros((height, width), dtype=np.float32)
        den = np.zeros((height, width), dtype=np.float32)
        beta = np.float32(p.seam_sharpness)
        for r0, r1, c0, c1, value, score in pieces:
            wgt = np.exp(beta * (score - best[r0:r1, c0:c1]))
            num[r0:r1, c0:c1] += wgt * value
            den[r0:r1, c0:c1] += wgt
        return num / np.maximum(den, np.float32(1e-12))

    # ----------------------------------------------------------------- tiles

    def tile(self, tx: int, ty: int) -> np.ndarray:
        """Tile ``(tx, ty)``: ``(tile_px, tile_px) uint8``, read-only, cached (LRU).

        Covers floor columns ``tx * tile_px ...`` and rows ``ty * tile_px ...``.
        Deterministic from ``(seed, tx, ty)`` whatever the order tiles are made in.
        """
        key = (int(tx), int(ty))
        with self._lock:
            t = self._tiles.get(key)
            if t is not None:
                self._tiles.move_to_end(key)
                return t
        t = self._make_tile(*key)
        with self._lock:
            if key not in self._tiles:
                self._tiles[key] = t
                self._cache_bytes += t.nbytes
                limit = self.params.cache_mb * 1024 * 1024
                while self._cache_bytes > limit and len(self._tiles) > 1:
                    _, old = self._tiles.popitem(last=False)
                    self._cache_bytes -= old.nbytes
        return t

    def _make_tile(self, tx: int, ty: int) -> np.ndarray:
        n = self.params.tile_px
        mpp = self.params.metres_per_px
        img = self._synthesise(tx * n * mpp, -ty * n * mpp, mpp, n, n)
        out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        out.setflags(write=False)
        self.tiles_generated += 1
        return out

    def patch(self, x0_m: float, y0_m: float, x1_m: float, y1_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Full-resolution floor pixels covering the world rectangle ``[x0, x1] x [y0, y1]``.

        Returns ``(image (H, W) uint8, affine (2, 3) float64)``; the affine maps world
        ``(x_m, y_m, 1)`` to the image's ``(col, row)`` (pixel centres at integers).
        North (+y) is up. The image may extend a little beyond the rectangle.
        """
        mpp = self.params.metres_per_px
        n = self.params.tile_px
        col0 = math.floor(min(x0_m, x1_m) / mpp)
        col1 = math.ceil(max(x0_m, x1_m) / mpp)
        row0 = math.floor(-max(y0_m, y1_m) / mpp)
        row1 = math.ceil(-min(y0_m, y1_m) / mpp)
        out = np.empty((row1 - row0 + 1, col1 - col0 + 1), dtype=np.uint8)
        for ty in range(row0 // n, row1 // n + 1):
            for tx in range(col0 // n, col1 // n + 1):
                t = self.tile(tx, ty)
                # Intersection of tile (tx, ty) with [row0, row1] x [col0, col1].
                ra, rb = max(ty * n, row0), min((ty + 1) * n - 1, row1)
                ca, cb = max(tx * n, col0), min((tx + 1) * n - 1, col1)
                out[ra - row0 : rb - row0 + 1, ca - col0 : cb - col0 + 1] = t[
                    ra - ty * n : rb - ty * n + 1, ca - tx * n : cb - tx * n + 1
                ]
        affine = np.array([[1.0 / mpp, 0.0, -col0], [0.0, -1.0 / mpp, -row0]])
        return out, affine

    def render_overview(self, x0_m: float, y0_m: float, x1_m: float, y1_m: float, px_per_m: float) -> np.ndarray:
        """A north-up picture of the floor over ``[x0, x1] x [y0, y1]``, ``(H, W) uint8``.

        ``H = round((y1 - y0) * px_per_m)``, ``W = round((x1 - x0) * px_per_m)``; draw it
        with ``imshow(img, extent=(x0, x1, y0, y1), origin="upper")``. Below native
        resolution the same blocks are cut from a photo pyramid (coarse mode): it is the
        same floor, without generating full-resolution tiles, and does not touch the
        tile cache. A 10 x 10 m overview at 100 px/m takes a fraction of a second.
        """
        if px_per_m <= 0:
            raise ValueError("px_per_m must be positive")
        xa, xb = min(x0_m, x1_m), max(x0_m, x1_m)
        ya, yb = min(y0_m, y1_m), max(y0_m, y1_m)
        width = max(int(round((xb - xa) * px_per_m)), 1)
        height = max(int(round((yb - ya) * px_per_m)), 1)
        mpp_out = 1.0 / px_per_m
        if mpp_out <= self.params.metres_per_px * 1.5:
            img, aff = self.patch(xa, ya, xb, yb)
            cols = (xa + (np.arange(width) + 0.5) * mpp_out) * aff[0, 0] + aff[0, 2]
            rows = (yb - (np.arange(height) + 0.5) * mpp_out) * aff[1, 1] + aff[1, 2]
            mx, my = np.meshgrid(cols.astype(np.float32), rows.astype(np.float32))
            return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out = np.empty((height, width), dtype=np.uint8)
        chunk = 512
        for r in range(0, height, chunk):
            for c in range(0, width, chunk):
                h = min(chunk, height - r)
                w = min(chunk, width - c)
                img = self._synthesise(xa + (c + 0.5) * mpp_out, yb - (r + 0.5) * mpp_out, mpp_out, w, h)
                out[r : r + h, c : c + w] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return out


class ImageFloor:
    """One image laid on the floor as is (no quilting), for tests and printed floors.

    Pixel ``(col, row)`` of ``image`` has its centre at world
    ``(origin_x_m + col * metres_per_px, origin_y_m - row * metres_per_px)``; outside the
    image the floor has the grey level ``fill``.
    """

    def __init__(
        self,
        image: np.ndarray,
        metres_per_px: float = 0.001,
        origin_xy_m: tuple[float, float] = (0.0, 0.0),
        fill: int = 0,
    ) -> None:
        self.image = _as_grey_u8(image, "ImageFloor image")
        self._mpp = float(metres_per_px)
        self.origin_xy_m = (float(origin_xy_m[0]), float(origin_xy_m[1]))
        self.fill = int(fill)

    @property
    def metres_per_px(self) -> float:
        """Size of one floor pixel, metres."""
        return self._mpp

    def patch(self, x0_m: float, y0_m: float, x1_m: float, y1_m: float) -> tuple[np.ndarray, np.ndarray]:
        """See :meth:`FloorSource.patch`."""
        mpp = self._mpp
        ox, oy = self.origin_xy_m
        col0 = math.floor((min(x0_m, x1_m) - ox) / mpp)
        col1 = math.ceil((max(x0_m, x1_m) - ox) / mpp)
        row0 = math.floor((oy - max(y0_m, y1_m)) / mpp)
        row1 = math.ceil((oy - min(y0_m, y1_m)) / mpp)
        out = np.full((row1 - row0 + 1, col1 - col0 + 1), self.fill, dtype=np.uint8)
        h, w = self.image.shape
        ra, rb = max(row0, 0), min(row1, h - 1)
        ca, cb = max(col0, 0), min(col1, w - 1)
        if ra <= rb and ca <= cb:
            out[ra - row0 : rb - row0 + 1, ca - col0 : cb - col0 + 1] = self.image[ra : rb + 1, ca : cb + 1]
        affine = np.array([[1.0 / mpp, 0.0, -ox / mpp - col0], [0.0, -1.0 / mpp, oy / mpp - row0]])
        return out, affine
