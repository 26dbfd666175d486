"""``bench/bench_forward_keyframe_profile.py``: which keyframes' profiles it sums (the
costliest, however they arrive) and that the sum holds every one of them."""

from __future__ import annotations

import cProfile
import pstats

from bench.bench_forward_keyframe_profile import TopKeyframes, summed


def test_the_costliest_are_kept_whatever_the_order_they_come_in():
    costs = [5.0, 41.0, 12.0, 57.5, 3.0, 44.0, 41.0, 9.0]
    top = TopKeyframes(3)
    for i, c in enumerate(costs):
        top.offer(c, i, f"kf{i}")
    assert [(c, i) for c, i, _ in top.items()] == [(57.5, 3), (44.0, 5), (41.0, 1)]  # a tie: the earlier one
    assert [item for _, _, item in top.items()] == ["kf3", "kf5", "kf1"]
    few = TopKeyframes(10)
    for i, c in enumerate(costs[:2]):
        few.offer(c, i, i)
    assert [i for _, i, _ in few.items()] == [1, 0]
    none = TopKeyframes(0)
    none.offer(1.0, 0, 0)
    assert none.items() == []


def _work(n: int) -> int:
    return sum(range(n))


def test_the_summed_profile_counts_every_kept_profile():
    profiles = []
    for calls in (1, 2, 4):
        prof = cProfile.Profile()
        prof.enable()
        for _ in range(calls):
            _work(10)
        prof.disable()
        profiles.append(prof)
    stats = summed(profiles)
    assert stats is not None
    counts = {func[2]: value[1] for func, value in stats.stats.items()}  # type: ignore[attr-defined]
    assert counts["_work"] == 7
    assert summed([]) is None
    assert isinstance(stats, pstats.Stats)


def test_the_split_takes_the_stage_parts_out_of_each_keyframe():
    from bench.bench_forward_keyframe_profile import split

    cpu = [10.0, 20.0, 50.0]
    parts = {"match": [0.0, 1.0, 1.0], "scan": [0.0, 4.0, 10.0], "level": [0.0, 0.0, 1.0],
             "ridge": [0.0, 0.0, 8.0], "store": [3.0, 3.0, 3.0]}  # the store is outside the call
    out = split(cpu, parts)
    assert out["stage"]["median"] == 5.0 and out["detector"]["median"] == 15.0
    assert out["cpu"]["median"] == 20.0
    assert 29.0 < out["detector"]["p99"] < 30.0  # 10, 15, 30: the p99 near the largest


def test_the_page_shows_the_split_and_every_kept_keyframe():
    from bench.bench_forward_keyframe_profile import page

    result = {"demo_args": ["--forward", "--seed", "0"], "profiled": False, "load": [3.1, 4.2],
              "machine": {"cpu_model": "test cpu"},
              "split": {"cpu": {"median": 14.0, "p99": 45.5}, "stage": {"median": 0.5, "p99": 21.0},
                        "detector": {"median": 13.5, "p99": 33.25}},
              "top": [{"keyframe": 219, "cpu_ms": 56.4, "parts": {"scan": 12.4, "ridge": 9.0}},
                      {"keyframe": 17, "cpu_ms": 50.0, "parts": {}}],
              "pieces": [{"function": "planefit.py:_refine", "what": "refinements", "calls": 9, "own_ms": 1.5,
                          "cum_ms": 3.25}]}
    text = "\n".join(page(result))
    assert "| detector | 13.50 | 33.25 |" in text and "| stage | 0.50 | 21.00 |" in text
    assert "| 219 | 56.4 | 0.0 | 12.4 | 0.0 | 9.0 |" in text and "| 17 | 50.0 |" in text
    assert "| `planefit.py:_refine` | refinements | 9 | 1.50 | 3.25 |" in text
    assert "no profiler" in text and "load 3.1-4.2" in text
