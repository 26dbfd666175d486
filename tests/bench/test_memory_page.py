"""The memory page of ``bench/bench_daemon.py`` from its JSON payloads: a labelled partial
``--memory`` run, a finished one and a ``--residency`` run, each as its section."""

from __future__ import annotations

import json
import math

from bench.bench_daemon import _labelled, memory_markdown

MACHINE = {"platform": "Linux-test", "cpu_count": 2, "python": "3.11", "numpy": "2.4"}
CONFIG = {"keyframe_distance_m": 0.15, "mode": 4, "shortlist": 10, "localise_mapped": False,
          "loop_spacing": 10, "loops_per_keyframe": 2, "fold": 10, "resident": 1024}


def _sample(n: int, rss: float, query_ms: float = math.nan) -> dict:
    return {"keyframes": n, "stored": n, "rss_mb": rss, "rss_trimmed_mb": rss - 3, "laps": 2, "index_mb": 8.1,
            "cpu_s": 50.0, "graph_loops": 120, "graph_held_loops": 2581, "graph_factors": 316, "graph_folded": 804,
            "query_ms_median": query_ms, "index_loads": 2586}


def test_the_page_has_a_section_per_payload_with_its_rows(tmp_path):
    partial = {"machine": MACHINE, "recording": "office.mcap",
               "memory": {"keyframes_target": 10000, "laps": 3, "rss_before_mb": 106.0, "config": CONFIG,
                          "samples": [_sample(1000, 152.0, 6.05), _sample(2000, 161.0)]}}
    path = tmp_path / "run.json"
    path.write_text(json.dumps(partial), encoding="utf-8")
    residency = {"machine": MACHINE, "residency": {
        "map": "m.sqlite", "map_keyframes": 1549, "mode": 4, "queries": 300, "sizes": [
            {"keyframes": 10000, "variants": {
                "in RAM": {"query_ms": {"median": 2.0, "p99": 3.0}, "reads_per_query": 0.0, "index_mb": 61.2,
                           "loops": 500, "candidates_sha256": "0123456789ab", "loops_sha256": "fedcba987654"},
                "read back, 1024 resident": {"query_ms": {"median": 2.5, "p99": 4.0}, "reads_per_query": 8.8,
                                             "index_mb": 9.2}}}]}}
    page = memory_markdown(_labelled(f"this code={path}"), residency)
    heads = [line for line in page.splitlines() if line.startswith("## ")]
    assert len(heads) == 2 and heads[0].startswith("## this code: every keyframe stored")
    assert "folded after each full solve (fold 10)" in heads[0] and "1024 kept decoded" in heads[0]
    assert "| 1000 | 1000 | 152 | 149 | 8.1 | 2 | 50 | 120 / 2581 | 316 (804) | 6.0 (2586) |" in page
    assert "| 2000 | 1000 |" not in page and "| 2000 | 2000 | 161 | 158 |" in page
    assert "stopped at 2000 keyframes, before its target of 10000" in page
    # loops and digests: "-" where the run did not count them (runs before the columns)
    assert "| 10000 | read back, 1024 resident | 2.50 | 4.00 | 1.25 | 8.80 | - | - | - | 9.2 |" in page
    assert "| 10000 | in RAM | 2.00 | 3.00 | 1.00 | 0.00 | 500 | 01234567 | fedcba98 | 61.2 |" in page
    assert _labelled(str(path)).get("label") is None


def test_a_scale_section_shows_the_map_read_and_the_parts_where_the_run_has_them():
    parts = {"shortlist": 0.5, "read": 0.3, "decode": 1.0, "local score": 2.5, "other": 0.2, "total": 4.5}
    new = {"keyframes": 10000, "distinct": 1000, "query_ms": {"median": 3.0, "p99": 5.0},
           "query_read_back_ms": {"median": 4.0, "p99": 7.0, "reads_per_query": 7.25},
           "query_from_map_ms": {"median": 4.5, "p99": 8.0, "reads_per_query": 7.25}, "same_candidates": True,
           "parts_ms": {"from the map": parts}}
    old = {"keyframes": 1000, "distinct": 1000, "query_ms": {"median": 3.0, "p99": 4.0},
           "query_read_back_ms": {"median": 3.3, "p99": 4.5, "reads_per_query": 0.0}}
    page = memory_markdown({"machine": MACHINE, "recording": "office.mcap", "scale": {"sizes": [old, new]}})
    assert "| 10000 | 1000 | 3.00 | 5.00 | 4.00 | 7.00 | 1.33 | 7.2 | 4.50 | 8.00 | 1.50 | 7.2 | yes |" in page
    assert "| 1000 | 1000 | 3.00 | 4.00 | 3.30 | 4.50 | 1.10 | 0.0 | - | - | - | - | - |" in page
    assert "| 10000 | from the map | 0.50 | 0.30 | 1.00 | 2.50 | 0.20 | 4.50 |" in page
    # a run before the map's column: its table as it was, no parts
    page = memory_markdown({"machine": MACHINE, "recording": "office.mcap", "scale": {"sizes": [old]}})
    assert "| 1000 | 1000 | 3.00 | 4.00 | 3.30 | 4.50 | 1.10 | 0.0 |" in page
    assert "from the map" not in page and "Where a query's time goes" not in page
