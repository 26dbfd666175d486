"""Steps 1-3 of the floor descriptor (:mod:`robotd.floor.descriptor`): interest points and
their orientation, selection by learned relevance with repeats dropped, and the raw local
descriptors of the selected keypoints."""

from __future__ import annotations

import math
import threading
from functools import lru_cache
from typing import NamedTuple

import cv2
import numpy as np

from robotd.floor.desccoding import cells, fit
from robotd.floor.descparams import N_ATTRIBUTES, N_ELEMENTS, ExtractParams, Learned, ModeSpec

__all__ = ["Candidates", "Workspace", "candidates", "drop_repeats", "grey", "kept_for_budget", "raw_descriptors",
           "working", "workspace"]


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


def grey(image: np.ndarray) -> np.ndarray:
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


def working(grey: np.ndarray, params: ExtractParams) -> np.ndarray:
    h, w = grey.shape
    if max(h, w) > params.max_side_px:
        f = params.max_side_px / max(h, w)
        grey = cv2.resize(grey, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    return grey


class Workspace:
    """Reusable buffers for :func:`candidates` on one half-resolution size ``(h2, w2)``.

    Each full-image array of the detection is ``h2 x w2`` float32 (300 KB at 640 x 480),
    above the C allocator's threshold for handing memory back to the system: allocated
    afresh per frame, every page of every such array is faulted in again (about 1,500
    page faults per frame in a process that only describes, four tenths of the
    extraction's CPU time on the machine the benchmarks run on; fewer where other large
    arrays have raised the allocator's threshold). Kept per thread (:func:`workspace`),
    about 10 MB at 640 x 480.
    The pooled maps of the :class:`Candidates` that :func:`candidates` returns are these
    buffers: the next call on the same workspace overwrites them.
    """

    def __init__(self, h2: int, w2: int) -> None:
        self.shape = (h2, w2)
        f32 = [np.empty((h2, w2), np.float32) for _ in range(8)]
        self.x, self.g1, self.d, self.t1, self.t2, self.gx, self.gy, self.mag = f32
        self.ang = np.empty((h2, w2), np.float32)
        self.e1, self.e2 = np.empty((h2, w2), bool), np.empty((h2, w2), bool)
        self.grad = np.empty((h2, w2, 2), np.float32)
        self.f64a, self.f64b = np.empty((h2, w2), np.float64), np.empty((h2, w2), np.float64)
        self.i0, self.idx = np.empty((h2, w2), np.intp), np.empty((h2, w2), np.intp)
        self.ch = np.empty(8 * h2 * w2, np.float32)
        self.pooled = (np.empty((h2, w2, 4), np.float32), np.empty((h2, w2, 4), np.float32))
        self._flat: dict[str, np.ndarray] = {}
        self._half: Workspace | None = None

    def half(self) -> Workspace:
        """The workspace of this size halved (the maps at ``pool_step`` or ``orientation_step`` 2)."""
        if self._half is None:
            self._half = Workspace(self.shape[0] // 2, self.shape[1] // 2)
        return self._half

    def buffer(self, name: str, shape: tuple[int, ...], dtype: type = np.float32) -> np.ndarray:
        """A C-contiguous ``shape`` array of ``dtype`` (uninitialised) in the reusable buffer
        ``name``, which grows as needed."""
        size = math.prod(shape)
        b = self._flat.get(name)
        if b is None or b.size < size or b.dtype != dtype:
            b = self._flat[name] = np.empty(max(size, 1), dtype)
        return b[:size].reshape(shape)


_local = threading.local()


def workspace(h2: int, w2: int) -> Workspace:
    """This thread's :class:`Workspace` for half-resolution size ``(h2, w2)`` (one size kept)."""
    ws = getattr(_local, "ws", None)
    if ws is None or ws.shape != (h2, w2):
        ws = _local.ws = Workspace(h2, w2)
    return ws


def _std(x: np.ndarray, tmp: np.ndarray) -> float:
    """``float(x.std())`` of a float32 image, computed as numpy does (same rounding), with
    ``tmp`` (same shape and type) for the deviations instead of a fresh array."""
    mean = np.add.reduce(x, axis=None, keepdims=True)
    np.true_divide(mean, x.size, out=mean, casting="unsafe")
    np.subtract(x, mean, out=tmp)
    np.multiply(tmp, tmp, out=tmp)
    return float(np.sqrt(np.add.reduce(tmp, axis=None) / x.size))


def candidates(work: np.ndarray, params: ExtractParams, learned: Learned | None,
               ws: Workspace | None = None) -> Candidates:
    """Steps 1 and 2: keypoints of a working image ``(h, w) uint8`` with their attributes.

    Sorted by decreasing relevance (by response when ``learned`` is None). ``ws``: the
    buffers to compute in (:class:`Workspace`; the returned pooled maps are its buffers);
    None allocates fresh ones.
    """
    h2, w2 = work.shape[0] // 2, work.shape[1] // 2
    empty = Candidates(np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
                       np.zeros((0, N_ATTRIBUTES), np.float32), np.zeros(0, np.float32),
                       (np.zeros((1, 1, 4), np.float32),) * 2)
    border = int(math.ceil(params.cell_px))  # keep the inner cells inside the image
    if min(h2, w2) < 2 * border + 3:
        return empty
    if ws is None or ws.shape != (h2, w2):
        ws = Workspace(h2, w2)
    s = params.detect_sigma_px
    coarse = params.detect_step == 2
    half = ws.half() if coarse or 2 in (params.orientation_step, params.pool_step) else ws
    x = ws.x
    prefiltered = coarse and params.detect_prefilter
    made_g1 = not coarse or prefiltered or not params.exact_maps or params.pool_step == 1
    if made_g1:  # g1 at every pixel: for the detection or the maps
        np.copyto(x, cv2.resize(work, (w2, h2), interpolation=cv2.INTER_AREA), casting="unsafe")
        if not coarse or prefiltered:  # (the maps' scale does not matter: each raw descriptor is normalised)
            x *= np.float32(1.0 / max(_std(x, ws.t1), 1.0))  # flat images: no keypoint passes
        g1 = cv2.GaussianBlur(x, (0, 0), s, dst=ws.g1)
    if coarse:
        # Detection on the image halved again (a quarter of the pixels), the same sigmas in
        # its pixels; positions back in half-resolution pixels. The orientation and the
        # exact maps start from its Gaussian image (``quarter``). With ``detect_prefilter``
        # that image is g1 halved (2 x 2 area averages of the half-resolution image already
        # low-passed at detect_sigma_px, about the same sigma in quarter pixels) instead of a
        # 4 x 4 box average of the working image smoothed: the box folds the fine texture
        # back into the detection's band.
        h4, w4 = half.shape
        sq1 = 0.5 * s
        if prefiltered:
            quarter = cv2.resize(g1, (w4, h4), dst=half.x, interpolation=cv2.INTER_AREA)
        else:
            xq = half.t2
            np.copyto(xq, cv2.resize(work, (w4, h4), interpolation=cv2.INTER_AREA), casting="unsafe")
            xq *= np.float32(1.0 / max(_std(xq, half.t1), 1.0))
            quarter = cv2.GaussianBlur(xq, (0, 0), sq1, dst=half.x)
        d = np.subtract(quarter, cv2.GaussianBlur(quarter, (0, 0), sq1 * math.sqrt(params.dog_ratio**2 - 1.0),
                                                  dst=half.t1), out=half.d)
        found = _extrema(d, int(math.ceil(0.5 * params.cell_px)), params, half)
        if found is None:
            return empty
        dc, edge, xy_half = found
        xy_half = xy_half * 2 + 0.5
    else:
        d = np.subtract(g1, cv2.GaussianBlur(g1, (0, 0), s * math.sqrt(params.dog_ratio**2 - 1.0), dst=ws.t1),
                        out=ws.d)
        found = _extrema(d, border, params, ws)
        if found is None:
            return empty
        dc, edge, xy_half = found
        # g1 halved: for the orientation at orientation_step 2 and the exact maps at pool_step 2
        # (the table-split maps at pool_step 2 halve their channels instead).
        quarter = (cv2.resize(g1, (w2 // 2, h2 // 2), dst=half.x, interpolation=cv2.INTER_AREA)
                   if params.orientation_step == 2 or (params.pool_step == 2 and params.exact_maps) else g1)
    # Orientation: gradient of the image smoothed at orientation_sigma_px, at the keypoint.
    # With orientation_step 2 (always with detect_step 2) it is taken on g1 halved (area
    # averaging), smoothed by what the sigma lacks after g1's and the halving's smoothing,
    # and scaled back to half-resolution pixels; the pooled maps start from the same
    # halved image.
    pooled: tuple[np.ndarray, np.ndarray] | None = None
    if params.orientation_from_maps:  # the pooled maps first: the orientation is read from them
        pooled = _pooled_maps(g1 if made_g1 else None, quarter, params, ws, half)
        v = _orientation_of_maps(pooled, xy_half, params, ws)
    else:
        if params.orientation_step == 2 or coarse:
            so = math.sqrt(max(params.orientation_sigma_px**2 - s * s - 0.25, 0.25)) / 2
            go, at, gain = cv2.GaussianBlur(quarter, (0, 0), so, dst=half.g1), (xy_half - 0.5) * 0.5, 0.5
            grad = cv2.merge([cv2.Sobel(go, cv2.CV_32F, 1, 0, dst=half.gx, ksize=1, scale=gain),
                              cv2.Sobel(go, cv2.CV_32F, 0, 1, dst=half.gy, ksize=1, scale=gain)], dst=half.grad)
        else:
            go, at = cv2.GaussianBlur(x, (0, 0), params.orientation_sigma_px, dst=ws.t1), xy_half
            grad = cv2.merge([cv2.Sobel(go, cv2.CV_32F, 1, 0, dst=ws.gx, ksize=1),
                              cv2.Sobel(go, cv2.CV_32F, 0, 1, dst=ws.gy, ksize=1)], dst=ws.grad)
        v = cv2.remap(grad, np.ascontiguousarray(at[:, :1]), np.ascontiguousarray(at[:, 1:]),
                      cv2.INTER_LINEAR).reshape(-1, 2)
    angle = np.arctan2(v[:, 1], v[:, 0]).astype(np.float32) % np.float32(2 * math.pi)
    xy = xy_half * 2 + 0.5  # half-resolution pixel centre -> working-image pixels
    hw = np.array([work.shape[1] - 1, work.shape[0] - 1], np.float32) * 0.5
    attributes = np.empty((N_ATTRIBUTES, len(xy)), np.float32)  # attribute-major while binned: contiguous rows
    np.abs(dc, out=attributes[0], casting="same_kind")
    attributes[1] = edge
    attributes[2] = np.linalg.norm((xy - hw) / hw, axis=1) / math.sqrt(2)
    attributes[3] = np.hypot(v[:, 0], v[:, 1])
    if learned is None:
        relevance = attributes[0].copy()
    else:
        relevance = np.zeros(len(xy), np.float32)
        for a in range(N_ATTRIBUTES):
            relevance += learned.rel_logp[a][np.searchsorted(learned.rel_edges[a], attributes[a])]
    attributes = attributes.T
    order = np.argsort(-relevance, kind="stable")
    if pooled is None:
        pooled = _pooled_maps(g1 if made_g1 else None, quarter, params, ws, half)
    return Candidates(xy[order], angle[order], attributes[order], relevance[order], pooled)


def _pooled_maps(g1: np.ndarray | None, quarter: np.ndarray, params: ExtractParams, ws: Workspace,
                 half: Workspace) -> tuple[np.ndarray, np.ndarray]:
    """Step 3's pooled orientation maps as ``params`` asks (:func:`_pooled_orientation_maps`)
    from the detection image smoothed at every pixel ``g1`` (None when only the exact maps
    of the halved image ``quarter`` are asked for)."""
    if params.pool_step == 2 and params.exact_maps:  # the halving's smoothing and the bilinear sampling deducted
        return _pooled_orientation_maps(quarter, math.sqrt(max(params.pool_sigma_px**2 - 1.0, 0.25)) / 2, half)
    assert g1 is not None
    if params.pool_step == 2:
        return _pooled_orientation_maps(g1, math.sqrt(max(params.pool_sigma_px**2 - 1.0, 0.25)) / 2, ws, False, half)
    return _pooled_orientation_maps(g1, params.pool_sigma_px, ws, params.exact_maps)


_DIRECTIONS = np.array([[math.cos(d * math.pi / 4) for d in range(4)],
                        [math.sin(d * math.pi / 4) for d in range(4)]], np.float32)
"""``(2, 4)``: the unit vectors of directions 0-3 (directions 4-7 are their opposites)."""


def _orientation_of_maps(pooled: tuple[np.ndarray, np.ndarray], xy_half: np.ndarray, params: ExtractParams,
                         ws: Workspace) -> np.ndarray:
    """``(K, 2) float32``: the orientation vectors of the keypoints at ``xy_half`` (half-resolution
    pixels) read from the pooled orientation maps (``params.orientation_from_maps``).

    Each map holds one direction's share of the gradients of the detection image smoothed
    at ``detect_sigma_px``, pooled at ``pool_sigma_px``: the sum of the 8 maps weighted by
    their directions' unit vectors is that gradient field pooled (the linear split between
    two directions gives back the gradient's direction and 0.92-1 of its length), smoothed
    by what ``orientation_sigma_px`` lacks after both (none when nothing lacks) and sampled
    at each keypoint: the gradient of the image smoothed at ``orientation_sigma_px``, without
    a Gaussian of that width over every pixel."""
    opposite = cv2.subtract(pooled[0], pooled[1], dst=ws.buffer("om_diff", pooled[0].shape))
    vec = cv2.transform(opposite, _DIRECTIONS, dst=ws.buffer("om_vec", opposite.shape[:2] + (2,)))
    lack = params.orientation_sigma_px**2 - params.detect_sigma_px**2 - params.pool_sigma_px**2
    if lack > 0:
        vec = cv2.GaussianBlur(vec, (0, 0), math.sqrt(lack) / params.pool_step, dst=ws.buffer("om_blur", vec.shape))
    at = (xy_half - 0.5) * 0.5 if params.pool_step == 2 else xy_half  # pixel centres of the halved maps
    return cv2.remap(vec, np.ascontiguousarray(at[:, :1]), np.ascontiguousarray(at[:, 1:]),
                     cv2.INTER_LINEAR).reshape(-1, 2)


def _extrema(d: np.ndarray, border: int, params: ExtractParams,
             ws: Workspace) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Step 1's interest points in a difference of Gaussians ``d (h, w) float32`` (a
    buffer of ``ws``, whose ``t1``, ``e1`` and ``e2`` it overwrites): 3 x 3 extrema above
    ``min_contrast`` at least ``border`` pixels inside, edges rejected by the Hessian
    ratio and offsets refined to sub-pixel by its quadratic fit (Lowe 2004, Sec. 4).
    Returns the DoG value ``(K,)``, the edge ratio ``(K,)`` and the ``(K, 2) float32``
    sub-pixel positions in ``d``'s pixels, or None when nothing passes."""
    w2 = d.shape[1]
    square = np.ones((3, 3), np.uint8)  # OpenCV's default kernel (None): the 8-neighbourhood
    ext = np.equal(d, cv2.dilate(d, square, dst=ws.t1), out=ws.e1)
    ext |= np.equal(d, cv2.erode(d, square, dst=ws.t1), out=ws.e2)
    ext &= np.greater(np.abs(d, out=ws.t1), params.min_contrast, out=ws.e2)
    ext[:border], ext[-border:], ext[:, :border], ext[:, -border:] = False, False, False, False
    i = np.flatnonzero(ext)  # np.nonzero's order, a third of its time
    df = d.ravel()  # pixels read by flat index (d[y, x + 1] is df[i + 1]): a fraction of 2-D indexing's time
    dc = df[i]
    if len(dc) > params.max_candidates:
        keep = np.argpartition(-np.abs(dc), params.max_candidates - 1)[: params.max_candidates]
        i, dc = i[keep], dc[keep]
    ys, xs = np.divmod(i, w2)
    # Hessian of the DoG: edge rejection (Lowe 2004, Sec. 4.1) and sub-pixel offset.
    right, left, down, up = df[i + 1], df[i - 1], df[i + w2], df[i - w2]
    dxx = right + left - 2 * dc
    dyy = down + up - 2 * dc
    dxy = 0.25 * (df[i + w2 + 1] - df[i + w2 - 1] - df[i - w2 + 1] + df[i - w2 - 1])
    det = dxx * dyy - dxy * dxy
    edge = (dxx + dyy) ** 2 / np.where(det > 0, det, 1.0)
    ok = (det > 0) & (edge < (params.edge_ratio + 1) ** 2 / params.edge_ratio)
    ys, xs, dc, dxx, dyy, dxy, det, edge, right, left, down, up = (
        v[ok] for v in (ys, xs, dc, dxx, dyy, dxy, det, edge, right, left, down, up))
    if len(xs) == 0:
        return None
    gx = 0.5 * (right - left)
    gy = 0.5 * (down - up)
    ox = np.clip((-dyy * gx + dxy * gy) / det, -0.5, 0.5)
    oy = np.clip((dxy * gx - dxx * gy) / det, -0.5, 0.5)
    return dc, edge, np.column_stack([xs + ox, ys + oy]).astype(np.float32)


def _pooled_orientation_maps(g: np.ndarray, sigma: float, ws: Workspace | None = None,
                             exact: bool = True, halved: Workspace | None = None) -> tuple[np.ndarray, np.ndarray]:
    """8 gradient-orientation channels of ``g`` (each gradient's magnitude split linearly
    between the two nearest of 8 directions), Gaussian-pooled at ``sigma`` pixels of ``g``:
    two ``(h, w, 4) float32`` images (directions 0-3 and 4-7; OpenCV filters and remaps up
    to 4 channels fastest). ``ws``: buffers of ``g``'s size (the result is its ``pooled``).

    ``exact`` False: the split is looked up in a table of :data:`_LUT_LEVELS` angles
    (:func:`_split_table`; the angle to 1/32 of a direction bin, each channel within 1/64
    of the magnitude of the exact split) and the channels are made by two table
    look-ups and two products instead of per-pixel scatters: about half the channel
    building's time. ``halved`` (only with ``exact`` False): the channels of ``g``'s
    gradients are halved (area averaging) into that workspace of half ``g``'s size and
    pooled there, ``sigma`` in its pixels (the result is its ``pooled``): the maps at a
    quarter of the pixels, from the gradients at every pixel."""
    h, w = g.shape
    if ws is None or ws.shape != (h, w):
        ws = Workspace(h, w)
    mag, ang = cv2.cartToPolar(cv2.Sobel(g, cv2.CV_32F, 1, 0, dst=ws.gx, ksize=1),
                               cv2.Sobel(g, cv2.CV_32F, 0, 1, dst=ws.gy, ksize=1), magnitude=ws.mag, angle=ws.ang)
    k = 2 * int(math.ceil(2 * sigma)) + 1
    if not exact:
        q = ws.buffer("q8", (h, w), np.uint8)
        # floor(angle * 256 / 2 pi) (rounding |x - 0.5|), the level whose centre is nearest
        cv2.convertScaleAbs(ang, dst=q, alpha=_LUT_LEVELS / (2 * math.pi), beta=-0.5)
        # Direction d's share at level q is direction 0's at level q - 32 d (mod 256: the
        # table turns with the angle), so each plane's 4 channels are the level shifted by
        # 32 d and one single-channel table serves all 8 directions (cv2.LUT with one
        # table: about 0.6 of the time of a table per channel, the same values).
        levels = [q] + [np.add(q, shift, out=ws.buffer(f"q8_{d}", (h, w), np.uint8))
                        for d, shift in enumerate(_LEVEL_SHIFTS[1:4], 1)]  # uint8: mod 256
        q0 = cv2.merge(levels, dst=ws.buffer("q8x4_0", (h, w, 4), np.uint8))
        qs = [q0, np.add(q0, _LEVEL_SHIFTS[4], out=ws.buffer("q8x4_1", (h, w, 4), np.uint8))]  # directions 4-7
        mag4 = cv2.merge([mag] * 4, dst=ws.buffer("mag4", (h, w, 4)))
        planes = ws.ch.reshape(2, h, w, 4)
        dst = ws if halved is None else halved
        hh, wh = dst.shape
        table = _level_table()
        if halved is not None and h == 2 * hh and w == 2 * wh:
            # Halving exactly 2 x 2 blocks is local: strips of _STRIP rows are split, weighted
            # and halved while they are in the cache (same values as the whole image at once).
            small = halved.ch.reshape(2, hh, wh, 4)
            for r0 in range(0, h, _STRIP):
                r1 = min(h, r0 + _STRIP)
                for i in range(2):
                    c = cv2.LUT(qs[i][r0:r1], table, dst=planes[i][r0:r1])
                    cv2.multiply(c, mag4[r0:r1], dst=c)
                    cv2.resize(c, (wh, (r1 - r0) // 2), dst=small[i][r0 // 2:r1 // 2], interpolation=cv2.INTER_AREA)
            return (cv2.GaussianBlur(small[0], (k, k), sigma, dst=halved.pooled[0]),
                    cv2.GaussianBlur(small[1], (k, k), sigma, dst=halved.pooled[1]))
        out = []
        for i in range(2):
            c = cv2.LUT(qs[i], table, dst=planes[i])
            cv2.multiply(c, mag4, dst=c)
            if halved is not None:
                c = cv2.resize(c, (wh, hh), dst=halved.ch.reshape(2, hh, wh, 4)[i], interpolation=cv2.INTER_AREA)
            out.append(cv2.GaussianBlur(c, (k, k), sigma, dst=dst.pooled[i]))
        return out[0], out[1]
    b = np.multiply(ang, np.float32(8 / (2 * math.pi)), out=ws.t1)
    b0 = ws.i0
    np.copyto(b0, b, casting="unsafe")  # truncation, as astype
    hi = np.subtract(b, b0, out=ws.f64a)  # float64, as the expression mag * (b - b0)
    np.multiply(mag, hi, out=hi)
    # Direction d of pixel p goes to plane d // 4, slot 4 p + d % 4; both planes contiguous.
    base, slot = _slots(h, w)
    ch = ws.ch
    ch.fill(0.0)
    idx = ws.idx
    b0 &= 7
    np.add(np.take(slot, b0, out=idx), base, out=idx)
    ch[idx] = np.subtract(mag, hi, out=ws.t2, casting="same_kind")
    b0 += 1
    b0 &= 7
    np.add(np.take(slot, b0, out=idx), base, out=idx)
    np.copyto(ws.t2, hi, casting="same_kind")
    ch[idx] = ws.t2  # never the slot just written
    ch4 = ch.reshape(2, h, w, 4)
    return (cv2.GaussianBlur(ch4[0], (k, k), sigma, dst=ws.pooled[0]),
            cv2.GaussianBlur(ch4[1], (k, k), sigma, dst=ws.pooled[1]))


_STRIP = 64
"""Rows per strip of the channels halved strip by strip (even)."""
_LUT_LEVELS = 256
"""Angles of the channel table (:func:`_pooled_orientation_maps` with ``exact`` False)."""
_LEVEL_SHIFTS = [np.uint8((-32 * d) % _LUT_LEVELS) for d in range(8)]
"""Added to the angle's level (mod 256) for direction ``d`` (:func:`_level_table`)."""


@lru_cache(maxsize=1)
def _split_table() -> tuple[np.ndarray, np.ndarray]:
    """``2 x (_LUT_LEVELS, 1, 4) float32`` (``cv2.LUT``'s 4-channel tables): row ``q`` splits a unit gradient at angle
    ``2 pi (q + 0.5) / _LUT_LEVELS`` (the centre of the angles ``[q, q + 1) 2 pi / _LUT_LEVELS``)
    between the two nearest of 8 directions (linearly, as the exact maps do); directions
    0-3 and 4-7."""
    b = (np.arange(_LUT_LEVELS) + 0.5) * (8 / _LUT_LEVELS)
    b0 = np.floor(b).astype(np.intp)
    t = np.zeros((_LUT_LEVELS, 8), np.float64)
    rows = np.arange(_LUT_LEVELS)
    t[rows, b0 % 8] += 1.0 - (b - b0)
    t[rows, (b0 + 1) % 8] += b - b0
    t = t.astype(np.float32)
    return np.ascontiguousarray(t[:, None, :4]), np.ascontiguousarray(t[:, None, 4:])


@lru_cache(maxsize=1)
def _level_table() -> np.ndarray:
    """``(256,) float32``: direction 0's share of a unit gradient at each angle level
    (:func:`_split_table`'s first column; direction ``d``'s is it at the level ``- 32 d``)."""
    return np.ascontiguousarray(_split_table()[0][:, 0, 0])


@lru_cache(maxsize=4)
def _slots(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """``(h, w) intp`` ``4 p`` for pixel ``p`` (row-major), and ``(8,) intp`` the offset
    of direction ``d`` from it in the two stacked ``(h, w, 4)`` planes."""
    d = np.arange(8, dtype=np.intp)
    return np.arange(0, 4 * h * w, 4, dtype=np.intp).reshape(h, w), (d >> 2) * (4 * h * w) + (d & 3)


_SHIFTS = np.stack([np.roll(np.eye(8, dtype=np.float32), s, axis=0) for s in range(9)])
"""``(9, 8, 8)``: ``x @ _SHIFTS[s]`` is ``x`` with element ``j`` taken from ``(s + j) % 8``."""
_TURN_SLOTS = np.stack([[((np.arange(8) + s + o) % 8) * 8 + np.arange(8) for s in range(8)] for o in (0, 1)])
"""``(2, 8, 8)``: flat positions in an 8 x 8 matrix of the entries of ``_SHIFTS[s]`` (``[0, s]``)
and ``_SHIFTS[s + 1]`` (``[1, s]``) that are 1, one per column."""
_GRID = np.meshgrid(np.arange(4, dtype=np.float32) - 1.5, np.arange(4, dtype=np.float32) - 1.5)


def raw_descriptors(c: Candidates, n: int, params: ExtractParams, ws: Workspace | None = None) -> np.ndarray:
    """Step 3: SIFT-like ``(n, 128) float32`` descriptors of the first ``n`` candidates.

    Cell-major (16 cells row by row in the keypoint's frame) x 8 relative orientation
    bins; L2-normalised, clipped at 0.2 and renormalised (Lowe 2004, Sec. 6.1).
    ``ws``: compute in its buffers; the result is then one of them (valid until the
    next call with ``ws``).
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
    if params.pool_step == 2:  # pixel centres of the halved maps
        mx = (mx - 0.5) * 0.5
        my = (my - 0.5) * 0.5
    if ws is None:
        smp = cv2.merge([cv2.remap(p, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
                         for p in c.pooled])  # (n, 16, 8): directions 0-7
    else:  # cv2.merge interleaves the two halves a fraction of a strided copy's time
        smp = cv2.merge([cv2.remap(p, mx, my, cv2.INTER_LINEAR, dst=ws.buffer(f"smp{i}", (n, 16, 4)),
                                   borderMode=cv2.BORDER_REFLECT_101) for i, p in enumerate(c.pooled)],
                        dst=ws.buffer("smp", (n, 16, 8)))
    # Turn the 8 absolute directions into directions relative to the keypoint: relative
    # bin j is absolute direction angle + j * 45 deg, interpolated between whole bins,
    # one 8 x 8 matrix per keypoint (a blend of two circular shifts).
    turn = _turns(ang, None if ws is None else ws.buffer("turn", (n, 8, 8)))
    d = np.matmul(smp, turn) if ws is None else np.matmul(smp, turn, out=ws.buffer("raw", (n, 16, 8)))
    d = d.reshape(n, N_ELEMENTS)
    d *= 1 / np.maximum(np.sqrt(np.einsum("ij,ij->i", d, d)), 1e-12)[:, None]
    np.minimum(d, 0.2, out=d)
    d *= 1 / np.maximum(np.sqrt(np.einsum("ij,ij->i", d, d)), 1e-12)[:, None]
    return d


def _turns(ang: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``(n, 8, 8) float32``: for each orientation in ``ang (n,) float32`` (radians, in
    [0, 2 pi]), the matrix that turns 8 absolute direction bins into bins relative to it,
    ``_SHIFTS[a0] (1 - f) + _SHIFTS[a0 + 1] f`` with ``a0 + f`` the orientation in bins.

    That blend has exactly two non-zero entries per column, ``1 - f`` and ``f`` (every
    product with 0 or 1 and every sum with 0 is exact), so they are written into zeros:
    the same matrices, bit for bit, at a fraction of the arithmetic. ``out``: an
    ``(n, 8, 8) float32`` C-contiguous buffer to write them in.
    """
    n = len(ang)
    a = ang * np.float32(8 / (2 * math.pi))
    a0 = a.astype(np.intp) & 7
    f = a - np.floor(a)
    turn = np.zeros((n, 8, 8), np.float32) if out is None else out
    if out is not None:
        turn.fill(0.0)
    flat = turn.reshape(-1)
    at = np.arange(0, 64 * n, 64)[:, None]
    flat[at + _TURN_SLOTS[0][a0]] = (1 - f)[:, None]
    flat[at + _TURN_SLOTS[1][a0]] = f[:, None]
    return turn


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


def _repeats(raw: np.ndarray, xy: np.ndarray, start: int, stop: int, params: ExtractParams,
             projected: np.ndarray | None = None, ws: Workspace | None = None) -> np.ndarray:
    """``(stop - start,) bool``: which of the checked candidates ``start:stop`` repeat
    (:func:`drop_repeats`) among all ``K`` checked ones, given their ``(K, 128)`` raw
    descriptors and ``(K, 2)`` working-image positions. Rows are independent, so the
    rows can be decided a block at a time (:func:`extract` decides only as many as the
    budget reaches).

    ``projected``: the raw descriptors times a ``(128, P)`` matrix with orthonormal
    columns (the learned PCA basis). A projection never lengthens a difference, so the
    pairs within ``repeat_distance`` after it include every pair within it before; only
    those few are measured in 128 dimensions. Same result, a quarter of the arithmetic.
    ``ws``: buffers for the ``(stop - start, K)`` products (same result).
    """
    t2 = params.repeat_distance**2
    sq = np.einsum("ij,ij->i", raw, raw)
    if projected is None:
        d2 = raw[start:stop] @ raw.T  # |a - b|^2 = |a|^2 + |b|^2 - 2 a.b, in place
        d2 *= -2.0
        d2 += sq[start:stop, None]
        d2 += sq[None, :]
        i, j = np.nonzero(d2 < t2)  # the diagonal, neighbours on one blob, repeats
    else:
        # [z_i, -|z_i|^2 / 2, 1] . [z_j, 1, (t - |z_j|^2) / 2] = (t - |z_i - z_j|^2) / 2: one
        # product and one comparison; t has a margin for float32 rounding.
        zq = np.einsum("ij,ij->i", projected, projected)
        rows = np.empty((stop - start, projected.shape[1] + 2), np.float32)
        rows[:, :-2] = projected[start:stop]
        rows[:, -2] = -0.5 * zq[start:stop]
        rows[:, -1] = 1.0
        cols = np.empty((len(projected), projected.shape[1] + 2), np.float32)
        cols[:, :-2] = projected
        cols[:, -2] = 1.0
        cols[:, -1] = 0.5 * (t2 + 1e-3 - zq)
        if ws is None:
            i, j = np.nonzero(rows @ cols.T > 0)
        else:
            shape = (stop - start, len(projected))
            prod = np.matmul(rows, cols.T, out=ws.buffer("prod", shape))
            i, j = np.divmod(np.flatnonzero(np.greater(prod, 0, out=ws.buffer("near", shape, bool))), shape[1])
        other = j != start + i  # most pairs are a candidate with itself: never a repeat (same position)
        i, j = i[other], j[other]
        exact = np.einsum("ij,ij->i", raw[start + i], raw[j])
        exact *= -2.0
        exact += sq[start + i]
        exact += sq[j]
        near = exact < t2
        i, j = i[near], j[near]
    patch_px = 2 * 4 * params.cell_px  # the patch width, in working-image pixels (cells are half-resolution)
    far = np.sum((xy[start + i] - xy[j]) ** 2, axis=1) >= patch_px**2
    out = np.zeros(stop - start, bool)
    out[i[far]] = True
    return out


def repeat_pool(params: ExtractParams, first: int, available: int) -> int:
    """How many candidates the repeat check takes (:func:`kept_for_budget`): ``repeat_pool``,
    or with ``repeat_pool_ratio`` > 0 that many times ``first`` (what the budget codes with
    no repeat dropped, or the global descriptor's minimum, plus one) when fewer; at most
    ``available``."""
    k = params.repeat_pool
    if params.repeat_pool_ratio > 0:
        k = min(k, math.ceil(params.repeat_pool_ratio * first))
    return min(k, available)


def kept_for_budget(c: Candidates, params: ExtractParams, spec: ModeSpec, grid_w: int, grid_h: int,
                     block: int = 256, basis: np.ndarray | None = None,
                     ws: Workspace | None = None) -> tuple[Candidates, np.ndarray, int]:
    """:func:`drop_repeats` and :func:`~robotd.floor.desccoding.fit` together, deciding only the rows needed.

    The coded keypoints are the first ``n`` kept candidates and the global descriptor
    aggregates the first ``max(n, global_min_features)``; whether a later candidate repeats
    changes neither. So the candidates are checked (each against the whole pool, as
    :func:`drop_repeats` does) a block at a time until the kept ones reach past what
    the budget codes. The first block is what the budget would code with no repeats
    dropped, and a fifth more; then ``block`` at a time. The result is the same as
    ``drop_repeats`` (with the pool of :func:`repeat_pool`) then ``fit`` for everything
    :func:`extract` uses: the returned
    candidates are exact up to the first ``max(n + 1, global_min_features)`` kept ones,
    and end there when not all were checked. ``basis``: a ``(128, P)`` matrix with
    orthonormal columns that prefilters the pairs (:func:`_repeats`; same result).
    ``ws``: buffers for the pool's raw descriptors and the pair products (same result).

    Returns the kept candidates, the raw descriptors of the first of them (the checked
    ones) and ``n``.
    """
    k = min(params.repeat_pool, len(c.xy))
    if params.repeat_distance <= 0 or k < 2:
        kept, raw = c, raw_descriptors(c, k, params)
        return kept, raw, fit(spec, cells(kept.xy, grid_w, grid_h))
    coded = cells(c.xy, grid_w, grid_h)  # every candidate's grid cell, once
    n = fit(spec, coded[:k])
    first = max(n + 1, params.global_min_features)
    k = max(2, repeat_pool(params, first, k))
    raw = raw_descriptors(c, k, params, ws)
    projected = None if basis is None else raw @ basis
    repeat = np.zeros(k, bool)
    done = 0
    step = min(k, first + first // 5 + 8)
    while True:
        stop = min(k, done + step)
        repeat[done:stop] = _repeats(raw, c.xy[:k], done, stop, params, projected, ws)
        done = stop
        step = block
        keep = np.flatnonzero(~repeat[:done])
        if done == k:  # every checked row decided; unchecked candidates after the pool are kept
            keep = np.concatenate([keep, np.arange(k, len(c.xy))])
        n = fit(spec, coded[keep], hint=n)
        if done == k or (n < len(keep) and len(keep) >= params.global_min_features):
            break
    kept = Candidates(c.xy[keep], c.angle[keep], c.attributes[keep], c.relevance[keep], c.pooled)
    return kept, raw[keep[keep < k]], n
