"""The forward camera's world: corridors and rooms with textured walls.

The world is 2.5-D: a flat floor, a flat ceiling at ``wall_height_m``, and vertical walls
standing on 2-D line segments, which is what a column raycaster renders exactly
(:mod:`sim.cameras.forward`). Free space is the union of corridors laid along a route's
polyline (``corridor_width_m`` wide, mitred joints) and of rooms (axis-aligned boxes); the
walls are the edges of that union (shapely), oriented so that free space lies on each
wall's left, and split so that no wall is longer than ``max_wall_m``.

What the walls carry, each wall's texture built once at ``px_per_m`` texels per metre:

* painted plaster (low-contrast smooth noise, a shade per wall), a dark skirting board;
* real photographs in frames: scikit-image's sample photos (astronaut, coffee, cat, rocket,
  Hubble deep field, coins, ...), loaded at run time, each placement a different crop,
  so photos make places distinct;
* perceptual aliasing on purpose, as in the corridors of paper 000's and RTAB-Map's
  sequences: one door design repeated all over the building, a few poster designs
  repeated in several places, wall-panelling patterns (stripes, tiles) on some walls,
  a floor of identical tiles and a ceiling of identical panels and lights.

Everything comes from ``seed`` (placements, crops, shades), so the same seed gives the
same world. Ground truth never comes from the pictures: walls are cut into cells of
``cell_m`` along their length, and :mod:`sim.cameras.forward` reports which cells each
image column sees (:func:`view_overlap`, :func:`same_place_matrix`).

Texture atlas: the wall textures are packed into bands of an atlas image narrower than
OpenCV's remap limit (32767 px), with a two-level mip chain (half and quarter size) below
the full-size level, and the floor and ceiling tiles stored three-by-three so a wrapped
coordinate always has its bilinear neighbours. One ``cv2.remap`` of that atlas renders a
whole frame.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from robotd.base.errors import ConfigError

if TYPE_CHECKING:
    from shapely.geometry.base import BaseGeometry  # shapely has no type information

__all__ = ["PHOTO_NAMES", "Wall", "WallWorld", "WorldParams", "corridor_world", "office_world", "world_for_route"]

#: scikit-image sample photographs hung on the walls (all ship inside the wheel).
PHOTO_NAMES: tuple[str, ...] = (
    "astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "coins", "camera",
    "moon", "motorcycle", "retina", "immunohistochemistry", "brick", "grass",
    "gravel", "cell", "page",
)

MIP_LEVELS = 3  # full, half, quarter resolution


@dataclass(frozen=True)
class WorldParams:
    """Geometry and texture density of a world. Lengths in metres.

    Fields:
        corridor_width_m: free width of a corridor laid along a route segment.
        wall_height_m: floor-to-ceiling height (walls span 0 .. this).
        px_per_m: wall texture density, texels per metre (300: a wall 1.75 m from a
            525 px focal length camera has one texel per pixel).
        floor_px_per_m, ceiling_px_per_m: floor and ceiling texture density.
        max_wall_m: longer walls are split (atlas bands are at most 8192 texels wide).
        cell_m: length of the wall cells the ground truth counts.
        door_spacing_m: mean distance between objects (doors, pictures, posters) on a wall.
    """

    corridor_width_m: float = 1.4
    wall_height_m: float = 2.5
    px_per_m: float = 300.0
    floor_px_per_m: float = 200.0
    ceiling_px_per_m: float = 100.0
    max_wall_m: float = 12.0
    cell_m: float = 0.1
    door_spacing_m: float = 0.6

    def __post_init__(self) -> None:
        for name in ("corridor_width_m", "wall_height_m", "px_per_m", "floor_px_per_m",
                     "ceiling_px_per_m", "max_wall_m", "cell_m", "door_spacing_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"world parameter {name} must be positive, got {v!r}")
        if self.max_wall_m * self.px_per_m > 8000:
            raise ConfigError("world parameter max_wall_m * px_per_m must stay below 8000 texels")


@dataclass(frozen=True)
class Wall:
    """One wall: from ``a`` to ``b`` (metres, world frame), free space on its left."""

    a_xy_m: tuple[float, float]
    b_xy_m: tuple[float, float]

    @property
    def length_m(self) -> float:
        return math.hypot(self.b_xy_m[0] - self.a_xy_m[0], self.b_xy_m[1] - self.a_xy_m[1])


@dataclass
class WallWorld:
    """Walls, their packed textures and the floor and ceiling tiles.

    Arrays (K walls): ``a_m``, ``b_m`` ``(K, 2) float64`` wall end points; ``tex_x0``,
    ``tex_y0`` ``(K,) float64`` full-resolution atlas position of each wall texture's
    texel (0, 0) (texture column 0 is at ``b``, so the picture reads left to right for a
    viewer in the free space); ``cell0`` ``(K,) int64`` first ground-truth cell of each
    wall; ``atlas`` the ``uint8`` mip atlas (see the module docstring).
    """

    params: WorldParams
    a_m: np.ndarray
    b_m: np.ndarray
    tex_x0: np.ndarray
    tex_y0: np.ndarray
    cell0: np.ndarray
    n_cells: int
    atlas: np.ndarray
    level_offsets: np.ndarray  # (MIP_LEVELS, 2) float64: (x, y) of each level in the atlas
    floor_origin: np.ndarray  # (2,) full-res atlas texel of the central floor tile copy
    floor_period_px: tuple[int, int]
    ceiling_origin: np.ndarray
    ceiling_period_px: tuple[int, int]
    free_space: BaseGeometry = field(repr=False)  # shapely geometry of the free space
    items: list[tuple[int, str, float, float]] = field(default_factory=list, repr=False)

    @property
    def n_walls(self) -> int:
        return int(self.a_m.shape[0])

    @property
    def bounds_m(self) -> tuple[float, float, float, float]:
        """``(x_min, y_min, x_max, y_max)`` of all walls."""
        p = np.vstack([self.a_m, self.b_m])
        return float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())

    def contains(self, x_m: float, y_m: float) -> bool:
        """Whether ``(x_m, y_m)`` lies in free space (not inside or behind a wall)."""
        from shapely.geometry import Point

        return bool(self.free_space.contains(Point(x_m, y_m)))

    def wall_texture(self, k: int) -> np.ndarray:
        """Wall ``k``'s full-resolution texture, ``(rows, cols) uint8`` (row 0 = ceiling)."""
        p = self.params
        h = int(round(p.wall_height_m * p.px_per_m))
        w = int(math.ceil(float(np.linalg.norm(self.b_m[k] - self.a_m[k])) * p.px_per_m))
        x0, y0 = int(self.tex_x0[k]), int(self.tex_y0[k])
        return self.atlas[y0:y0 + h, x0:x0 + w]

    def overview(self, px_per_m: float = 40.0, margin_m: float = 0.5) -> np.ndarray:
        """A top view, ``(H, W, 3) uint8``: free space light, walls dark, north up, with
        each wall's items as coloured ticks (doors brown, photos green, posters blue)."""
        x0, y0, x1, y1 = self.bounds_m
        x0, y0, x1, y1 = x0 - margin_m, y0 - margin_m, x1 + margin_m, y1 + margin_m
        w, h = int(math.ceil((x1 - x0) * px_per_m)), int(math.ceil((y1 - y0) * px_per_m))
        img = np.full((h, w, 3), 90, np.uint8)

        def px(p: np.ndarray) -> np.ndarray:
            return np.column_stack([(p[..., 0] - x0) * px_per_m, (y1 - p[..., 1]) * px_per_m])

        geoms = getattr(self.free_space, "geoms", [self.free_space])
        for g in geoms:
            cv2.fillPoly(img, [np.round(px(np.asarray(g.exterior.coords))).astype(np.int32)], (235, 235, 235))
            for ring in g.interiors:
                cv2.fillPoly(img, [np.round(px(np.asarray(ring.coords))).astype(np.int32)], (90, 90, 90))
        for a, b in zip(self.a_m, self.b_m):
            pa, pb = px(a[None]), px(b[None])
            cv2.line(img, tuple(np.round(pa[0]).astype(int)), tuple(np.round(pb[0]).astype(int)), (20, 20, 20), 2)
        colours = {"door": (40, 80, 140), "photo": (40, 160, 40), "poster": (200, 90, 30)}
        for k, kind, s0, s1 in self.items:
            a, b = self.a_m[k], self.b_m[k]
            d = (b - a) / np.linalg.norm(b - a)
            n = np.array([-d[1], d[0]])
            # Item positions are measured from b (texture column 0) towards a.
            p0, p1 = b - d * s0 + 0.08 * n, b - d * s1 + 0.08 * n
            q0, q1 = px(p0[None])[0], px(p1[None])[0]
            cv2.line(img, tuple(np.round(q0).astype(int)), tuple(np.round(q1).astype(int)), colours[kind], 3)
        return img


