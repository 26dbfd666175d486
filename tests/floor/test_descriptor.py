"""The compact floor descriptor: the byte bound holds for any image in every mode, the bytes
decode back to what extraction selected, and damaged or forged bytes give DescriptorError."""

from __future__ import annotations

import math
import re
import struct
import zlib

import cv2
import numpy as np
import pytest
import skimage.data
from hypothesis import given, settings
from hypothesis import strategies as st

from robotd.base.errors import DescriptorError, RobotdError
from robotd.base.geometry import wrap_angle
from robotd.floor.compression import ternarise
from robotd.floor.descriptor import (ANGLE_BITS, MODE_BYTES, MODES, POSITION_STEP_PX, ExtractParams, decode,
                                     describe, drop_repeats, extract, load_learned)
from robotd.floor.keypoints import candidates, raw_descriptors
from robotd.base.camera import FloorCameraModel
from sim.world.floor import Floor
from sim.cameras.floor import FloorRenderer, RenderParams

ALL_MODES = sorted(MODES)
HEADER_BYTES = 20  # magic, version, mode, sizes, n, k, reserved, CRC (module docstring)


# ----------------------------------------------------------------------------- helpers

@pytest.fixture(scope="module")
def frames() -> dict[str, np.ndarray]:
    """One virtual-robot floor frame ``(480, 640) uint8`` per texture photo."""
    cam = FloorCameraModel.default()
    out = {}
    for i, name in enumerate(("brick", "grass", "gravel")):
        floor = Floor.from_photos([getattr(skimage.data, name)()], seed=31 + i)
        renderer = FloorRenderer(floor, cam, RenderParams(), np.random.default_rng(7 + i))
        out[name] = renderer.render(np.array([0.4, -0.3, 0.5 + i]), 0.1, 0.0, 3.0)
    return out


@pytest.fixture(scope="module")
def coded(frames) -> dict[int, bytes]:
    """A real descriptor of the brick frame in every mode."""
    return {m: extract(frames["brick"], m) for m in ALL_MODES}


