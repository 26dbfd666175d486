"""``bench/bench_daemon.py --residency`` of several maps: how a map's queries repeat its
earlier keyframes, the local scores and geometric checks a query makes, and the page's
section comparing the maps round by round."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bench.bench_daemon import map_laps, memory_markdown, pairs_per_query
from robotd.floor import match

MACHINE = {"platform": "Linux-test", "cpu_count": 2, "python": "3.11", "numpy": "2.4"}


def test_map_laps_counts_identical_descriptors_and_the_nearest_keyframe_outside_the_window():
    s = 10**9
    recs = [SimpleNamespace(descriptor=b"a", x_m=0.0, y_m=0.0, stamp_ns=0),
            SimpleNamespace(descriptor=b"b", x_m=1.0, y_m=0.0, stamp_ns=1 * s),
            SimpleNamespace(descriptor=b"a", x_m=0.0, y_m=0.0, stamp_ns=100 * s),   # lap 2 replayed
            SimpleNamespace(descriptor=b"c", x_m=1.03, y_m=0.04, stamp_ns=101 * s)]  # lap 2 anew
    got = map_laps(recs, 2, 20.0)
    assert got["distinct_descriptors"] == 3
    assert got["queries_with_identical_keyframe"] == 1
    assert got["nearest_keyframe_m"]["median"] == pytest.approx((0.0 + 0.05) / 2)
    assert got["nearest_keyframe_m"]["max"] == pytest.approx(0.05)


@pytest.fixture(scope="module")
def two_passes():
    import skimage.data

    from robotd.base.camera import FloorCameraModel
    from robotd.floor.descriptor import decode, extract
    from sim.cameras.floor import FloorRenderer, RenderParams
    from sim.world.floor import Floor

    floor = Floor.from_photos([skimage.data.gravel()], seed=3)
    renderer = FloorRenderer(floor, FloorCameraModel.default(), RenderParams(), np.random.default_rng(1))
    images = [renderer.render(np.array([0.1 * i, dy, 0.0]), 0.1, 0.0, 30.0) for dy in (0.0, 0.01) for i in range(6)]
    return [decode(extract(im, 4)) for im in images]


def test_pairs_per_query_counts_every_local_score_and_restores_the_matcher(two_passes):
    from robotd.floor.index import FloorIndex, IndexParams

    index = FloorIndex(IndexParams(shortlist=4))
    for i, d in enumerate(two_passes):
        index.add(i, d)
    n0 = len(two_passes)
    ids, stamps = np.arange(n0), np.arange(n0, dtype=np.int64) * 10**9
    qrows = list(range(6, n0))  # the second pass, the first pass outside the 3 s window
    score = match.Matcher.score
    before = index.local_matches
    got = pairs_per_query(index, qrows, two_passes, ids, stamps, n0, 5.0, 3.0)
    scored = index.local_matches - before
    assert match.Matcher.score is score
    assert got["local_scores_per_query"] * len(qrows) == scored > 0
    assert sum(got["local_score_reasons"].values()) == scored
    loops = sum(c.score >= 5.0 for q in qrows
                for c in index.query(two_passes[q], k=5, min_score=5.0,
                                     exclude_ids=ids[np.abs(stamps - stamps[q]) < 3 * 10**9]))
    assert 0 < loops <= got["geometric_checks_per_query"] * len(qrows) <= scored


def _run(label: str, rnd: int, ms: float, loops: int) -> dict:
    v = {"query_ms": {"median": ms, "p99": ms * 2}, "reads_per_query": 0.0, "loops": loops, "index_mb": 1.0}
    return {"label": label, "round": rnd, "load_average": [2.0, 2.0, 2.0], "map_keyframes": 1500, "queries": 100,
            "distinct_descriptors": 1500 if label == "new" else 746, "queries_with_identical_keyframe": 0,
            "nearest_keyframe_m": {"median": 0.01, "max": 0.02},
            "sizes": [{"keyframes": 1000, "local_scores_per_query": 9.5, "geometric_checks_per_query": 3.25,
                       "variants": {"in RAM": {**v, "query_ms": {"median": ms - 1, "p99": ms}},
                                    "from the map, 1024 resident": v}}]}


def test_the_maps_section_gives_each_round_its_ratio_to_the_first_map_and_the_medians():
    runs = [_run("old", 1, 8.0, 500), _run("new", 1, 4.0, 300), _run("old", 2, 10.0, 500), _run("new", 2, 6.0, 300),
            _run("old", 3, 9.0, 500), _run("new", 3, 3.0, 300)]
    page = memory_markdown({"machine": MACHINE, "residency_maps": runs})
    assert "| new | 1500 | 1500 | 0 of 100 | 0.010 / 0.020 |" in page
    assert "| 1000 | new | 2 | 2.0 | 6.00 | 5.00 | 0.60 | 3.00 | 9.50 | 3.25 |" in page
    assert "| 1000 | old | 1 | 2.0 | 8.00 | 7.00 | 1.00 | 5.00 |" in page
    assert "| 1000 | old | median of the rounds | | **9.00** |" in page
    assert "| 1000 | new | median of the rounds | | **4.00** |" in page


@pytest.mark.parametrize("argv", [["--memory", "10", "--memory-seeds", "1,x"],
                                  ["--memory", "10", "--memory-seeds", ","],
                                  ["--memory", "10", "--memory-seeds", "1,2", "--forward"],
                                  ["--residency", "old=/nonexistent/map.sqlite"]])
def test_the_options_refuse_what_they_cannot_run(argv, tmp_path, capsys):
    from bench.bench_daemon import main

    with pytest.raises(SystemExit) as exc:
        main([*argv, "--out", str(tmp_path), "--cache", str(tmp_path)])
    assert exc.value.code == 2 and "error:" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # nothing recorded, nothing written
