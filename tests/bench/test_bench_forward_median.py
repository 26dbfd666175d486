"""``bench/bench_forward_median.py``: the comparison of two trees' answers, which must name
every difference (the bench's claim that the cuts keep every answer rests on it)."""

from __future__ import annotations

from bench.bench_forward_median import TOL, differences


def _answer(**change):
    a = {"words": [3, 1, 4], "status": "loop", "loop": 7, "candidate": 7, "p": 0.91, "virtual": 0.25,
         "verification": {"accepted": True, "reason": "accepted", "n_matches": 80, "n_inliers": 41,
                          "rotation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                          "translation_dir": [0.0, 0.0, 1.0]}}
    a.update(change)
    return a


def test_the_same_answers_and_rounding_within_the_tolerance_differ_nowhere():
    assert differences(_answer(), _answer()) == []
    assert differences(_answer(p=0.91 + TOL / 2), _answer()) == []
    assert differences(_answer(p=float("nan")), _answer(p=float("nan"))) == []
    assert differences(_answer(verification=None), _answer(verification=None)) == []


def test_every_changed_field_is_named_where_it_is():
    assert differences(_answer(words=[3, 1, 5]), _answer(), "image 0") == ["image 0.words[2]: 5 != 4"]
    assert differences(_answer(words=[3, 1]), _answer(), "i") == ["i.words: length 2 != 3"]
    assert differences(_answer(status="no_geometric_consistency"), _answer(), "i") == \
        ["i.status: 'no_geometric_consistency' != 'loop'"]
    assert differences(_answer(p=0.91 + 10 * TOL), _answer(), "i")[0].startswith("i.p: ")
    moved = _answer()
    moved["verification"] = dict(moved["verification"], translation_dir=[0.0, 1e-6, 1.0])
    assert differences(moved, _answer(), "i") == ["i.verification.translation_dir[1]: 1e-06 != 0.0"]
    assert len(differences(_answer(verification=None), _answer(), "i")) == 1
    assert differences(_answer(loop=None), _answer(), "i") == ["i.loop: None != 7"]