# ------------------------------------------------------------------------- layouts


def office_world(seed: int = 0, params: WorldParams = WorldParams()) -> WallWorld:
    """The office of the ``office`` route (:mod:`sim.route`): a corridor round a 10 x 6 m
    block, a cross corridor at x = 5 m, and a room over the south-west corner (x, y in
    -0.7 .. 4.1 m, opening onto the corridors to the east and the north) with a square
    pillar in its middle; the room and the cross corridor share a 0.2 m partition."""
    from sim.route import build_route

    route = build_route("office")
    rooms = [(-0.7, -0.7, 4.1, 4.1)]
    pillars = [(1.1, 1.1, 2.4, 2.4)]
    return _build(_free_space(route.points(), params.corridor_width_m, rooms, pillars), seed, params)


def world_for_route(route_name: str, seed: int = 0, params: WorldParams = WorldParams()) -> WallWorld:
    """The world of a named route: the office for ``"office"``, otherwise corridors laid
    along the route's polyline."""
    if route_name == "office":
        return office_world(seed, params)
    from sim.route import build_route

    route = build_route(route_name)
    return _build(_free_space(route.points(), params.corridor_width_m, [], []), seed, params)


def corridor_world(waypoints_m: np.ndarray, seed: int = 0, params: WorldParams = WorldParams(),
                   rooms: tuple[tuple[float, float, float, float], ...] = ()) -> WallWorld:
    """Corridors along ``waypoints_m`` ``(N, 2)`` plus rooms ``(x0, y0, x1, y1)``."""
    return _build(_free_space(np.asarray(waypoints_m, float), params.corridor_width_m, list(rooms), []),
                  seed, params)


