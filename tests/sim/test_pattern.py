"""The printed plank/tile floor: joints where the geometry says, prints that repeat."""

import numpy as np
import pytest

from robotd.base.errors import ConfigError
from sim.world.pattern import PatternFloor, PatternParams


def _photo(size: int = 512) -> np.ndarray:
    return np.random.default_rng(1).integers(60, 200, (size, size)).astype(np.uint8)


def test_tile_joints_and_print_repeats():
    # A photo that holds two disjoint 0.3 m crops unstretched: white noise, so tiles of
    # different prints (or windows a pixel apart) do not correlate.
    f = PatternFloor(_photo(640), PatternParams(kind="tiles", width_m=0.3, joint_m=0.004, prints=2))
    img, aff = f.patch(0.0, -0.9, 1.2, 0.0)
    # World x = 0.3 m is a joint; the centre of a tile is print content, not joint grey.
    col = lambda x: int(round(aff[0, 0] * x + aff[0, 2]))  # noqa: E731
    row = lambda y: int(round(aff[1, 1] * y + aff[1, 2]))  # noqa: E731
    assert img[row(-0.15), col(0.3)] == 45
    assert img[row(-0.15), col(0.15)] != 45 or img[row(-0.15), col(0.16)] != 45
    # Two prints over 12 tiles: some tiles are pixel-identical copies of each other.
    tiles = [img[row(-0.3 * r) + 10:row(-0.3 * r) + 280, col(0.3 * c) + 10:col(0.3 * c) + 280]
             .astype(float).ravel() for r in range(3) for c in range(4)]
    ncc = [np.corrcoef(tiles[0], t)[0, 1] for t in tiles[1:]]
    same = sum(n > 0.95 for n in ncc)
    assert 1 <= same <= 10 and all(n > 0.95 or abs(n) < 0.2 for n in ncc)


def test_patch_affine_matches_sampling_and_planks_are_staggered():
    f = PatternFloor(_photo(), PatternParams(kind="planks", length_m=0.45, width_m=0.12, stagger=1 / 3))
    img, aff = f.patch(-0.5, -0.5, 0.5, 0.5)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.45, 0.45, (200, 2))
    cols = np.rint(aff[0, 0] * pts[:, 0] + aff[0, 2]).astype(int)
    rows = np.rint(aff[1, 1] * pts[:, 1] + aff[1, 2]).astype(int)
    # The pixel whose centre is nearest each point has the pattern's value there.
    centres_x = (cols - aff[0, 2]) / aff[0, 0]
    centres_y = (rows - aff[1, 2]) / aff[1, 1]
    assert np.array_equal(img[rows, cols], f._sample(centres_x, centres_y))
    # Row 0 has a joint at x = 0; row 1 (y in [0.12, 0.24)) is shifted by 0.15 m.
    assert f._sample(np.array([0.0005]), np.array([0.06]))[0] == 45
    assert f._sample(np.array([0.1505]), np.array([0.18]))[0] == 45
    assert f._sample(np.array([0.0005]), np.array([0.18]))[0] != 45


def test_bad_pattern_params():
    with pytest.raises(ConfigError):
        PatternParams(kind="hexagons")
    with pytest.raises(ConfigError):
        PatternParams(width_m=0.01, joint_m=0.01)


def test_print_choice_has_no_short_period():
    # Each print about equally often, and no grid period: shifted by up to 8 planks or rows,
    # the print map agrees with itself about 1 / prints of the time (an exactly periodic
    # map, as a hash that keeps only low bits gives, would agree everywhere at its period).
    from sim.world.pattern import _print_index

    col, row = np.meshgrid(np.arange(-40, 40), np.arange(-40, 40))
    k = _print_index(col, row, seed=5, prints=4)
    assert np.allclose(np.bincount(k.ravel(), minlength=4) / k.size, 0.25, atol=0.03)
    for dc in range(0, 9):
        for dr in range(0, 9):
            if dc == dr == 0:
                continue
            agree = np.mean(k[dr:, dc:] == k[:k.shape[0] - dr, :k.shape[1] - dc])
            assert 0.18 < agree < 0.32, (dc, dr, agree)
    assert not np.array_equal(k, _print_index(col, row, seed=6, prints=4))


@pytest.mark.parametrize("params", [PatternParams(kind="planks"), PatternParams(kind="tiles", width_m=0.3),
                                    PatternParams(kind="planks", prints=6)])
def test_prints_are_disjoint_crops(params):
    # Overlapping crops would share content at a shift: more aliasing than the print count.
    for seed in range(8):
        f = PatternFloor(_photo(), params, seed=seed)
        boxes = f.crop_boxes
        assert len(boxes) == params.prints
        for a in range(len(boxes)):
            for b in range(a + 1, len(boxes)):
                ya, xa, h, w = boxes[a]
                yb, xb, _, _ = boxes[b]
                assert abs(ya - yb) >= h or abs(xa - xb) >= w, (seed, boxes)
        # Each print is its box of the photo (stretched when the photo is too small).
        assert f._prints.shape[1:] == (boxes[0][2], boxes[0][3])
        assert len({f._prints[k].tobytes() for k in range(len(boxes))}) == params.prints
