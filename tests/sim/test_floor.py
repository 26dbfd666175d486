"""The quilted floor: determinism, no repeats, real texture, tiles, patches, sources."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data

from robotd.base.errors import ConfigError
from sim.world.floor import Floor, FloorParams, ImageFloor


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a.astype(np.float64) - a.mean()
    b = b.astype(np.float64) - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _sharpness(img: np.ndarray) -> float:
    """High-frequency energy relative to contrast (Laplacian std / image std)."""
    f = img.astype(np.float32)
    return float(np.std(cv2.Laplacian(f, cv2.CV_32F)) / np.std(f))


@pytest.fixture(scope="module")
def gravel_floor() -> Floor:
    return Floor.from_photos([skimage.data.gravel()], seed=5)


def test_tiles_do_not_depend_on_generation_order() -> None:
    keys = [(tx, ty) for tx in (-2, -1, 0, 3) for ty in (-1, 0, 2)]
    a = Floor.default(seed=11)
    b = Floor.default(seed=11)
    tiles_a = {k: a.tile(*k).copy() for k in keys}
    tiles_b = {k: b.tile(*k).copy() for k in reversed(keys)}
    for k in keys:
        assert np.array_equal(tiles_a[k], tiles_b[k]), k
    # A different seed is a different floor.
    c = Floor.default(seed=12)
    assert not np.array_equal(c.tile(0, 0), tiles_a[(0, 0)])


def test_patch_is_the_same_floor_whatever_the_request(gravel_floor: Floor) -> None:
    big, aff_big = gravel_floor.patch(-0.3, -0.2, 0.4, 0.3)
    small, aff_small = gravel_floor.patch(0.05, 0.0, 0.25, 0.1)
    mpp = gravel_floor.metres_per_px
    assert aff_big[0, 0] == pytest.approx(1.0 / mpp) and aff_big[1, 1] == pytest.approx(-1.0 / mpp)
    # World points on the pixel grid land on integer pixels in both patches with the same value.
    pts = np.array([[0.05, 0.0], [0.1, 0.05], [0.25, 0.1], [0.137, 0.071]])
    for x, y in pts:
        cb, rb = aff_big @ [x, y, 1.0]
        cs, rs = aff_small @ [x, y, 1.0]
        assert abs(cb - round(cb)) < 1e-6 and abs(cs - round(cs)) < 1e-6
        assert big[round(rb), round(cb)] == small[round(rs), round(cs)]
    # North is up: the first row is the rectangle's top edge (largest y).
    assert (aff_small @ [0.05, 0.1, 1.0])[1] == pytest.approx(0.0, abs=1e-6)


def test_tiles_join_without_visible_edges(gravel_floor: Floor) -> None:
    img, aff = gravel_floor.patch(-0.5, -0.5, 0.5, 0.5)
    f = img.astype(np.float32)
    col_steps = np.abs(np.diff(f, axis=1)).mean(axis=0)  # step between column c and c+1
    n = gravel_floor.params.tile_px
    c0 = int(round(aff[0, 2]))  # patch column of world x = 0, a tile edge
    edges = [c for c in range(len(col_steps)) if (c - c0 + 1) % n == 0]
    assert edges, "the patch must contain a tile edge"
    typical = np.median(col_steps)
    for c in edges:
        assert col_steps[c] < 1.3 * typical


def test_no_view_sized_region_repeats(gravel_floor: Floor) -> None:
    a, _ = gravel_floor.patch(0.1, 0.1, 0.74, 0.58)
    b, _ = gravel_floor.patch(1.3, 0.2, 1.94, 0.68)
    a = a[:480, :640]
    b = b[:480, :640]
    assert abs(_ncc(a, b)) < 0.1
    # Search the centre of view a anywhere in a 1.2 x 1.2 m area around view b,
    # at any of 12 rotations: nothing is a copy (a copy scores ~1).
    search, _ = gravel_floor.patch(1.0, -0.2, 2.2, 1.0)
    search = search.astype(np.float32)
    best = 0.0
    for angle in range(0, 360, 30):
        rot = cv2.getRotationMatrix2D((320.0, 240.0), angle, 1.0)
        tmpl = cv2.warpAffine(a.astype(np.float32), rot, (640, 480))[160:320, 240:400]
        best = max(best, float(cv2.matchTemplate(search, tmpl, cv2.TM_CCOEFF_NORMED).max()))
    assert best < 0.3
    # Control: the same measure on a tiled photo finds the exact repeat.
    tiled = ImageFloor(np.tile(skimage.data.gravel(), (4, 4)))
    ta, _ = tiled.patch(0.1, -0.58, 0.74, -0.1)
    tb, _ = tiled.patch(0.612, -1.092, 1.252, -0.612)
    assert _ncc(ta[:480, :640], tb[:480, :640]) > 0.99


def test_floor_keeps_the_photo_detail(gravel_floor: Floor) -> None:
    img, _ = gravel_floor.patch(0.0, 0.0, 0.64, 0.48)
    photo = skimage.data.gravel()
    # Native-scale blocks: as much fine detail as the photo itself (upsampling by 2 would
    # roughly halve this, wide blending would lower it too).
    assert _sharpness(img) > 0.85 * _sharpness(photo)
    # Contrast kept and mildly normalised towards the target.
    p = gravel_floor.params
    assert abs(float(img.mean()) - p.target_mean) < 12.0
    assert 0.7 * p.target_std < float(img.std()) < 1.4 * p.target_std
    upsampled = cv2.resize(photo[:240, :320], (640, 480), interpolation=cv2.INTER_LINEAR)
    assert _sharpness(upsampled) < 0.6 * _sharpness(photo)  # the measure sees blur


def test_default_floor_uses_distinct_photo_regions() -> None:
    floor = Floor.default(seed=3)
    assert floor.source_names == ["skimage:brick", "skimage:grass", "skimage:gravel"]
    xs, ys = np.meshgrid(np.arange(-6.0, 6.0, 0.05), np.arange(-6.0, 6.0, 0.05))
    src = floor.region_source_at(xs, ys)
    counts = np.bincount(src.ravel(), minlength=3)
    assert np.all(counts > 0.1 * src.size)
    # Regions are a few metres across: neighbouring 5 cm samples rarely change photo...
    changes = np.mean(src[:, 1:] != src[:, :-1])
    assert 0.002 < changes < 0.05
    # ...and region borders wobble: they are longer than the straight borders of the same
    # layout without wobble (a Voronoi diagram of the region centres).
    straight = Floor.default(seed=3, region_wobble_m=0.0).region_source_at(xs, ys)

    def border_length(s: np.ndarray) -> int:
        return int(np.sum(s[:, 1:] != s[:, :-1]) + np.sum(s[1:, :] != s[:-1, :]))

    assert border_length(src) > 1.08 * border_length(straight)


def test_single_photo_floor_uses_it_everywhere(tmp_path) -> None:
    path = tmp_path / "floor.png"
    colour = np.dstack([skimage.data.grass()] * 3)
    colour[:, :, 2] = 255 - colour[:, :, 2]  # make it genuinely colour
    cv2.imwrite(str(path), colour)
    floor = Floor.from_photos([path], seed=1)
    assert floor.source_names == [str(path)]
    assert np.all(floor.region_source_at(np.linspace(-20, 20, 50), np.linspace(20, -20, 50)) == 0)
    tile = floor.tile(0, 0)
    assert tile.ndim == 2 and tile.dtype == np.uint8 and tile.std() > 15


def test_unreadable_files_are_config_errors_naming_the_file(tmp_path) -> None:
    missing = tmp_path / "nope.png"
    with pytest.raises(ConfigError, match="nope.png"):
        Floor.from_photos([missing])
    junk = tmp_path / "junk.jpg"
    junk.write_bytes(b"not an image at all")
    with pytest.raises(ConfigError, match="junk.jpg"):
        Floor.from_photos([junk])


def test_small_photos_shrink_blocks_and_tiny_ones_are_rejected() -> None:
    rng = np.random.default_rng(0)
    floor = Floor.from_photos([rng.integers(0, 255, (200, 220), dtype=np.uint8)])
    assert floor.block_px < 128
    assert 2 * floor.params.block_support * floor.block_px * floor.params.scale_range[1] <= 200
    assert floor.tile(0, 0).shape == (256, 256)
    with pytest.raises(ConfigError, match="too small"):
        Floor.from_photos([rng.integers(0, 255, (20, 20), dtype=np.uint8)])


def test_cache_is_bounded_and_evicted_tiles_come_back_identical() -> None:
    floor = Floor.from_photos([skimage.data.brick()], seed=2, tile_px=64, cache_mb=3 * 64 * 64 / 2**20)
    first = floor.tile(0, 0).copy()
    for k in range(1, 8):
        floor.tile(k, 0)
    assert floor.cache_bytes <= 3 * 64 * 64
    generated = floor.tiles_generated
    assert np.array_equal(floor.tile(0, 0), first)
    assert floor.tiles_generated == generated + 1  # (0, 0) had been evicted and was remade
    floor.tile(0, 0)
    assert floor.tiles_generated == generated + 1  # now a cache hit


def test_overview_is_the_same_floor_downsampled(gravel_floor: Floor) -> None:
    px_per_m = 250.0  # 4 mm per overview pixel: coarse mode
    before = gravel_floor.tiles_generated
    ov = gravel_floor.render_overview(0.0, 0.0, 0.6, 0.4, px_per_m)
    assert ov.shape == (100, 150) and ov.dtype == np.uint8
    assert gravel_floor.tiles_generated == before  # coarse mode made no full-resolution tile
    full, aff = gravel_floor.patch(0.0, 0.0, 0.6, 0.4)
    # Area-average the full-resolution floor onto the overview's pixel grid.
    c0, r0 = aff @ [0.0, 0.4, 1.0]
    crop = full[int(round(r0)) : int(round(r0)) + 400, int(round(c0)) : int(round(c0)) + 600]
    reference = cv2.resize(crop, (150, 100), interpolation=cv2.INTER_AREA)
    assert _ncc(ov, reference) > 0.8
    other = cv2.resize(full[-400:, -600:][::-1, ::-1], (150, 100), interpolation=cv2.INTER_AREA)
    assert abs(_ncc(ov, other)) < 0.3


def test_overview_north_is_up() -> None:
    marked = np.zeros((100, 100), dtype=np.uint8)
    marked[:10, :] = 200  # top rows of the image = north edge
    floor = ImageFloor(marked, metres_per_px=0.01, origin_xy_m=(0.0, 1.0))
    img, aff = floor.patch(0.0, 0.0, 1.0, 1.0)
    col, row = aff @ [0.5, 0.95, 1.0]
    assert img[int(round(row)), int(round(col))] == 200
    col, row = aff @ [0.5, 0.05, 1.0]
    assert img[int(round(row)), int(round(col))] == 0


def test_params_out_of_range_name_the_key() -> None:
    with pytest.raises(ConfigError, match="block_jitter"):
        FloorParams(block_jitter=0.7)
    with pytest.raises(ConfigError, match="metres_per_px"):
        Floor.default(metres_per_px=-1.0)