def _free_space(points: np.ndarray, width_m: float, rooms: list[tuple[float, float, float, float]],
                pillars: list[tuple[float, float, float, float]]) -> BaseGeometry:
    from shapely.geometry import LineString, box
    from shapely.ops import unary_union

    half = 0.5 * width_m
    parts = [LineString([tuple(p), tuple(q)]).buffer(half, cap_style="square", join_style="mitre")
             for p, q in zip(points[:-1], points[1:]) if np.linalg.norm(q - p) > 1e-9]
    parts += [box(*r) for r in rooms]
    free = unary_union(parts)
    for p in pillars:
        free = free.difference(box(*p))
    # Snap to a millimetre grid so that mitred joints and unions leave no sliver walls.
    from shapely import set_precision

    return set_precision(free, 1e-3).simplify(1e-4)


def _walls(free: BaseGeometry, max_wall_m: float) -> list[Wall]:
    from shapely.geometry.polygon import orient

    walls: list[Wall] = []
    for g in getattr(free, "geoms", [free]):
        g = orient(g, sign=1.0)  # exterior counter-clockwise, holes clockwise: free space on the left
        for ring in [g.exterior, *g.interiors]:
            c = np.asarray(ring.coords)
            for p, q in zip(c[:-1], c[1:]):
                length = float(np.linalg.norm(q - p))
                if length < 1e-6:
                    continue
                n = max(1, math.ceil(length / max_wall_m - 1e-9))
                for i in range(n):
                    a = p + (q - p) * i / n
                    b = p + (q - p) * (i + 1) / n
                    walls.append(Wall((float(a[0]), float(a[1])), (float(b[0]), float(b[1]))))
    return walls


