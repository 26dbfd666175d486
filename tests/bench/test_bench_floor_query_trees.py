"""``bench/bench_floor_query_trees.py``: the answer digest (equal for equal answers, changed by
any field of any candidate) and the page of several runs."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from bench.bench_floor_query_trees import answer_digest, main, page
from robotd.floor.match import MatchReason, MatchResult


@dataclass(frozen=True)
class _Cand:
    keyframe_id: int
    global_score: float
    local: MatchResult


def _result(score: float = 100.0) -> MatchResult:
    return MatchResult(score, 40, 3, np.array([1, 2, 3]), np.array([4, 5, 6]), np.zeros((3, 2), np.float32),
                       np.ones((3, 2), np.float32), np.eye(2, 3), MatchReason.OK)


def test_the_digest_is_equal_for_equal_answers_and_changes_with_any_field():
    base = [_Cand(7, 0.8, _result()), _Cand(9, 0.7, _result(95.0))]
    assert answer_digest(base) == answer_digest([_Cand(7, 0.8, _result()), _Cand(9, 0.7, _result(95.0))])
    t = np.eye(2, 3)
    t[0, 2] = np.nextafter(0.0, 1.0)  # one bit of a transform
    changed = [
        [base[1], base[0]],
        [replace(base[0], keyframe_id=8), base[1]],
        [replace(base[0], global_score=np.nextafter(0.8, 1.0)), base[1]],
        [replace(base[0], local=replace(base[0].local, score=np.nextafter(100.0, 0.0))), base[1]],
        [replace(base[0], local=replace(base[0].local, n_inliers=4)), base[1]],
        [replace(base[0], local=replace(base[0].local, inliers_b=np.array([4, 5, 7]))), base[1]],
        [replace(base[0], local=replace(base[0].local, transform=t)), base[1]],
        [replace(base[0], local=replace(base[0].local, transform=None)), base[1]],
        [replace(base[0], local=replace(base[0].local, reason=MatchReason.BELOW_MIN_SCORE)), base[1]],
        base[:1],
    ]
    digests = {answer_digest(c) for c in changed}
    assert len(digests) == len(changed) and answer_digest(base) not in digests


def test_the_page_has_one_section_per_run_with_every_tree():
    def run(after_ms: float) -> dict:
        def tree(ms: float, same: int) -> dict:
            return {"query_ms": {"median": ms, "p90": 1.5 * ms}, "ratio": ms / 4.0, "paired_ratio": ms / 4.1,
                    "ratio_by_round": [ms / 4.0, ms / 4.2], "answers_same_as_first": same, "answers": 200,
                    "loops_first_round": 500}
        return {"machine": {"platform": "Linux-test", "cpu_model": "x"}, "load_start": [1.0], "load_end": [2.0],
                "result": {"map_keyframes": 1500, "map": "m.sqlite", "mode": 4, "queries": 100, "min_score": 90.0,
                           "k": 5, "rounds": 2, "trees": [{"label": "before", "commit": "abc"},
                                                          {"label": "after", "commit": "def"}],
                           "sizes": [{"keyframes": 10000, "trees": {"before": tree(4.0, 200),
                                                                      "after": tree(after_ms, 199)}}]}}

    text = page([run(3.2), run(3.4)])
    assert text.count("## Run ") == 2 and text.count("### 10000 keyframes") == 2
    assert "| after | 3.20 | 0.800 (0.80, 0.76) | 0.780 | 4.80 | 199/200 | 500 |" in text
    assert "| before | 4.00 | 1.000 (1.00, 0.95) | 0.976 | 6.00 | 200/200 | 500 |" in text
    single = page([run(3.2)])
    assert "## Run" not in single and "## 10000 keyframes" in single and "after (commit def)" in single


@pytest.mark.parametrize("trees, says", [
    (["a=/nonexistent"], "--tree 'a=/nonexistent': LABEL=PATH of a tree holding robotd/"),
    (["justapath"], "--tree 'justapath': LABEL=PATH"),
    (["a=."], "two or more --tree LABEL=PATH"),
    (["a=.", "b=."], "no such map"),
])
def test_the_bench_refuses_what_it_cannot_run_and_writes_nothing(trees, says, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(Path(__file__).resolve().parents[2])  # "." holds robotd/
    args = [a for t in trees for a in ("--tree", t)]
    with pytest.raises(SystemExit) as exc:
        main(args + ["--map", str(tmp_path / "absent.sqlite"), "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    assert says in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
