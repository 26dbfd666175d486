"""The working memory of the forward detector: the inverted index's removal,
the Bayes filter over hypothesis ids, and the detector on a synthetic two-pass scene."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.forward import (
    LOOP,
    DetectorParams,
    Features,
    ForwardDetector,
    InvertedIndex,
    MemoryParams,
)
from robotd.forward.filter import (
    neighbourhood_sums,
    neighbourhood_sums_ids,
    predict,
    predict_ids,
    select_candidate,
    select_candidate_ids,
)
from robotd.forward.memory import WorkingMemory

# --- the inverted index ----------------------------------------------------------------------

IMAGES = {0: [0, 0, 1], 1: [1, 2], 2: [2, 2, 2, 3], 3: [4, 0, 2]}


def _index(ids) -> InvertedIndex:
    idx = InvertedIndex()
    for i in ids:
        idx.add_image(i, np.array(IMAGES[i]))
    return idx


def _by_id(idx: InvertedIndex, scores: np.ndarray) -> dict[int, float]:
    return {int(i): float(s) for i, s in zip(idx.image_ids, scores) if i >= 0}


def test_a_removed_image_no_longer_counts_and_comes_back_unchanged():
    query = np.array([0, 2, 2, 4, 1])
    full = _index([0, 1, 2, 3])
    before = _by_id(full, full.vote(query)[0]), full.vote(query)[1], list(full.virtual_image())
    full.remove_image(1, np.array(IMAGES[1]))
    assert full.n_images == 3 and 1 not in full and list(full.image_ids) == [0, -1, 2, 3]
    # Exactly an index that never had image 1: N, df, tf-idf, the virtual image.
    fresh = _index([0, 2, 3])
    s, v = full.vote(query)
    s2, v2 = fresh.vote(query)
    assert _by_id(full, s) == pytest.approx(_by_id(fresh, s2))
    assert v == pytest.approx(v2) and list(full.virtual_image()) == list(fresh.virtual_image())
    assert full.document_frequency(1) == 1 and full.document_frequency(2) == 2
    assert full.tfidf(2, 2) == pytest.approx(3 / 4 * math.log(3 / 2))
    # Back in (its old slot), every vote is what it was.
    full.add_image(1, np.array(IMAGES[1]))
    assert list(full.image_ids) == [0, 1, 2, 3]
    s, v = full.vote(query)
    assert _by_id(full, s) == pytest.approx(before[0]) and v == pytest.approx(before[1])
    assert list(full.virtual_image()) == before[2]


def test_removal_refuses_what_was_not_indexed():
    idx = _index([0, 1, 2])
    with pytest.raises(ValueError, match="not indexed"):
        idx.remove_image(7, np.array([0]))
    with pytest.raises(ValueError):
        idx.remove_image(1, np.array([1, 3]))      # not its words
    with pytest.raises(ValueError):
        idx.remove_image(1, np.array([1]))         # not all of them
    assert idx.n_images == 3 and idx.document_frequency(1) == 2  # nothing changed
    with pytest.raises(ValueError, match="already"):
        idx.add_image(1, np.array([0]))            # already there
    idx.remove_image(0, np.array(IMAGES[0]))
    with pytest.raises(ValueError, match="increase"):
        idx.add_image(-1, np.array([0]))           # older than the newest, and never removed
    idx.add_image(0, np.array(IMAGES[0]))          # a removed image may come back
    assert idx.n_images == 3


# --- the filter over hypothesis ids -----------------------------------------------------------

def test_the_filter_over_ids_is_the_papers_on_dense_ids():
    rng = np.random.default_rng(3)
    for n_prev, n_new in ((0, 1), (1, 1), (3, 4), (9, 10), (30, 31)):
        post = rng.random(1 + n_prev)
        post /= post.sum()
        got = predict_ids(post, np.arange(n_prev), np.arange(n_new))
        assert np.allclose(got, predict(post, n_new), atol=1e-15)
        prior = predict(post, n_new)
        assert np.allclose(neighbourhood_sums_ids(prior, np.arange(n_new)), neighbourhood_sums(prior))
        cand, prob, _ = select_candidate_ids(prior, np.arange(n_new))
        assert (cand, prob) == select_candidate(prior)


def test_predict_ids_by_hand_when_places_leave_and_come():
    # Hypotheses 0, 1, 5 -> 1, 5, 6: place 0 left, 6 is new. Gaussian weights of offsets
    # 0, +-1, +-2: 0.402620, 0.244201, 0.054489.
    post = np.array([0.4, 0.2, 0.1, 0.3])
    prior = predict_ids(post, np.array([0, 1, 5]), np.array([1, 5, 6]))
    new = 0.1 / 3 * 0.4                               # each hypothesis' share of no loop
    to5 = 0.9 * 0.3 * 0.402620 / (0.402620 + 0.244201)  # 5 keeps part of its mass, 6 gets the rest
    assert np.allclose(prior, [0.9 * 0.4 + 0.1 * 0.6,
                               new + 0.9 * 0.2 + 0.9 * 0.1,  # 0's only remaining neighbour is 1
                               new + to5,
                               new + 0.9 * 0.3 - to5], atol=1e-6)
    assert prior.sum() == pytest.approx(1.0)
    # A place that leaves with no neighbour left gives its mass to no loop.
    assert np.allclose(predict_ids(np.array([0.5, 0.5]), np.array([0]), np.array([10])),
                       [0.45 + 0.05 + 0.45, 0.05])
    assert np.allclose(predict_ids(np.array([0.5, 0.5]), np.array([0]), np.array([], np.int64)), [1.0])


def test_neighbourhoods_follow_ids_not_positions():
    # Hypotheses 3, 4, 9: 9 is not a neighbour of 4 although it comes next.
    post = np.array([0.1, 0.3, 0.25, 0.35])
    assert np.allclose(neighbourhood_sums_ids(post, np.array([3, 4, 9])), [0.55, 0.55, 0.35])
    cand, prob, best = select_candidate_ids(post, np.array([3, 4, 9]))
    assert cand is None and prob == pytest.approx(0.55) and best == 3
    with pytest.raises(ValueError):
        neighbourhood_sums_ids(post, np.array([4, 3, 9]))


def test_working_memory_refuses_a_bound_it_cannot_hold():
    with pytest.raises(ValueError, match="must exceed"):
        WorkingMemory(InvertedIndex(), MemoryParams(max_places=18), protect_recent=12, neighbours=2)
    WorkingMemory(InvertedIndex(), MemoryParams(max_places=21), protect_recent=12, neighbours=2)


# --- the detector on a synthetic scene -------------------------------------------------------
#
# A camera looks sideways at a textured wall of random 3D points (each with its own SIFT-like
# descriptor) and moves along it in 0.8 m steps: 80 images forward (pass 1), then from the
# place of image 60 back to the start, 0.3 m nearer the wall (pass 2). Image 80 + m is at
# the place of image 60 - m. With 40 places in the working memory, places 0 .. 39 are in
# long-term memory when pass 2 begins.

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
STEP_M, N1, BACK = 0.8, 80, 60


def _scene():
    rng = np.random.default_rng(0)
    n = 3600
    pts = np.column_stack([rng.uniform(-2, 66, n), rng.uniform(1.5, 3.0, n), rng.uniform(-1.2, 1.2, n)])
    desc = rng.normal(size=(n, 128))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    xs = [i * STEP_M for i in range(N1)] + [i * STEP_M for i in range(BACK, -1, -1)]
    ys = [0.0] * N1 + [0.3] * (BACK + 1)
    out = []
    for x, y in zip(xs, ys):
        depth = pts[:, 1] - y
        u = 500 * (pts[:, 0] - x) / depth + 320
        v = 500 * -pts[:, 2] / depth + 240
        ok = (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
        uv = np.column_stack([u[ok], v[ok]]) + rng.normal(0, 0.3, (ok.sum(), 2))
        d = desc[ok] + rng.normal(0, 0.012, (ok.sum(), 128))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        out.append(Features(uv.astype(np.float32), d.astype(np.float32), (480, 640)))
    return out


@pytest.fixture(scope="module")
def scene():
    return _scene()


def _run(scene, **memory):
    det = ForwardDetector(DetectorParams(memory=MemoryParams(**memory)), camera_matrix=K)
    return det, [det.process_features(f) for f in scene]


def _place(image: int) -> int:
    return image if image < N1 else BACK - (image - N1)


def test_places_in_long_term_memory_come_back_and_close_their_loops(scene):
    det, ds = _run(scene, max_places=40)
    # The bound holds after every image, and the index holds exactly the working memory.
    assert max(d.working_memory for d in ds) == 40
    assert all(d.working_memory <= 40 for d in ds)
    assert det.index.n_images == len(det.memory) == 40
    assert all(np.all(np.diff(d.hypothesis_ids) > 0) for d in ds)
    # The filter stays a distribution through transfers and retrievals.
    assert all(abs(d.posterior.sum() - 1) < 1e-9 and d.posterior.min() >= 0 for d in ds)
    # Places 0 .. 39 had all left by the start of pass 2.
    gone = {q for d in ds[:N1] for q in d.transferred}
    assert gone == set(range(40))
    back = {q for d in ds for q in d.retrieved}
    loops = [(d.image_id, d.loop_id) for d in ds if d.status == LOOP]
    assert all(abs(_place(t) - j) <= 1 for t, j in loops)  # every loop is true
    old = [(t, j) for t, j in loops if j < 40]
    # Measured: 40 loops with places 1 .. 39, each retrieved first; pass 2 ends at place 0.
    assert len(old) >= 30 and {j for _, j in old} <= back
    assert min(j for _, j in old) <= 2


def test_without_retrieval_long_term_places_stay_lost(scene):
    _, ds = _run(scene, max_places=40, max_retrieved=0)
    loops = [(d.image_id, d.loop_id) for d in ds if d.status == LOOP]
    assert not [j for _, j in loops if j < 40]
    assert all(d.working_memory <= 40 and not d.retrieved for d in ds)


def test_below_the_bound_the_detector_is_the_papers(scene):
    _, paper = _run(scene)
    _, bounded = _run(scene, max_places=1000)       # never reached: 141 images
    assert [d.status for d in bounded] == [d.status for d in paper]
    assert [d.loop_id for d in bounded] == [d.loop_id for d in paper]
    for a, b in zip(paper, bounded):
        assert np.array_equal(a.hypothesis_ids, b.hypothesis_ids)
        assert np.allclose(a.posterior, b.posterior, rtol=0, atol=1e-12)
        assert np.allclose(a.scores, b.scores, rtol=0, atol=1e-12)
        assert not b.retrieved and not b.transferred
    # The scene's loops: pass 2 closes with its places 59 .. 1 (all of them in memory).
    assert sum(d.status == LOOP for d in paper) >= 50


class _Clock:
    """A fake clock: every reading is ``step_s`` later than the one before."""

    def __init__(self, step_s: float) -> None:
        self.now, self.step = 0.0, step_s

    def __call__(self) -> float:
        self.now += self.step
        return self.now


def test_a_time_budget_moves_out_the_share_of_places_over_it(scene):
    # Every clock reading is 1 ms later, so the vote and the filter take 2 ms per image:
    # with a 1.5 ms budget each image is 4/3 over, and a quarter of the places must leave.
    det = ForwardDetector(DetectorParams(memory=MemoryParams(time_budget_s=1.5e-3)),
                          camera_matrix=K, timer=_Clock(1e-3))
    ds = [det.process_features(f) for f in scene[:60]]
    assert all(d.times_s["likelihood"] + d.times_s["filter"] == pytest.approx(2e-3) for d in ds)
    for d in ds:
        n = d.working_memory + len(d.transferred)          # places before the transfer
        movable = max(0, d.image_id - 12 + 1) - (d.image_id + 1 - n)  # older than the last 12 (+ 2)
        assert len(d.transferred) == min(math.ceil(n / 4), max(movable, 0))
    assert ds[-1].working_memory < 30 and det.memory.transferred == 60 - ds[-1].working_memory
    # A budget never reached changes nothing.
    det2 = ForwardDetector(DetectorParams(memory=MemoryParams(time_budget_s=2.5e-3)),
                           camera_matrix=K, timer=_Clock(1e-3))
    assert all(not det2.process_features(f).transferred for f in scene[:60])
