"""The forward camera's world: layout against the office route, items, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.base.errors import ConfigError
from sim.route import build_route, plan_motion
from sim.world.rooms import WorldParams, corridor_world, office_world


@pytest.fixture(scope="module")
def office():
    return office_world(seed=0)


def _distance_to_walls(world, xy: np.ndarray) -> np.ndarray:
    """``(N,)`` distance of points ``(N, 2)`` to the nearest wall segment."""
    a, b = world.a_m[None], world.b_m[None]
    p = xy[:, None, :]
    e = b - a
    s = np.clip(((p - a) * e).sum(-1) / (e * e).sum(-1), 0.0, 1.0)
    return np.linalg.norm(p - (a + s[..., None] * e), axis=-1).min(axis=1)


def test_office_route_stays_in_free_space_clear_of_the_walls(office):
    motion = plan_motion(build_route("office"))
    xy = motion.poses[::100, :2]
    assert all(office.contains(x, y) for x, y in xy)
    # Corridors are 1.4 m wide around the route: the robot keeps 0.5 m or more from any wall.
    assert _distance_to_walls(office, xy).min() >= 0.5


def test_office_walls_leave_free_space_on_their_left(office):
    mid = 0.5 * (office.a_m + office.b_m)
    d = office.b_m - office.a_m
    left = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
    assert all(office.contains(*(m + 0.05 * n)) for m, n in zip(mid, left))
    assert not any(office.contains(*(m - 0.05 * n)) for m, n in zip(mid, left))


def test_office_has_repeated_doors_photos_and_posters(office):
    kinds = [k for _, k, _, _ in office.items]
    assert kinds.count("door") >= 5 and kinds.count("photo") >= 5 and kinds.count("poster") >= 3
    # Every door is the same door: their textures are identical (perceptual aliasing).
    doors = [(k, s0, s1) for k, kind, s0, s1 in office.items if kind == "door"]
    ppm = office.params.px_per_m
    crops = [office.wall_texture(k)[:, int(round(s0 * ppm)):int(round(s0 * ppm)) + int(0.9 * ppm)]
             for k, s0, _ in doors[:3]]
    # Shading differs per wall orientation, so compare normalised patterns.
    z = [(c - c.mean()) / c.std() for c in (x.astype(np.float64)[150:600] for x in crops)]
    assert np.corrcoef(z[0].ravel(), z[1].ravel())[0, 1] > 0.97


def test_world_is_deterministic_per_seed():
    pts = np.array([[0.0, 0.0], [4.0, 0.0]])
    a, b = corridor_world(pts, seed=3), corridor_world(pts, seed=3)
    c = corridor_world(pts, seed=4)
    assert np.array_equal(a.atlas, b.atlas) and a.items == b.items
    assert not np.array_equal(a.atlas, c.atlas)


def test_corridor_world_walls_are_the_corridor_box():
    w = corridor_world(np.array([[0.0, 0.0], [4.0, 0.0]]), params=WorldParams(corridor_width_m=2.0))
    assert w.n_walls == 4
    assert w.bounds_m == pytest.approx((-1.0, -1.0, 5.0, 1.0))
    assert w.n_cells == 2 * 60 + 2 * 20  # 0.1 m cells along 6 + 6 + 2 + 2 m


def test_bad_parameters_are_config_errors():
    with pytest.raises(ConfigError, match="corridor_width_m"):
        WorldParams(corridor_width_m=0.0)
