"""The Bayes filter of paper 000 Sec. IV against hand-derived numbers."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.forward.filter import (FilterParams, diffusion_weights, neighbourhood_sums, predict,
                                   select_candidate, transition_matrix, update)
from robotd.forward.likelihood import adjust_likelihood

# exp(-k^2 / 2) for k = -2..2, normalised: 0.135335, 0.606531, 1, 0.606531, 0.135335 / 2.483732
W = [0.054489, 0.244201, 0.402620, 0.244201, 0.054489]

# p(S_t = i | S_t-1 = j) with three image hypotheses before and four after (index 0 = no loop).
# Column j = -1: 0.9 stays, 0.1 / 4 to each image. Column image 0: offsets 0, +1, +2 exist,
# 0.9 * W[2:] / sum(W[2:]); images 1 and 2 lose one neighbour (offset -2 resp. +2 would be
# image -1 resp. 4), 0.9 * W[k] / 0.945511.
T = np.array([
    [0.900, 0.100000, 0.100000, 0.100000],
    [0.025, 0.516687, 0.232447, 0.051866],
    [0.025, 0.313387, 0.383240, 0.232447],
    [0.025, 0.069926, 0.232447, 0.383240],
    [0.025, 0.000000, 0.051866, 0.232447],
])


def test_diffusion_weights_are_the_gaussian_over_two_neighbours():
    assert np.allclose(diffusion_weights(), W, atol=1e-6)
    assert diffusion_weights(FilterParams(neighbours=1)).shape == (3,)


def test_transition_matrix_by_hand():
    m = transition_matrix(3, 4)
    assert m.shape == (5, 4)
    assert np.allclose(m, T, atol=1e-6)
    assert np.allclose(m.sum(axis=0), 1.0)  # p(S_t >= -1 | S_t-1 = j) = 1 for every j


def test_interior_columns_carry_the_full_gaussian_times_0_9():
    m = transition_matrix(10, 11)
    assert np.allclose(m[1 + 3:1 + 8, 1 + 5], 0.9 * np.array(W), atol=1e-6)
    assert m[0, 1 + 5] == pytest.approx(0.1)
    assert np.count_nonzero(m[1:, 1 + 5]) == 5


def test_predict_then_update_by_hand():
    post = np.array([0.5, 0.2, 0.2, 0.1])
    prior = predict(post, 4)
    assert np.allclose(prior, [0.5, 0.167513, 0.175070, 0.111299, 0.046118], atol=1e-6)
    assert np.allclose(prior, T @ post)
    # Votes: virtual image 1, images 0..3: 0, 0, 6, 1. Mean 1.6, std 2.245: only image 2
    # stands out, with (6 - 1.6) / 1.6 = 2.75.
    like = adjust_likelihood(np.array([1.0, 0.0, 0.0, 6.0, 1.0]))
    assert np.allclose(like, [1, 1, 1, 2.75, 1])
    assert np.allclose(update(prior, like), [0.418490, 0.140205, 0.146530, 0.256175, 0.038600],
                       atol=1e-6)


def test_before_any_hypothesis_the_no_loop_state_keeps_its_mass():
    assert np.allclose(predict(np.array([1.0]), 0), [1.0])
    assert np.allclose(predict(np.array([1.0]), 1), [0.9, 0.1])
    with pytest.raises(ValueError):
        predict(np.array([0.5, 0.5]), 0)


def test_neighbourhood_sums_and_candidate():
    post = np.array([0.05, 0.0, 0.1, 0.3, 0.4, 0.15, 0.0, 0.0])
    sums = neighbourhood_sums(post)
    assert np.allclose(sums, [0.4, 0.8, 0.95, 0.95, 0.85, 0.55, 0.15])
    # Images 2 and 3 tie at 0.95; the first is taken, and its most probable neighbour (3) returned.
    cand, prob = select_candidate(post)
    assert (cand, prob) == (3, pytest.approx(0.95))
    cand, prob = select_candidate(post, FilterParams(loop_threshold=0.96))
    assert cand is None and prob == pytest.approx(0.95)


def test_update_refuses_a_vanished_posterior():
    with pytest.raises(ValueError):
        update(np.array([0.0, 1.0]), np.array([1.0, 0.0]))


def test_the_total_rule_thresholds_one_minus_the_no_loop_probability():
    """A place seen twice far apart in time splits its probability between two
    neighbourhoods: neither passes 0.8 alone, the total loop probability does."""
    post = np.zeros(21)
    post[0] = 0.11
    post[1 + 3] = 0.45   # image 3
    post[1 + 15] = 0.40  # image 15, far from 3
    post[1 + 16] = 0.04
    assert select_candidate(post, FilterParams())[0] is None
    cand, prob = select_candidate(post, FilterParams(rule="total"))
    assert cand == 3 and prob == pytest.approx(0.89)
    assert select_candidate(post, FilterParams(rule="total", loop_threshold=0.95))[0] is None
    with pytest.raises(ValueError):
        FilterParams(rule="sum")


@pytest.mark.parametrize("neighbours, sigma", [(0, 1.0), (1, 0.7), (2, 1.0), (3, 1.5)])
def test_predict_spreads_each_image_over_its_existing_neighbours_at_any_length(neighbours, sigma):
    """The prior against the transition matrix built column by column from its definition
    (the Gaussian renormalised over the neighbours that exist), for histories shorter and
    longer than the Gaussian: the ends lack neighbours, the middle has them all."""
    p = FilterParams(neighbours=neighbours, sigma_images=sigma)
    g = diffusion_weights(p)
    rng = np.random.default_rng(neighbours)
    for n_prev in (0, 1, 2, 3, 5, 8, 40):
        for n_new in (n_prev, n_prev + 1, n_prev + 3):
            if n_new == 0:
                continue
            t = np.zeros((1 + n_new, 1 + n_prev))
            t[0, 0] = p.p_no_loop_stays
            t[1:, 0] = (1 - p.p_no_loop_stays) / n_new
            for j in range(n_prev):
                t[0, 1 + j] = p.p_loop_ends
                near = [(j + o, g[o + neighbours]) for o in range(-neighbours, neighbours + 1) if 0 <= j + o < n_new]
                total = sum(w for _, w in near)
                for i, w in near:
                    t[1 + i, 1 + j] = (1 - p.p_loop_ends) * w / total
            post = rng.random(1 + n_prev)
            post /= post.sum()
            assert predict(post, n_new, p) == pytest.approx(t @ post, abs=1e-15)


def test_the_total_rule_below_its_threshold_gives_no_candidate_and_the_total():
    """Under the threshold the total rule answers without a candidate and with the total
    loop probability whatever the neighbourhoods hold; with no image hypothesis, (None, 0)."""
    post = np.array([0.75, 0.2, 0.05])
    assert select_candidate(post, FilterParams(rule="total", loop_threshold=0.3)) == (None, pytest.approx(0.25))
    assert select_candidate(np.array([1.0]), FilterParams(rule="total", loop_threshold=0.0)) == (None, 0.0)
    assert select_candidate(np.array([1.0]), FilterParams(loop_threshold=0.0)) == (None, 0.0)
