"""``bench/bench_forward_median.py``: the comparison of two trees' answers, which must name
every difference (the bench's claim that the cuts keep every answer rests on it)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from bench.bench_forward_median import TOL, differences, filter_digest


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


def _detection(**change):
    d = {"scores": np.array([0.5, 0.0, 1.25]), "likelihood": np.array([1.0, 1.0, 2.5]),
         "posterior": np.array([0.7, 0.1, 0.2]), "hypothesis_ids": np.arange(2, dtype=np.int64)}
    d.update(change)
    return SimpleNamespace(**d)


def test_the_filter_digest_changes_with_one_bit_of_any_array_and_with_a_dtype():
    assert filter_digest(_detection()) == filter_digest(_detection())
    base = filter_digest(_detection())
    post = np.array([0.7, 0.1, 0.2])
    post[2] = np.nextafter(post[2], 1.0)  # one ulp
    assert filter_digest(_detection(posterior=post)) != base
    assert filter_digest(_detection(likelihood=np.array([1.0, 1.0, 2.5000000000000004]))) != base
    assert filter_digest(_detection(scores=np.array([0.5, 0.0, 1.25], np.float32))) != base
    assert filter_digest(_detection(hypothesis_ids=np.arange(2, dtype=np.int32))) != base
    # the same values split differently between two arrays are not the same answer
    assert filter_digest(_detection(scores=np.array([0.5, 0.0]), likelihood=np.array([1.25, 1.0, 1.0, 2.5]))) != base