def _sections(data: bytes) -> list[tuple[str, int, int]]:
    """``(name, start, end)`` byte ranges of a descriptor, from the documented layout."""
    _, _, mode, _, _, _, _, n, k, _, _ = struct.unpack_from("<2sBBHHHHHBBI", data)
    spec = MODES[mode]
    sizes = [("header", 16), ("crc", 4), ("global", spec.global_bits // 8), ("rice remainders", -(-n * k // 8)),
             ("angles", -(-n * ANGLE_BITS // 8)), ("trits", -(-n * spec.length // 5))]
    out, pos = [], 0
    for name, size in sizes:
        out.append((name, pos, pos + size))
        pos += size
    out.append(("unary", pos, len(data)))
    return out


def _with_crc(data: bytes | bytearray) -> bytes:
    """``data`` with its CRC-32 field recomputed: a forgery the checksum cannot catch."""
    b = bytearray(data)
    b[16:20] = struct.pack("<I", zlib.crc32(bytes(b[20:]), zlib.crc32(bytes(b[:16]))))
    return bytes(b)


def _set_header(data: bytes, **fields: int) -> bytes:
    """Change named header fields and recompute the CRC."""
    names = ["magic", "version", "mode", "width", "height", "work_width", "work_height", "n", "k", "reserved", "crc"]
    values = dict(zip(names, struct.unpack_from("<2sBBHHHHHBBI", data)))
    values.update(fields)
    return _with_crc(struct.pack("<2sBBHHHHHBBI", *values.values()) + data[HEADER_BYTES:])


def _check_valid(data: bytes, mode: int, height: int, width: int) -> None:
    """Everything the format promises about ``extract(image of height x width, mode)``."""
    assert isinstance(data, bytes)
    assert len(data) <= MODE_BYTES[mode]
    d = decode(data)
    spec = MODES[mode]
    n = len(d)
    assert d.mode == mode and (d.width_px, d.height_px) == (width, height)
    assert d.length == spec.length
    assert d.xy_px.shape == (n, 2) and d.xy_px.dtype == np.float32
    assert np.all(d.xy_px >= -0.5) and np.all(d.xy_px[:, 0] <= width - 0.5) and np.all(d.xy_px[:, 1] <= height - 0.5)
    assert d.angle_rad.shape == (n,)
    assert np.all((d.angle_rad >= 0) & (d.angle_rad < 2 * math.pi))
    levels = d.angle_rad / (2 * math.pi / 2**ANGLE_BITS)
    assert np.allclose(levels, np.round(levels), atol=1e-3)
    words = -(-spec.length // 64)
    assert d.local_pos.shape == d.local_neg.shape == (n, words) and d.local_pos.dtype == np.uint64
    assert not np.any(d.local_pos & d.local_neg)  # an element is never +1 and -1
    t = d.ternary()
    assert t.shape == (n, spec.length) and set(np.unique(t).tolist()) <= {-1.0, 0.0, 1.0}
    assert d.global_bits.shape == (spec.global_bits // 8,) and d.global_bits.dtype == np.uint8
    assert d.position_step_px >= POSITION_STEP_PX
    if max(height, width) <= ExtractParams().max_side_px:
        assert d.position_step_px == POSITION_STEP_PX
    # Coded order: grid cells in row-major order, never decreasing.
    dx, dy = np.diff(d.xy_px[:, 0]), np.diff(d.xy_px[:, 1])
    assert np.all((dy > 0) | ((dy == 0) & (dx >= 0)))


# ----------------------------------------------------------------------------- the byte bound

def _noise(rng, h, w):
    return rng.integers(0, 256, (h, w), dtype=np.uint8)


def _smooth(rng, h, w):
    sigma = float(rng.uniform(0.7, 8.0))
    x = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), sigma)
    x = (x - x.min()) / max(float(np.ptp(x)), 1e-6)
    return np.round(255 * x).astype(np.uint8)


def _salt_and_pepper(rng, h, w):
    return np.where(rng.random((h, w)) < 0.5, 0, 255).astype(np.uint8)


def _checker(rng, h, w):
    s = int(rng.integers(1, 40))
    yy, xx = np.mgrid[0:h, 0:w]
    return np.where(((yy // s) + (xx // s)) % 2 == 0, 0, 255).astype(np.uint8)


@st.composite
def images(draw, max_h: int = 480, max_w: int = 640) -> np.ndarray:
    """Random noise, blank at any grey, saturated (0/255) checkerboards and salt-and-pepper
    noise, smoothed noise, tiny,
    thin strips; grey, BGR (equal or independent channels), or a non-contiguous view."""
    kind = draw(st.sampled_from(["noise", "blank", "checker", "salt_and_pepper", "smooth", "tiny", "strip"]))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    if kind == "tiny":
        h, w = draw(st.integers(1, 40)), draw(st.integers(1, 40))
    elif kind == "strip":
        h, w = draw(st.integers(1, 40)), draw(st.integers(41, 4000))
        if draw(st.booleans()):
            h, w = w, h
    else:
        h, w = draw(st.integers(1, max_h)), draw(st.integers(1, max_w))
    if kind == "blank":
        grey = np.full((h, w), draw(st.integers(0, 255)), np.uint8)
    else:
        grey = {"noise": _noise, "checker": _checker, "salt_and_pepper": _salt_and_pepper, "smooth": _smooth,
                "tiny": _smooth, "strip": _noise}[kind](rng, h, w)
    layout = draw(st.sampled_from(["grey", "bgr_same", "bgr", "flipped"]))
    if layout == "bgr_same":
        return np.dstack([grey] * 3)
    if layout == "bgr":
        return np.dstack([grey, _noise(rng, h, w), grey[::-1, ::-1]])
    if layout == "flipped":
        return grey[::-1, ::-1]
    return grey


@settings(derandomize=True, database=None, max_examples=150, deadline=None)
@given(image=images(), mode=st.sampled_from(ALL_MODES))
def test_any_image_fits_the_bound_and_decodes_consistently(image, mode):
    _check_valid(extract(image, mode), mode, image.shape[0], image.shape[1])


@pytest.mark.parametrize("kind", [_noise, _salt_and_pepper, _checker, _smooth])
@pytest.mark.parametrize("mode", ALL_MODES)
def test_every_kind_of_full_size_image_in_every_mode(kind, mode):
    """Full 480 x 640 frames of each kind, whatever examples hypothesis picks above."""
    image = kind(np.random.default_rng(mode), 480, 640)
    data = extract(image, mode)
    _check_valid(data, mode, 480, 640)
    assert len(decode(data)) > 0


@settings(derandomize=True, database=None, max_examples=6, deadline=None)
@given(h=st.integers(1281, 3000), w=st.integers(1281, 4000), seed=st.integers(0, 2**32 - 1),
       smooth=st.booleans(), mode=st.sampled_from(ALL_MODES))
def test_huge_images_fit_the_bound(h, w, seed, smooth, mode):
    rng = np.random.default_rng(seed)
    image = _smooth(rng, h, w) if smooth else _noise(rng, h, w)
    data = extract(image, mode)
    _check_valid(data, mode, h, w)
    d = decode(data)
    # Downscaled to max_side_px: the coordinate grid grows with the scale.
    assert d.position_step_px == pytest.approx(POSITION_STEP_PX * max(h, w) / 1280, rel=0.02)


@pytest.mark.parametrize("grey_level", [0, 1, 127, 254, 255])
@pytest.mark.parametrize("mode", ALL_MODES)
def test_blank_image_has_no_keypoints_and_costs_header_plus_global(grey_level, mode):
    data = extract(np.full((480, 640), grey_level, np.uint8), mode)
    assert len(data) == HEADER_BYTES + MODES[mode].global_bits // 8
    d = decode(data)
    assert len(d) == 0 and d.ternary().shape == (0, MODES[mode].length)
    assert not np.any(d.global_bits)  # nothing aggregated: every projection is 0, no sign bit set


@pytest.mark.parametrize("name", ["brick", "grass", "gravel"])
def test_floor_frames_fill_at_least_85_percent_of_every_budget(frames, name):
    counts = []
    for mode in ALL_MODES:
        data = extract(frames[name], mode)
        assert 0.85 * MODE_BYTES[mode] <= len(data) <= MODE_BYTES[mode], (mode, len(data))
        d = decode(data)
        _check_valid(data, mode, 480, 640)
        counts.append(len(d))
    assert all(b > a for a, b in zip(counts, counts[1:])), counts  # more bytes: more keypoints
    assert counts[0] >= 40 and counts[-1] >= 400, counts
    lengths = [MODES[m].length for m in ALL_MODES]
    assert all(b > a for a, b in zip(lengths, lengths[1:]))  # and longer local descriptors


def test_extraction_is_deterministic_and_layout_independent(frames):
    img = frames["grass"]
    for mode in (1, 4, 6):
        a = extract(img, mode)
        assert extract(img.copy(), mode) == a
        assert extract(np.dstack([img] * 3), mode) == a  # BGR with equal channels is the same grey
        assert extract(img[:, :, None], mode) == a
        assert extract(np.ascontiguousarray(img[::-1])[::-1], mode) == a  # a strided view
    assert extract(img, 3) != extract(frames["brick"], 3)


def test_describe_is_decode_of_extract(frames):
    d1, d2 = describe(frames["gravel"], 5), decode(extract(frames["gravel"], 5))
    for f in ("xy_px", "angle_rad", "local_pos", "local_neg", "global_bits"):
        assert np.array_equal(getattr(d1, f), getattr(d2, f))


# ----------------------------------------------------------------------------- round trip of the content

@pytest.mark.parametrize("mode", [1, 3, 6])
def test_decoded_keypoints_are_the_most_relevant_candidates(frames, mode):
    """Positions within half a grid step, angles within half a quantisation step, and the
    trits exactly as ternarised, for the ``n`` most relevant candidates that do not repeat
    in the image (within the pool the budget sizes), in coded order."""
    from robotd.floor.desccoding import cells, fit
    from robotd.floor.keypoints import repeat_pool

    img = frames["brick"]  # 640 px: the working image is the image itself
    params, learned = ExtractParams(), load_learned()
    c0 = candidates(img, params, learned)
    first = max(fit(MODES[mode], cells(c0.xy[:params.repeat_pool], 320, 240)) + 1, params.global_min_features)
    pool = ExtractParams(repeat_pool=repeat_pool(params, first, len(c0.xy)), repeat_pool_ratio=0.0)
    c, _ = drop_repeats(c0, pool)
    d = decode(extract(img, mode))
    n = len(d)
    assert 0 < n < len(c.xy)
    step = POSITION_STEP_PX
    col = ((c.xy[:n, 0] + 0.5) // step).astype(int)
    row = ((c.xy[:n, 1] + 0.5) // step).astype(int)
    order = np.lexsort((np.arange(n), col, row))  # row-major cells, ties in relevance order
    xy = c.xy[:n][order]
    assert np.all(np.abs(d.xy_px - xy) <= step / 2 + 1e-4)
    dang = np.abs(wrap_angle(d.angle_rad - c.angle[:n][order]))
    assert np.all(dang <= math.pi / 2**ANGLE_BITS + 1e-5)
    trits = ternarise(raw_descriptors(c, n, params), learned, MODES[mode].length)[order]
    assert np.array_equal(d.ternary(), trits.astype(np.float32))


def _blobs(h: int, w: int, centres: np.ndarray, sigma_px: float) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.full((h, w), 60.0)
    for x, y in centres:
        img += 120 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma_px**2))
    return np.round(img).astype(np.uint8)


@pytest.mark.parametrize("scale", [1, 3])
def test_keypoints_land_on_known_blobs(scale):
    """Twelve Gaussian blobs at sub-pixel positions: a keypoint within half a grid step
    (plus 0.35 step of detection error) of each, also in a downscaled 1920 x 1440 image."""
    rng = np.random.default_rng(4)
    h, w = 480 * scale, 640 * scale
    gx, gy = np.meshgrid((np.arange(4) + 0.5) * w / 4, (np.arange(3) + 0.5) * h / 3)
    centres = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-20, 20, (12, 2)) * scale
    # Twelve identical blobs repeat one another: keep them to test where keypoints land.
    d = describe(_blobs(h, w, centres, 4.0 * scale), 2, ExtractParams(repeat_distance=0.0))
    expected_step = POSITION_STEP_PX * max(1.0, w / 1280)
    assert d.position_step_px == pytest.approx(expected_step)
    err = np.abs(d.xy_px[None, :, :] - centres[:, None, :]).max(axis=2).min(axis=1)  # per blob, nearest keypoint
    assert np.all(err <= 0.85 * expected_step), err
    assert 12 <= len(d) <= 20  # the blobs, and at most a few ring responses


def _repeat_scene() -> tuple[np.ndarray, list[tuple[int, int]], tuple[int, int], int]:
    """A 640 x 480 grass image with one 160 px gravel crop pasted twice and another once.

    Returns the image, the two copies' top-left corners, the unique crop's corner and the
    crop size (offsets are even, so both copies fall on the same half-resolution grid).
    """
    img = cv2.resize(skimage.data.grass(), (640, 480), interpolation=cv2.INTER_CUBIC)
    size = 160
    gravel = skimage.data.gravel()
    crop, other = gravel[:size, :size], gravel[300:300 + size, 300:300 + size]
    copies, unique = [(120, 100), (380, 220)], (100, 290)
    for x, y in copies:
        img[y:y + size, x:x + size] = crop
    img[unique[1]:unique[1] + size, unique[0]:unique[0] + size] = other
    return img, copies, unique, size


def _inside(xy: np.ndarray, corner: tuple[int, int], size: int, margin: int) -> np.ndarray:
    x, y = corner
    return ((xy[:, 0] >= x + margin) & (xy[:, 0] < x + size - margin)
            & (xy[:, 1] >= y + margin) & (xy[:, 1] < y + size - margin))


@pytest.mark.parametrize("mode", [2, 4, 6])
def test_keypoints_that_repeat_in_the_image_are_not_coded(mode):
    """Where the image holds two copies of one texture, none of the copies' keypoints whose
    patch lies inside the copy is coded; a texture that appears once keeps its keypoints.
    With repeats kept (``repeat_distance=0``) the copies have keypoints like any texture."""
    img, copies, unique, size = _repeat_scene()
    margin = 40  # the descriptor patch (4 cells of 6 half-resolution px) plus the blur
    kept = describe(img, mode)
    every = describe(img, mode, ExtractParams(repeat_distance=0.0))
    for corner in copies:
        assert np.sum(_inside(every.xy_px, corner, size, margin)) >= 5
        assert np.sum(_inside(kept.xy_px, corner, size, margin)) == 0
    assert np.sum(_inside(kept.xy_px, unique, size, margin)) >= 5
    assert len(kept) >= 0.9 * len(every)  # the budget is filled with other keypoints


def test_drop_repeats_keeps_the_order_and_returns_the_kept_raw_descriptors():
    img, copies, _, size = _repeat_scene()
    params, learned = ExtractParams(), load_learned()
    c = candidates(img, params, learned)
    kept, raw = drop_repeats(c, params)
    assert 0 < len(kept.xy) < len(c.xy)
    # The kept candidates are a subsequence of the candidates, in relevance order.
    assert np.all(np.diff(kept.relevance) <= 0)
    idx = [int(np.flatnonzero(np.all(c.xy == p, axis=1))[0]) for p in kept.xy]
    assert idx == sorted(idx)
    assert np.array_equal(raw, raw_descriptors(kept, len(raw), params))
    # Nothing dropped with the check off; only checked candidates (the pool) are dropped.
    assert len(drop_repeats(c, ExtractParams(repeat_distance=0.0))[0].xy) == len(c.xy)
    small = ExtractParams(repeat_pool=50)
    kept_small, raw_small = drop_repeats(c, small)
    assert np.array_equal(kept_small.xy[len(raw_small):], c.xy[50:])


@pytest.mark.parametrize("mode", [1, 4, 6])
def test_kept_for_budget_prefiltered_by_the_pca_basis_decides_as_the_full_check(frames, mode):
    """The prefilter only skips pairs a projection proves far: same candidates, same raw
    descriptors, same count, with and without it; and the same as drop_repeats then fit."""
    from robotd.floor.desccoding import cells, fit
    from robotd.floor.keypoints import kept_for_budget

    img = frames["gravel"]
    params, learned = ExtractParams(repeat_pool_ratio=0.0), load_learned()
    c = candidates(img, params, learned)
    grid_w, grid_h = 320, 240
    plain = kept_for_budget(c, params, MODES[mode], grid_w, grid_h)
    pre = kept_for_budget(c, params, MODES[mode], grid_w, grid_h, basis=learned.pca_basis)
    assert plain[2] == pre[2] > 0 and np.array_equal(plain[1], pre[1])
    assert np.array_equal(plain[0].xy, pre[0].xy)
    kept, _ = drop_repeats(c, params)
    assert pre[2] == fit(MODES[mode], cells(kept.xy, grid_w, grid_h))
    m = max(pre[2] + 1, params.global_min_features)
    assert np.array_equal(pre[0].xy[:m], kept.xy[:m])


@pytest.mark.parametrize("mode", [1, 4, 6])
def test_repeat_pool_ratio_checks_a_pool_sized_by_the_budget(frames, mode):
    """With ``repeat_pool_ratio`` the repeat check takes that many times what the budget
    codes (or the global minimum) plus one, capped by ``repeat_pool``: the same as
    drop_repeats with that pool, then fit; on a frame of the repeated scene it drops
    repeats as the full pool does."""
    from robotd.floor.desccoding import cells, fit
    from robotd.floor.keypoints import kept_for_budget, repeat_pool

    img = frames["gravel"]
    learned = load_learned()
    params = ExtractParams(repeat_pool_ratio=1.5)
    c = candidates(img, params, learned)
    grid_w, grid_h = 320, 240
    n0 = fit(MODES[mode], cells(c.xy[:params.repeat_pool], grid_w, grid_h))
    first = max(n0 + 1, params.global_min_features)
    pool = repeat_pool(params, first, len(c.xy))
    assert pool == min(math.ceil(1.5 * first), params.repeat_pool, len(c.xy)) < len(c.xy)
    kept, raw, n = kept_for_budget(c, params, MODES[mode], grid_w, grid_h, basis=learned.pca_basis)
    ref, ref_raw = drop_repeats(c, ExtractParams(repeat_pool=pool, repeat_pool_ratio=0.0))
    assert n == fit(MODES[mode], cells(ref.xy, grid_w, grid_h))
    m = max(n + 1, params.global_min_features)
    assert np.array_equal(kept.xy[:m], ref.xy[:m]) and np.array_equal(raw[:m], ref_raw[:m])
    assert repeat_pool(ExtractParams(repeat_pool_ratio=0.0), first, len(c.xy)) == min(1000, len(c.xy))


def test_workspace_gives_what_fresh_arrays_give(frames):
    """Candidates computed in a reused workspace (as extract does) equal those computed in
    fresh arrays, also after the workspace held another image and for the maps at half
    resolution; and extract's bytes do not depend on what the thread described before."""
    from robotd.floor.keypoints import Workspace

    learned = load_learned()
    ws = Workspace(240, 320)
    for params in (ExtractParams(), ExtractParams(pool_step=1), ExtractParams(pool_step=2, orientation_step=2),
                   ExtractParams(exact_maps=True), ExtractParams(pool_step=1, orientation_step=1, exact_maps=True),
                   ExtractParams(detect_step=2), ExtractParams(detect_step=2, exact_maps=True)):
        for name in ("brick", "grass", "brick"):
            fresh = candidates(frames[name], params, learned)
            reused = candidates(frames[name], params, learned, ws)
            for a, b in zip(fresh[:4], reused[:4]):
                assert np.array_equal(a, b)
            for a, b in zip(fresh.pooled, reused.pooled):
                assert np.array_equal(a, b)
            assert np.array_equal(raw_descriptors(fresh, 300, params), raw_descriptors(reused, 300, params, ws))
    first = [extract(frames[n], 4) for n in ("gravel", "brick")]
    assert [extract(frames[n], 4) for n in ("gravel", "brick")] == first
    assert extract(frames["brick"], 4) == first[1]


def test_fit_from_any_hint_is_the_largest_prefix_that_fits():
    from robotd.floor.desccoding import fit, size

    def bisect(spec, cells):  # the size grows with every keypoint: plain bisection from [0, len]
        lo, hi = 0, len(cells)
        while lo < hi:
            mid = (lo + hi + 1) // 2
            lo, hi = (mid, hi) if size(spec, np.sort(cells[:mid])) <= spec.bytes else (lo, mid - 1)
        return lo

    rng = np.random.default_rng(5)
    for _ in range(15):
        cells = rng.choice(320 * 240, size=int(rng.integers(0, 2500)), replace=False).astype(np.int64)
        for mode in (1, 4, 6):
            spec = MODES[mode]
            want = bisect(spec, cells)
            assert size(spec, np.sort(cells[:want])) <= spec.bytes
            assert want == len(cells) or size(spec, np.sort(cells[:want + 1])) > spec.bytes
            for hint in (None, 0, 7, len(cells), 10_000, int(rng.integers(0, 2500))):
                assert fit(spec, cells, hint) == want


@pytest.mark.parametrize("step", [1, 2])
def test_orientation_maps_at_half_resolution_keep_the_descriptor_close(frames, step):
    """The maps kept at every second pixel are a coarser sampling of the same smooth maps:
    the raw descriptors of the same keypoints stay far closer to those at full resolution
    than two views of one floor point are (0.3 apart is the 90th percentile of those)."""
    img = frames["grass"]
    learned = load_learned()
    full = ExtractParams(pool_step=1, orientation_step=1)
    half = ExtractParams(pool_step=2, orientation_step=step)
    c1, c2 = candidates(img, full, learned), candidates(img, half, learned)
    assert np.array_equal(c1.xy[np.argsort(c1.xy[:, 0] * 1e4 + c1.xy[:, 1])],
                          c2.xy[np.argsort(c2.xy[:, 0] * 1e4 + c2.xy[:, 1])])  # same keypoints
    if step == 1:
        assert np.array_equal(c1.xy, c2.xy) and np.array_equal(c1.angle, c2.angle)
    n = 300
    # The same keypoints in c1's order, with c2's orientation and maps.
    at = {tuple(p): i for i, p in enumerate(c2.xy.tolist())}
    idx = np.array([at[tuple(p)] for p in c1.xy[:n].tolist()])
    c2n = c2._replace(xy=c2.xy[idx], angle=c2.angle[idx])
    dist = np.linalg.norm(raw_descriptors(c1, n, full) - raw_descriptors(c2n, n, half), axis=1)
    assert np.median(dist) < 0.15 and np.mean(dist < 0.3) > 0.9
    dang = np.abs(wrap_angle(c2.angle[idx] - c1.angle[:n]))
    assert np.median(dang) < (0.01 if step == 1 else 0.05)


def test_extract_params_repeat_fields_out_of_range():
    with pytest.raises(ValueError):
        ExtractParams(repeat_distance=-0.1)
    with pytest.raises(ValueError):
        ExtractParams(repeat_pool=-1)
    with pytest.raises(ValueError):
        ExtractParams(repeat_pool_ratio=-0.5)
    for bad in ({"pool_step": 3}, {"pool_step": 0}, {"orientation_step": 4}, {"detect_step": 0}, {"detect_step": 3}):
        with pytest.raises(ValueError, match="out of range"):
            ExtractParams(**bad)


# ----------------------------------------------------------------------------- bad arguments

@pytest.mark.parametrize("mode", [0, 7, -1, 2.0, 1.5, True, "1", None])
def test_unknown_mode_is_a_value_error(mode):
    with pytest.raises(ValueError, match="mode must be one of"):
        extract(np.zeros((64, 64), np.uint8), mode)


def test_numpy_integer_modes_are_accepted():
    img = np.zeros((64, 64), np.uint8)
    assert extract(img, np.int64(3)) == extract(img, 3)


@pytest.mark.parametrize("image, message", [
    (np.zeros((48, 64), np.float32), "uint8"),
    (np.zeros((48, 64), np.uint16), "uint8"),
    (np.zeros((48, 64), bool), "uint8"),
    (np.zeros((48, 64, 2), np.uint8), "shape"),
    (np.zeros((2, 48, 64), np.uint8), "shape"),
    (np.zeros((0, 64), np.uint8), "shape"),
    (np.zeros(64, np.uint8), "shape"),
    (np.zeros((1, 65536), np.uint8), "65535"),
    (np.zeros((65536, 1), np.uint8), "65535"),
])
def test_bad_image_is_a_value_error(image, message):
    with pytest.raises(ValueError, match=message):
        extract(image, 1)


def test_largest_allowed_side_is_accepted():
    data = extract(np.zeros((1, 65535), np.uint8), 1)
    assert decode(data).width_px == 65535


def test_extract_params_out_of_range():
    with pytest.raises(ValueError, match="out of range"):
        ExtractParams(max_side_px=16)
    with pytest.raises(ValueError, match="out of range"):
        ExtractParams(dog_ratio=1.0)


# ----------------------------------------------------------------------------- damaged bytes

@pytest.mark.parametrize("mode", ALL_MODES)
def test_every_single_byte_change_is_caught(coded, mode):
    """CRC-32 catches every burst of up to 32 bits, so every changed byte anywhere
    (header, checksum, every section, the tail) must give DescriptorError."""
    data = coded[mode]
    names = {name for name, start, end in _sections(data) if end > start}
    assert names == {"header", "crc", "global", "rice remainders", "angles", "trits", "unary"}
    rng = np.random.default_rng(mode)
    masks = rng.integers(1, 256, len(data))
    b = bytearray(data)
    for i in range(len(data)):
        for mask in ((1 << (i % 8)), int(masks[i])):
            b[i] ^= mask
            with pytest.raises(DescriptorError):
                decode(bytes(b))
            b[i] ^= mask
    assert decode(bytes(b)).mode == mode  # restored


@pytest.mark.parametrize("mode", [1, 6])
def test_every_truncation_is_caught(coded, mode):
    data = coded[mode]
    for cut in range(len(data)):
        with pytest.raises(DescriptorError, match="truncated|checksum"):
            decode(data[:cut])


def test_messages_name_the_problem(coded):
    data = coded[2]
    cases = [
        (b"", "truncated: 0 bytes"),
        (data[:10], "truncated: 10 bytes"),
        (b"XY" + data[2:], "bad magic"),
        (data[:2] + bytes([2]) + data[3:], "unsupported version 2"),
        (data[:3] + bytes([0]) + data[4:], "bad mode 0"),
        (data[:3] + bytes([9]) + data[4:], "bad mode 9"),
        (data[:3] + bytes([1]) + data[4:], "exceed mode 1's bound of 512"),
        (data + bytes(MODE_BYTES[2] - len(data) + 1), "exceed mode 2's bound of 1024"),
        (data[:-1] + bytes([data[-1] ^ 0x10]), "checksum mismatch"),  # (data may fill its bound exactly)
    ]
    for bad, message in cases:
        with pytest.raises(DescriptorError, match=re.escape(message)) as e:
            decode(bad)
        assert str(e.value).startswith("floor descriptor: ")
    assert issubclass(DescriptorError, RobotdError)


@pytest.mark.parametrize("value", ["FD", 42, None, [70, 68], np.frombuffer(b"FD", np.uint8)])
def test_non_bytes_is_a_descriptor_error(value):
    with pytest.raises(DescriptorError, match="expected bytes"):
        decode(value)


def test_bytearray_and_memoryview_decode_like_bytes(coded):
    data = coded[3]
    ref = decode(data)
    for view in (bytearray(data), memoryview(data)):
        assert np.array_equal(decode(view).xy_px, ref.xy_px)


@settings(derandomize=True, database=None, max_examples=150, deadline=None)
@given(st.binary(max_size=2048))
def test_random_bytes_are_a_descriptor_error(data):
    with pytest.raises(DescriptorError):
        decode(data)


@settings(derandomize=True, database=None, max_examples=150, deadline=None)
@given(mode=st.sampled_from(ALL_MODES), body=st.binary(min_size=0, max_size=600), n=st.integers(0, 80),
       k=st.integers(0, 20), size=st.tuples(st.integers(0, 700), st.integers(0, 700)))
def test_random_bodies_with_a_correct_checksum_never_crash(mode, body, n, k, size):
    """A valid magic, version, mode and CRC over garbage: decoded or DescriptorError, never
    another exception; what decodes keeps every documented invariant."""
    head = struct.pack("<2sBBHHHHHBBI", b"FD", 1, mode, size[0], size[1], size[0], size[1], n, k, 0, 0)
    data = _with_crc(head + body)
    try:
        d = decode(data)
    except DescriptorError:
        return
    _check_valid(data, mode, size[1], size[0])
    assert len(d) == n


# ----------------------------------------------------------------------------- forged bytes (CRC recomputed)

def test_forged_header_fields_are_caught(coded):
    data = coded[4]
    _, _, _, width, height, ww, wh, n, k, _, _ = struct.unpack_from("<2sBBHHHHHBBI", data)
    forged = {
        "n + 1": dict(n=n + 1), "n - 1": dict(n=n - 1), "n = 0": dict(n=0), "n = 65535": dict(n=65535),
        "k + 1": dict(k=k + 1), "k - 1": dict(k=k - 1), "k = 17": dict(k=17), "k = 255": dict(k=255),
        "reserved": dict(reserved=1), "work wider than image": dict(work_width=width + 1),
        "work taller than image": dict(work_height=height + 1), "zero work width": dict(work_width=0),
        "zero size": dict(width=0, height=0, work_width=0, work_height=0),
        "positions outside the image": dict(height=20, work_height=20),
    }
    for label, fields in forged.items():
        with pytest.raises(DescriptorError):
            decode(_set_header(data, **fields))
            pytest.fail(f"forged {label} decoded")


def test_forged_sections_are_caught(coded):
    data = coded[3]
    s = {name: (start, end) for name, start, end in _sections(data)}
    trits = bytearray(data)
    trits[s["trits"][0]] = 243  # 3**5: not five trits
    with pytest.raises(DescriptorError, match="bad descriptor code"):
        decode(_with_crc(trits))
    for label, bad in [("extra 0x00: another terminator", data + b"\x00"),
                       ("extra 0xFF: padding of 8 or more bits", data + b"\xff"),
                       ("a unary byte dropped", data[:-1]),
                       ("all unary zeros", data[:s["unary"][0]] + bytes(s["unary"][1] - s["unary"][0])),
                       ("no unary part", data[:s["unary"][0]]),
                       ("body cut inside the trits", data[:s["trits"][0] + 3])]:
        with pytest.raises(DescriptorError, match="position code|truncated"):
            decode(_with_crc(bad))
            pytest.fail(f"forged {label} decoded")


def _trit_bytes(trits: list[int]) -> bytes:
    """Trits in {-1, 0, 1}, five per byte, the first as the least significant base-3 digit."""
    digits = [t + 1 for t in trits] + [0] * (-len(trits) % 5)
    return bytes(sum(d * 3**i for i, d in enumerate(digits[j:j + 5])) for j in range(0, len(digits), 5))


def _hand_made(height: int) -> bytes:
    """A mode-1 descriptor of a 64 x ``height`` image built bit by bit from the layout:
    two keypoints in grid cells 5 and 70 (32 cells per row), Rice k = 2."""
    # gaps 5 = 1 << 2 | 1 and 65 = 16 << 2 | 1: remainders 01 01, quotients 1 and 16.
    remainders = bytes([0b0101_0000])
    angles = bytes([0b00011_111, 0b11_000000])  # levels 3 and 31, 5 bits each
    t = [0] * 48
    t[0], t[24 + 1], t[47] = 1, -1, 1
    unary = bytes([0b10_111111, 0b11111111, 0b110_11111])  # "10", 16 ones and "0", padding ones
    glob = bytes(range(32))
    head = struct.pack("<2sBBHHHHHBBI", b"FD", 1, 1, 64, height, 64, height, 2, 2, 0, 0)
    return _with_crc(head + glob + remainders + angles + _trit_bytes(t) + unary)


def test_hand_made_descriptor_decodes_to_its_values():
    d = decode(_hand_made(48))
    assert (d.mode, d.width_px, d.height_px, len(d), d.length) == (1, 64, 48, 2, 24)
    assert np.array_equal(d.xy_px, np.array([[10.5, 0.5], [12.5, 4.5]], np.float32))  # cell centres
    assert np.allclose(d.angle_rad, np.array([3, 31]) * 2 * math.pi / 32)
    expected = np.zeros((2, 24), np.float32)
    expected[0, 0], expected[1, 1], expected[1, 23] = 1, -1, 1
    assert np.array_equal(d.ternary(), expected)
    assert np.array_equal(d.global_bits, np.arange(32, dtype=np.uint8))


def _read_bit_by_bit(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray, bytes]:
    """The byte layout of the module docstring read one bit, one trit, one keypoint at a
    time (no numpy): positions ``(n, 2)``, angles ``(n,)``, trits ``(n, length)`` and the
    global bits, for :func:`decode` to match."""
    _magic, _version, mode, width, height, ww, wh, n, k, _reserved, _crc = struct.unpack_from(
        "<2sBBHHHHHBBI", data)
    length, pos = MODES[mode].length, HEADER_BYTES

    def section(size: int) -> bytes:
        nonlocal pos
        pos += size
        return data[pos - size:pos]

    def msb_bits(raw: bytes) -> list[int]:
        return [(byte >> (7 - i)) & 1 for byte in raw for i in range(8)]

    glob = section(MODES[mode].global_bits // 8)
    rem = msb_bits(section(-(-n * k // 8)))
    ang = msb_bits(section(-(-n * ANGLE_BITS // 8)))
    trits = [(byte // 3**i) % 3 - 1 for byte in section(-(-n * length // 5)) for i in range(5)]
    unary = msb_bits(data[pos:])
    grid_w, step = -(-ww // POSITION_STEP_PX), POSITION_STEP_PX
    xy, angles, ternary = [], [], np.zeros((n, length), np.float32)
    cell = u = 0
    for i in range(n):
        quotient = 0
        while unary[u]:
            quotient, u = quotient + 1, u + 1
        u += 1
        cell += (quotient << k) + sum(b << (k - 1 - j) for j, b in enumerate(rem[i * k:(i + 1) * k]))
        col, row = cell % grid_w, cell // grid_w
        xy.append(((col * step + (step - 1) / 2 + 0.5) * (width / ww) - 0.5,
                   (row * step + (step - 1) / 2 + 0.5) * (height / wh) - 0.5))
        level = sum(b << (ANGLE_BITS - 1 - j) for j, b in enumerate(ang[i * ANGLE_BITS:(i + 1) * ANGLE_BITS]))
        angles.append(level * (2 * math.pi / 2**ANGLE_BITS))
        ternary[i] = trits[i * length:(i + 1) * length]
    return (np.array(xy, np.float32).reshape(n, 2), np.array(angles, np.float32), ternary, glob)


@pytest.mark.parametrize("mode", ALL_MODES)
def test_decode_gives_what_the_layout_read_bit_by_bit_gives(frames, coded, mode):
    """The whole-array decode against the layout read one bit at a time: every position,
    angle and trit exactly, and the bit planes' padding beyond ``length`` zero."""
    for data in (coded[mode], extract(frames["gravel"], mode), _hand_made(48) if mode == 1 else coded[mode]):
        d = decode(data)
        xy, angles, ternary, glob = _read_bit_by_bit(data)
        assert len(d) > 1
        assert d.xy_px.dtype == np.float32 and np.array_equal(d.xy_px, xy)
        assert d.angle_rad.dtype == np.float32 and np.array_equal(d.angle_rad, angles)
        assert np.array_equal(d.ternary(), ternary)
        assert d.global_bits.tobytes() == glob
        words = -(-d.length // 64)
        for plane in (d.local_pos, d.local_neg):
            assert plane.dtype == np.uint64 and plane.shape == (len(d), words) and plane.flags.c_contiguous
            every_bit = np.unpackbits(plane.astype("<u8").view(np.uint8), axis=1, bitorder="little")
            assert not every_bit[:, d.length:].any()
        assert not (d.local_pos & d.local_neg).any()


def test_forged_position_beyond_the_grid_is_caught():
    """Cell 70 needs three rows of 32 cells: a 64 x 4 image has two."""
    with pytest.raises(DescriptorError, match="outside the image"):
        decode(_hand_made(4))
    assert len(decode(_hand_made(6))) == 2  # three rows: cell 70 fits


def test_only_an_orthonormal_pca_basis_prefilters_the_repeat_check():
    """The prefilter is exact only for orthonormal columns (an SVD's): a learned table
    with any other basis gets the full check."""
    from dataclasses import replace

    from robotd.floor.descriptor import _orthonormal_basis

    learned = load_learned()
    assert _orthonormal_basis(learned) is not None
    assert _orthonormal_basis(replace(learned, pca_basis=learned.pca_basis * 1.5)) is None
    skew = learned.pca_basis.copy()
    skew[:, 1] += 0.3 * skew[:, 0]
    assert _orthonormal_basis(replace(learned, pca_basis=skew)) is None


@pytest.mark.parametrize("name", ["brick", "gravel"])
def test_table_split_is_within_a_64th_of_the_magnitude_of_the_exact_split(frames, name):
    """The orientation channels looked up in the 256-angle table differ from the exact
    linear split by at most 1/64 of the gradient's magnitude in each channel (the angle is
    off by at most half a level, 1/64 of a direction bin), so the pooled maps differ by at
    most the pooled magnitude / 64; and they are not the exact maps (the table is used)."""
    from robotd.floor.keypoints import Workspace, _pooled_orientation_maps

    x = cv2.GaussianBlur(cv2.resize(frames[name], (320, 240), interpolation=cv2.INTER_AREA).astype(np.float32),
                         (0, 0), 1.8)
    sigma = 2.5
    exact = [m.copy() for m in _pooled_orientation_maps(x, sigma, Workspace(240, 320), exact=True)]
    table = _pooled_orientation_maps(x, sigma, Workspace(240, 320), exact=False)
    k = 2 * math.ceil(2 * sigma) + 1
    mag = cv2.GaussianBlur(cv2.magnitude(cv2.Sobel(x, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(x, cv2.CV_32F, 0, 1, ksize=1)),
                           (k, k), sigma)
    for e, t in zip(exact, table):
        err = np.abs(e - t).max(axis=2)
        assert np.all(err <= mag / 64 + 1e-4 * (1 + mag))
        assert err.max() > 0
    # The 8 channels of each pixel still sum to its pooled magnitude.
    total = exact[0].sum(2) + exact[1].sum(2)
    assert np.allclose(table[0].sum(2) + table[1].sum(2), total, rtol=1e-4, atol=1e-4)


def test_default_and_full_resolution_descriptors_of_one_frame_match(frames):
    """A map described with :data:`FULL_RESOLUTION` (the bytes before the faster defaults)
    still matches frames described with the defaults: the same frame described both ways
    keeps most keypoints (positions identical: the detection is the same) and scores
    nearly what it scores against itself, and another floor does not match it."""
    from robotd.floor.descriptor import FULL_RESOLUTION
    from robotd.floor.match import local_score

    for name in ("brick", "grass"):
        new, old = decode(extract(frames[name], 4)), decode(extract(frames[name], 4, FULL_RESOLUTION))
        shared = {tuple(p) for p in new.xy_px.tolist()} & {tuple(p) for p in old.xy_px.tolist()}
        assert len(shared) >= 0.8 * len(old)
        self_score = local_score(old, old).score
        assert local_score(new, old).score >= 0.7 * self_score > 0
    other = decode(extract(frames["gravel"], 4, FULL_RESOLUTION))
    assert local_score(decode(extract(frames["brick"], 4)), other).score < 0.1 * local_score(other, other).score


def test_maps_halved_from_every_pixels_gradients_stay_closer_than_maps_of_the_halved_image(frames):
    """With ``pool_step`` 2 the default splits the gradients of every pixel and halves the
    channels; ``exact_maps`` takes the gradients of the halved image. Both pool a quarter of
    the pixels, but the first keeps the fine gradients: the raw descriptors of the same
    keypoints stay well under half as far from those pooled at every pixel."""
    img = frames["gravel"]
    learned = load_learned()
    full = ExtractParams(pool_step=1, exact_maps=True)
    c_full = candidates(img, full, learned)
    ref = raw_descriptors(c_full, 300, full)
    dist = {}
    for name, params in (("halved", ExtractParams()), ("coarse", ExtractParams(exact_maps=True))):
        c = candidates(img, params, learned)
        assert np.array_equal(c.xy, c_full.xy) and np.array_equal(c.angle, c_full.angle)  # same keypoints
        dist[name] = np.median(np.linalg.norm(raw_descriptors(c, 300, params) - ref, axis=1))
    assert dist["halved"] < 0.5 * dist["coarse"]
    assert dist["halved"] < 0.06


@pytest.mark.parametrize("prefilter", [False, True])
def test_candidates_of_the_quarter_image_land_on_the_default_keypoints(frames, prefilter):
    """``detect_step`` 2 (:data:`QUARTER`) finds the candidates on the detection image
    halved, at the same scale, and gives positions in working-image pixels as the default
    does: most of the default's most relevant keypoints have a quarter-image candidate
    within 2 px (a position off by the factor of the halving would land far away), and
    the same frame described both ways keeps much of its self-score, another floor none.
    So with ``detect_prefilter`` (the quarter image from the low-passed detection image),
    whose candidates are not those of the box-averaged quarter image."""
    import dataclasses

    from robotd.floor.descriptor import QUARTER as PLAIN
    from robotd.floor.match import local_score

    QUARTER = dataclasses.replace(PLAIN, detect_prefilter=prefilter)  # noqa: N806
    learned = load_learned()
    if prefilter:
        a, b = candidates(frames["brick"], PLAIN, learned), candidates(frames["brick"], QUARTER, learned)
        assert len(a.xy) != len(b.xy) or not np.array_equal(a.xy, b.xy)
    for name in ("brick", "grass", "gravel"):
        ref = candidates(frames[name], ExtractParams(), learned)
        c = candidates(frames[name], QUARTER, learned)
        assert 0.5 * len(ref.xy) < len(c.xy) < 1.5 * len(ref.xy)
        d = np.linalg.norm(ref.xy[:300, None, :] - c.xy[None, :, :], axis=2).min(axis=1)
        assert np.mean(d < 2.0) >= 0.7, np.mean(d < 2.0)
        assert np.median(d) < 1.0
        assert raw_descriptors(c, 300, QUARTER).shape == (min(300, len(c.xy)), 128)
    for mode in MODES:  # the byte bound holds for it too
        assert len(extract(frames["grass"], mode, QUARTER)) <= MODE_BYTES[mode]
    quarter = decode(extract(frames["brick"], 4, QUARTER))
    default = decode(extract(frames["brick"], 4))
    other = decode(extract(frames["gravel"], 4, QUARTER))
    self_score = local_score(default, default).score
    assert local_score(quarter, default).score >= 0.4 * self_score > 0
    assert local_score(other, default).score < 0.1 * self_score


def test_prefiltered_quarter_image_aliases_less_on_the_printed_planks():
    """The printed plank floor's views a lattice step apart (as ``tests/floor/test_match.py``
    renders them): the quarter image box-averaged from the working image (:data:`QUARTER`)
    folds the print's fine texture into the detection's band, its extrema move between
    copies of one print, the repeat check misses them, and the view a lattice step away
    scores about as much as the true 5 cm overlap. With ``detect_prefilter`` it scores
    markedly less in every mode the alias test checks (yet not under its half: the default
    detection's is)."""
    import dataclasses

    from robotd.floor.descriptor import QUARTER, describe
    from robotd.floor.match import local_score
    from sim.world.pattern import PatternFloor, PatternParams

    floor = PatternFloor(skimage.data.gravel(), PatternParams(kind="planks"), 0.001, seed=1)
    renderer = FloorRenderer(floor, FloorCameraModel.default(), RenderParams(), np.random.default_rng(0))
    here = np.array([1.108, 0.255, -1.926])
    ahead = 0.05 * np.array([math.cos(here[2]), math.sin(here[2]), 0.0])
    views = {name: renderer.render(here + d, 0.0, 0.0, 0.0)
             for name, d in (("here", np.zeros(3)), ("lattice", np.array([0.15, 0.12, 0.0])), ("near", ahead))}

    def alias_ratio(params: ExtractParams, mode: int) -> float:
        h = describe(views["here"], mode, params)
        return (local_score(h, describe(views["lattice"], mode, params)).score
                / local_score(h, describe(views["near"], mode, params)).score)

    for mode in (2, 3, 5):
        plain = alias_ratio(QUARTER, mode)
        prefiltered = alias_ratio(dataclasses.replace(QUARTER, detect_prefilter=True), mode)
        assert prefiltered < 0.85 * plain, (mode, prefiltered, plain)


def test_orientation_read_from_the_pooled_maps_is_near_the_smoothed_gradients(frames):
    """``orientation_from_maps``: the 8 pooled direction maps summed as vectors and smoothed
    by what the orientation's sigma lacks are the gradient of the image smoothed at
    ``orientation_sigma_px``, up to the linear split's error: the same candidates (positions,
    responses) with orientations within a degree at the median and a few at the 90th
    percentile of those at every pixel (a wrong direction vector, sign or axis would put
    them tens of degrees off), and strengths within a tenth."""
    learned = load_learned()
    maps = ExtractParams(orientation_from_maps=True)
    for name in ("brick", "grass", "gravel"):
        ref = candidates(frames[name], ExtractParams(), learned)
        c = candidates(frames[name], maps, learned)
        ia, ib = np.lexsort(ref.xy.T[::-1]), np.lexsort(c.xy.T[::-1])
        assert np.array_equal(ref.xy[ia], c.xy[ib])
        assert np.array_equal(ref.attributes[ia, :3], c.attributes[ib, :3])
        off = np.abs(wrap_angle(c.angle[ib].astype(np.float64) - ref.angle[ia]))
        strength = c.attributes[ib, 3] / ref.attributes[ia, 3]
        top = np.argsort(-ref.relevance[ia])[:300]
        assert np.degrees(np.median(off[top])) < 1.0, np.degrees(np.median(off[top]))
        assert np.degrees(np.percentile(off[top], 90)) < 4.0
        assert 0.9 < np.median(strength[top]) < 1.0
    with pytest.raises(ValueError):
        ExtractParams(orientation_from_maps=True, detect_step=2)
