"""``bench/bench_floor_query_fewer.py``: the variants' names, the places a query's loops fall
in, and the page of several runs."""

from __future__ import annotations

import pytest

from bench.bench_floor_query_fewer import page, parse_variant, places


def test_a_variant_names_its_levers_and_defaults_to_the_query_as_it_is():
    assert parse_variant("default") == 5
    assert parse_variant("k 2") == 2
    assert parse_variant("k 3 k 1") == 1  # the last one named
    with pytest.raises(ValueError):
        parse_variant("k")
    with pytest.raises(ValueError):
        parse_variant("place 10")  # one loop per place: removed from the index


def test_places_are_runs_of_ids_closer_than_the_spacing():
    assert places([], 10) == 0
    assert places([40, 3, 0, 9], 10) == 2  # 0, 3, 9 one place; 40 another
    assert places([0, 10, 20], 10) == 3
    assert places([0, 9, 18], 10) == 1  # chained within the spacing


def test_the_page_has_one_section_per_run_with_every_variant():
    def run(ms: float) -> dict:
        v = {"query_ms": {"median": ms, "p90": 2 * ms}, "ratio": ms / 6.0, "ratio_by_round": [ms / 6.0],
             "pairs_per_query": 2.0, "loops_per_query": 2.0, "places_per_query": 1.5, "queries_without_loop": 0}
        d = dict(v, query_ms={"median": 6.0, "p90": 9.0}, ratio=1.0, ratio_by_round=[1.0], pairs_per_query=5.0,
                 loops_per_query=5.0)
        return {"machine": {"platform": "Linux-test", "cpu_model": "x", "git_commit": "abc"},
                "load_start": [1.0], "load_end": [2.0],
                "result": {"map_keyframes": 1500, "map": "m.sqlite", "mode": 4, "queries": 100, "min_score": 90.0,
                           "shortlist": 10, "confidence": 0.99, "rounds": 1, "place_ids": 10,
                           "sizes": [{"keyframes": 1000, "variants": {"default": d, "k 2": v}}]}}

    text = page([run(3.0), run(3.3)])
    assert text.count("## Run ") == 2 and text.count("### 1000 keyframes") == 2
    assert "| k 2 | 3.00 | 0.500 (0.50) | 6.00 | 2.00 | 2.00 | 1.50 | 0 |" in text
    assert "| k 2 | 3.30 | 0.550 (0.55) |" in text
    single = page([run(3.0)])
    assert "## Run" not in single and "## 1000 keyframes" in single