# ------------------------------------------------------------------------ textures


@functools.cache
def _load_photo(name: str) -> np.ndarray:
    """A scikit-image sample photo as grey ``uint8``, read-only (cached: worlds share them)."""
    import skimage.data

    img = skimage.data.stereo_motorcycle()[0] if name == "motorcycle" else getattr(skimage.data, name)()
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        f = img.astype(np.float32)
        img = cv2.normalize(f, np.empty_like(f), 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    img.setflags(write=False)
    return img


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cell_px: int, amp: float) -> np.ndarray:
    small = rng.standard_normal((max(2, h // cell_px + 2), max(2, w // cell_px + 2))).astype(np.float32)
    big = cv2.resize(small, (w + 2 * cell_px, h + 2 * cell_px), interpolation=cv2.INTER_CUBIC)
    return amp * big[cell_px:cell_px + h, cell_px:cell_px + w]


def _door(ppm: float) -> np.ndarray:
    """The one door design (0.95 x 2.1 m with its frame), identical everywhere."""
    rng = np.random.default_rng(12345)  # fixed: every door is the same door
    w, h = int(0.95 * ppm), int(2.1 * ppm)
    door = np.full((h, w), 60.0, np.float32)  # frame
    f = int(0.06 * ppm)
    grain = _smooth_noise(rng, h - f, w - 2 * f, max(2, int(0.01 * ppm)), 6.0)
    grain += cv2.resize(rng.standard_normal((max(2, (h - f) // 40), w - 2 * f)).astype(np.float32),
                        (w - 2 * f, h - f), interpolation=cv2.INTER_LINEAR) * 10.0
    door[f:, f:w - f] = 135.0 + grain
    # Two recessed panels below, a window above, a handle, a kick plate.
    def rect(x0: float, y0: float, x1: float, y1: float, val: float | None, edge: float = 35.0) -> None:
        c0, r0, c1, r1 = int(x0 * ppm), int(y0 * ppm), int(x1 * ppm), int(y1 * ppm)
        if val is not None:
            door[r0:r1, c0:c1] = val
        cv2.rectangle(door, (c0, r0), (c1, r1), edge, max(1, int(0.008 * ppm)))

    rect(0.22, 0.25, 0.73, 0.85, 40.0)  # window (dark glass)
    cv2.line(door, (int(0.475 * ppm), int(0.25 * ppm)), (int(0.475 * ppm), int(0.85 * ppm)), 90.0, max(1, int(0.01 * ppm)))
    rect(0.2, 1.05, 0.75, 1.85, None)
    door[int(1.87 * ppm):int(2.05 * ppm), f:w - f] = 175.0  # kick plate
    cv2.rectangle(door, (int(0.76 * ppm), int(1.05 * ppm)), (int(0.85 * ppm), int(1.1 * ppm)), 220.0, -1)  # handle
    cv2.circle(door, (int(0.8 * ppm), int(1.2 * ppm)), max(1, int(0.015 * ppm)), 25.0, -1)  # lock
    return door


def _posters(ppm: float) -> list[np.ndarray]:
    """Three poster designs (0.6 x 0.85 m), each hung in several places."""
    w, h = int(0.6 * ppm), int(0.85 * ppm)
    out = []
    # 1: the scikit-image logo over bold stripes.
    logo = _load_photo("logo")
    p = np.full((h, w), 235.0, np.float32)
    for i in range(0, h, max(2, int(0.08 * ppm))):
        p[i:i + int(0.04 * ppm)] = 70.0
    lg = cv2.resize(logo, (w - 20, int((w - 20) * logo.shape[0] / logo.shape[1]))).astype(np.float32)
    p[20:20 + lg.shape[0], 10:10 + lg.shape[1]] = lg
    out.append(p)
    # 2: a page of text (a real scan) on a dark border.
    page = _load_photo("page")
    p = np.full((h, w), 30.0, np.float32)
    p[15:h - 15, 15:w - 15] = cv2.resize(page, (w - 30, h - 30)).astype(np.float32)
    out.append(p)
    # 3: a geometric pattern: concentric circles and a checkerboard strip.
    p = np.full((h, w), 200.0, np.float32)
    for r in range(w // 2, 5, -max(3, int(0.04 * ppm))):
        cv2.circle(p, (w // 2, int(0.35 * h)), r, 40.0 if (r // max(3, int(0.04 * ppm))) % 2 else 220.0, -1)
    sq = max(2, int(0.05 * ppm))
    for i in range(0, w, sq):
        for j in range(int(0.75 * h), h - 5, sq):
            if ((i // sq) + (j // sq)) % 2:
                p[j:j + sq, i:i + sq] = 20.0
    out.append(p)
    return out


def _pattern_band(kind: int, w: int, h: int, ppm: float) -> np.ndarray:
    """A wall-panelling band (0.1 .. 0.9 m): the same pattern wherever it is used."""
    x = np.arange(w)[None, :] / ppm
    y = np.arange(h)[:, None] / ppm
    if kind == 0:  # vertical boards with dark joints
        v = 150.0 + 25.0 * np.sin(2 * np.pi * x / 0.15) + 0.0 * y
        v = np.where((x % 0.15) < 0.008, 60.0, v)
    elif kind == 1:  # square tiles
        v = np.where(((x // 0.15) + (y // 0.15)) % 2 == 0, 200.0, 120.0)
        v = np.where(((x % 0.15) < 0.006) | ((y % 0.15) < 0.006), 70.0, v)
    else:  # chevrons
        v = np.where(((x + np.abs((y % 0.2) - 0.1)) % 0.2) < 0.1, 190.0, 90.0)
    return np.broadcast_to(v, (h, w)).astype(np.float32)


def _wall_texture(length_m: float, params: WorldParams, rng: np.random.Generator, photos: list[np.ndarray],
                  door: np.ndarray, posters: list[np.ndarray], photo_counter: list[int]
                  ) -> tuple[np.ndarray, list[tuple[str, float, float]]]:
    """One wall's texture, ``(rows, cols) float32`` (row 0 at the ceiling, column 0 at the
    wall's end ``b``), and the items hung on it ``(kind, s0_m, s1_m)`` from column 0."""
    ppm = params.px_per_m
    H = int(round(params.wall_height_m * ppm))
    W = int(math.ceil(length_m * ppm))
    shade = float(rng.uniform(165.0, 215.0))
    tex = shade + _smooth_noise(rng, H, W, max(2, int(0.4 * ppm)), 5.0)
    tex += rng.standard_normal((H, W)).astype(np.float32) * 2.0

    def row(h_m: float) -> int:  # texture row of height h_m above the floor
        return int(round((params.wall_height_m - h_m) * ppm))

    if length_m > 2.0 and rng.random() < 0.45:
        band = _pattern_band(int(rng.integers(0, 3)), W, row(0.1) - row(0.9), ppm)
        tex[row(0.9):row(0.1)] = band
        tex[row(0.92):row(0.9)] = 95.0  # dado rail
    tex[row(0.1):] = 55.0  # skirting board
    tex[row(0.1):row(0.1) + max(1, int(0.01 * ppm))] = 110.0
    items: list[tuple[str, float, float]] = []
    s = float(rng.uniform(0.2, 0.8))
    while True:
        kind = rng.choice(["door", "photo", "poster"], p=[0.4, 0.4, 0.2])
        if kind == "door":
            width_m = door.shape[1] / ppm
        elif kind == "poster":
            width_m = posters[0].shape[1] / ppm
        else:
            width_m = float(rng.uniform(0.7, 1.4))
        if s + width_m > length_m - 0.15:
            break
        c0 = int(round(s * ppm))
        if kind == "door":
            img = door
            r0 = row(2.1)
        elif kind == "poster":
            img = posters[int(rng.integers(0, len(posters)))]
            r0 = row(1.75)
        else:
            photo = photos[photo_counter[0] % len(photos)]
            photo_counter[0] += 1
            ph, pw = photo.shape
            aspect = float(rng.uniform(0.6, 0.85))
            cw = int(min(pw, ph / aspect) * rng.uniform(0.55, 0.9))
            chh = int(cw * aspect)
            x = int(rng.integers(0, pw - cw + 1))
            y = int(rng.integers(0, ph - chh + 1))
            crop = photo[y:y + chh, x:x + cw]
            fw = int(width_m * ppm)
            fh = int(fw * aspect)
            frame = max(2, int(0.03 * ppm))
            img = np.full((fh + 2 * frame, fw + 2 * frame), 35.0, np.float32)
            img[frame:frame + fh, frame:frame + fw] = cv2.resize(crop, (fw, fh), interpolation=cv2.INTER_AREA)
            width_m = img.shape[1] / ppm
            if s + width_m > length_m - 0.15:
                break
            centre = 1.3
            r0 = row(centre + 0.5 * img.shape[0] / ppm)
        r0 = max(r0, 0)
        ih, iw = min(img.shape[0], H - r0), img.shape[1]
        tex[r0:r0 + ih, c0:c0 + iw] = img[:ih]
        items.append((str(kind), s, s + iw / ppm))
        s += iw / ppm + float(rng.exponential(params.door_spacing_m)) + 0.15
    return tex, items


def _floor_tile(ppm: float) -> np.ndarray:
    """1 x 1 m of the floor: four 0.5 m vinyl tiles with speckle and dark joints; the floor
    repeats it everywhere."""
    rng = np.random.default_rng(777)
    n = int(round(1.0 * ppm))
    speckle = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), 1.2) * 18.0
    tile = 120.0 + speckle
    ij = np.arange(n)
    q = ((ij[:, None] // (n // 2)) + (ij[None, :] // (n // 2))) % 2
    tile += np.where(q == 0, 8.0, -8.0).astype(np.float32)
    j = max(1, int(0.006 * ppm))
    tile[:j] = 70.0
    tile[:, :j] = 70.0
    tile[n // 2:n // 2 + j] = 70.0
    tile[:, n // 2:n // 2 + j] = 70.0
    return tile


def _ceiling_tile(ppm: float) -> np.ndarray:
    """2.4 x 1.2 m of the ceiling: 0.6 m acoustic panels, one a bright light panel."""
    rng = np.random.default_rng(778)
    w, h = int(round(2.4 * ppm)), int(round(1.2 * ppm))
    tile = 215.0 + rng.standard_normal((h, w)).astype(np.float32) * 5.0
    p = int(round(0.6 * ppm))
    tile[:, :p] = 250.0  # the light
    tile[:, p // 2 - 1:p // 2 + 1] = 200.0
    g = max(1, int(0.02 * ppm))
    for k in range(0, w, p):
        tile[:, k:k + g] = 150.0
    for k in range(0, h, p):
        tile[k:k + g] = 150.0
    return tile


# --------------------------------------------------------------------------- build


def _build(free: BaseGeometry, seed: int, params: WorldParams) -> WallWorld:
    rng = np.random.default_rng(seed)
    walls = _walls(free, params.max_wall_m)
    if not walls:
        raise ConfigError("the world has no walls")
    ppm = params.px_per_m
    photos = [_load_photo(n) for n in PHOTO_NAMES]
    order = rng.permutation(len(photos))
    photos = [photos[i] for i in order]
    door = _door(ppm)
    posters = _posters(ppm)

    pad = 8
    band_w = 8192
    wall_h = int(round(params.wall_height_m * ppm))
    # Shading: a wall facing the light direction is brighter (one diffuse light from the
    # north-east, a fill light everywhere).
    light = np.array([0.6, 0.8])
    textures, places, items = [], [], []
    x, band = pad, 0
    counter = [0]
    cell0, n_cells = [], 0
    for k, wl in enumerate(walls):
        length = wl.length_m
        tex, its = _wall_texture(length, params, rng, photos, door, posters, counter)
        d = np.subtract(wl.b_xy_m, wl.a_xy_m) / length
        normal = np.array([-d[1], d[0]])
        tex *= np.float32(0.8 + 0.2 * float(normal @ light))
        if x + tex.shape[1] + pad > band_w:
            x, band = pad, band + 1
        places.append((x, band))
        textures.append(tex)
        items += [(k, kind, s0, s1) for kind, s0, s1 in its]
        x += tex.shape[1] + pad
        cell0.append(n_cells)
        n_cells += int(math.ceil(length / params.cell_m - 1e-9))
    n_bands = band + 1
    band_h = wall_h + 2 * pad
    floor = _floor_tile(params.floor_px_per_m)
    ceil = _ceiling_tile(params.ceiling_px_per_m)
    fl3, ce3 = np.tile(floor, (3, 3)), np.tile(ceil, (3, 3))
    extra_h = max(fl3.shape[0], ce3.shape[0]) + 2 * pad
    h0 = n_bands * band_h + extra_h
    h0 += (-h0) % 4
    w0 = band_w
    level0 = np.full((h0, w0), 128.0, np.float32)
    tex_x0, tex_y0 = np.zeros(len(walls)), np.zeros(len(walls))
    for k, (tex, (x, b)) in enumerate(zip(textures, places)):
        y = b * band_h + pad
        th, tw = tex.shape
        # Replicate the border into the padding: bilinear lookups at a wall's edge stay on it.
        level0[y - pad:y + th + pad, x - pad:x + tw + pad] = cv2.copyMakeBorder(
            tex, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
        tex_x0[k], tex_y0[k] = x, y
    fy0 = n_bands * band_h + pad
    level0[fy0:fy0 + fl3.shape[0], pad:pad + fl3.shape[1]] = fl3
    cx0 = pad + fl3.shape[1] + 2 * pad
    level0[fy0:fy0 + ce3.shape[0], cx0:cx0 + ce3.shape[1]] = ce3
    if cx0 + ce3.shape[1] > w0:
        raise ConfigError("floor and ceiling tiles do not fit the atlas")
    floor_origin = np.array([pad + floor.shape[1], fy0 + floor.shape[0]], float)
    ceiling_origin = np.array([cx0 + ceil.shape[1], fy0 + ceil.shape[0]], float)
    level0 = np.clip(level0, 0, 255).astype(np.uint8)
    # Mip chain below level 0: level 1 (half) at x = 0, level 2 (quarter) beside it.
    l1 = cv2.resize(level0, (w0 // 2, h0 // 2), interpolation=cv2.INTER_AREA)
    l2 = cv2.resize(l1, (w0 // 4, h0 // 4), interpolation=cv2.INTER_AREA)
    atlas = np.zeros((h0 + h0 // 2, w0), np.uint8)
    atlas[:h0] = level0
    atlas[h0:, :w0 // 2] = l1
    atlas[h0:h0 + h0 // 4, w0 // 2:w0 // 2 + w0 // 4] = l2
    offsets = np.array([[0.0, 0.0], [0.0, h0], [w0 / 2.0, h0]])
    return WallWorld(params=params, a_m=np.array([w.a_xy_m for w in walls]),
                     b_m=np.array([w.b_xy_m for w in walls]), tex_x0=tex_x0, tex_y0=tex_y0,
                     cell0=np.asarray(cell0, np.int64), n_cells=n_cells, atlas=atlas,
                     level_offsets=offsets, floor_origin=floor_origin,
                     floor_period_px=(floor.shape[1], floor.shape[0]), ceiling_origin=ceiling_origin,
                     ceiling_period_px=(ceil.shape[1], ceil.shape[0]), free_space=free, items=items)
