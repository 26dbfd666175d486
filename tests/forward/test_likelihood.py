"""Likelihood factors: the paper's normalisation and RTAB-Map's variant."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.forward.likelihood import adjust_likelihood


def test_paper_normalisation_includes_the_virtual_image():
    # Mean 3, std 4.0: only the virtual image (11) stands out: (11 - 3) / 3.
    like = adjust_likelihood(np.array([11.0, 1.0, 1.0, 1.0, 1.0]))
    assert np.allclose(like, [8 / 3, 1, 1, 1, 1])


def test_no_votes_means_no_information():
    assert np.array_equal(adjust_likelihood(np.zeros(4)), np.ones(4))
    assert adjust_likelihood(np.zeros(0)).shape == (0,)


def test_rtabmap_variant():
    # Non-zero real scores 2, 4, 10: mean 16/3, std 3.399346; 10 > 8.73 becomes
    # (10 - std) / mean; the no-loop hypothesis gets mean / std + 1 whatever its vote.
    like = adjust_likelihood(np.array([5.0, 0.0, 2.0, 4.0, 10.0]), "rtabmap")
    assert np.allclose(like, [2.568948, 1, 1, 1, 1.237623], atol=1e-6)


def test_unknown_method_is_refused():
    with pytest.raises(ValueError):
        adjust_likelihood(np.ones(3), "other")  # type: ignore[arg-type]
