"""The incremental vocabulary, the inverted index, tf-idf and the virtual image."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.forward.vocabulary import InvertedIndex, Vocabulary, VocabularyParams, sorted_isin, sorted_union


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.standard_normal((n, 128)).astype(np.float32)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _near(d: np.ndarray, rng: np.random.Generator, scale: float = 0.01) -> np.ndarray:
    e = d + scale * rng.standard_normal(d.shape).astype(np.float32)
    return e / np.linalg.norm(e, axis=1, keepdims=True)


def test_words_are_created_only_for_descriptors_far_from_every_word():
    rng = np.random.default_rng(1)
    a, b, c = _unit(rng, 3)  # random unit vectors are about 1.4 apart
    voc = Vocabulary()
    words, new = voc.add(np.stack([a, _near(a[None], rng)[0], b]))
    assert list(words) == [0, 0, 1] and new == 2  # a and its near copy share one word
    words, new = voc.add(np.stack([_near(b[None], rng)[0], c]))
    assert list(words) == [1, 2] and new == 1
    assert len(voc) == 3
    assert list(voc.quantize(np.stack([c, _unit(rng, 1)[0]]))) == [2, -1]
    assert list(voc.quantize(c[None])) == [2]  # a single query too
    assert list(voc.add(_unit(rng, 1))[0]) == [3]


def test_the_radius_decides():
    rng = np.random.default_rng(2)
    a = _unit(rng, 1)
    far = _near(a, rng, 0.05)  # about 0.05 * sqrt(128) = 0.57 away
    dist = float(np.linalg.norm(far - a))
    assert 0.4 < dist < 0.8
    assert list(Vocabulary(params=VocabularyParams(word_radius_l2=0.4)).add(np.vstack([a, far]))[0]) == [0, 1]
    assert list(Vocabulary(params=VocabularyParams(word_radius_l2=0.9)).add(np.vstack([a, far]))[0]) == [0, 0]


def test_binary_words_use_the_hamming_distance():
    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, (1, 32), dtype=np.uint8)
    close = a.copy()
    close[0, :3] ^= 0xFF  # 24 bits differ
    far = a.copy()
    far[0, :8] ^= 0xFF  # 64 bits differ
    voc = Vocabulary(dim=32, binary=True, params=VocabularyParams(word_radius_bits=40))
    words, new = voc.add(np.vstack([a, close, far]))
    assert list(words) == [0, 0, 1] and new == 2


def test_many_words_stay_searchable():
    rng = np.random.default_rng(4)
    d = _unit(rng, 3000)
    voc = Vocabulary()
    for k in range(0, 3000, 300):
        voc.add(d[k:k + 300])
    assert len(voc) == 3000
    hits = voc.quantize(_near(d[::10], rng))
    assert np.mean(hits == np.arange(0, 3000, 10)) > 0.97  # approximate search, nearly exact


def _index() -> InvertedIndex:
    idx = InvertedIndex()
    idx.add_image(0, np.array([0, 0, 1]))
    idx.add_image(1, np.array([1, 2]))
    idx.add_image(2, np.array([2, 2, 2, 3]))
    return idx


def test_tfidf_after_insertions_and_kept_current():
    idx = _index()
    assert idx.document_frequency(2) == 2
    assert idx.tfidf(0, 0) == pytest.approx(2 / 3 * math.log(3))       # 0.732408
    assert idx.tfidf(1, 1) == pytest.approx(1 / 2 * math.log(3 / 2))   # 0.202733
    assert idx.tfidf(2, 2) == pytest.approx(3 / 4 * math.log(3 / 2))   # 0.304099
    assert idx.tfidf(3, 0) == 0.0
    idx.add_image(3, np.array([0]))
    # N = 4 and df(0) = 2 now: the same pair weighs less.
    assert idx.tfidf(0, 0) == pytest.approx(2 / 3 * math.log(2))       # 0.462098
    with pytest.raises(ValueError):
        idx.add_image(3, np.array([1]))


def test_virtual_image_is_the_most_frequent_words():
    idx = _index()
    # Occurrences: w0 2, w1 2, w2 4, w3 1; 9 words over 3 images -> n = 3; the tie between
    # w0 and w1 goes to the older word.
    assert list(idx.virtual_image()) == [2, 0, 1]
    assert list(InvertedIndex().virtual_image()) == []


def test_votes_are_tfidf_sums_and_the_virtual_image_votes_too():
    idx = _index()
    scores, virtual = idx.vote(np.array([2, 0, -1, 7]))  # -1 (no word) and 7 (unknown) ignored
    assert np.allclose(scores, [2 / 3 * math.log(3), 1 / 2 * math.log(1.5), 3 / 4 * math.log(1.5)])
    assert virtual == pytest.approx((math.log(1.5) + math.log(3)) / 3)  # 0.501359
    # A word twice in the query votes twice.
    scores2, _ = idx.vote(np.array([2, 2]))
    assert np.allclose(scores2, [0.0, math.log(1.5), 1.5 * math.log(1.5)])


def test_words_seen_in_one_image_only_are_purged_after_the_set_age():
    """iBoW-LCD's purging: a word no later image found leaves the search once
    ``purge_after`` images have come after the image that made it; a word that recurred
    stays; ids are never reused."""
    rng = np.random.default_rng(7)
    params = VocabularyParams(word_radius_bits=40, purge_after=2)
    voc = Vocabulary(dim=32, binary=True, params=params)
    a = rng.integers(0, 256, (2, 32), dtype=np.uint8)  # image 0: two words, 0 and 1
    voc.add(a)
    voc.add(a[:1])                       # image 1 finds word 0 again: it recurred
    assert voc.purged == 0 and list(voc.quantize(a)) == [0, 1]  # one image after: not yet
    voc.add(rng.integers(0, 256, (1, 32), dtype=np.uint8))  # image 2: word 1 (seen once) goes
    assert voc.purged == 1 and voc.n_searchable == len(voc) - 1
    assert list(voc.quantize(a)) == [0, -1]
    words, new = voc.add(a[1:])          # the same descriptor now makes a new word
    assert new == 1 and words[0] == len(voc) - 1 and words[0] != 1


def test_no_purging_by_default():
    rng = np.random.default_rng(8)
    voc = Vocabulary(dim=32, binary=True)
    for _ in range(30):
        voc.add(rng.integers(0, 256, (5, 32), dtype=np.uint8))
    assert voc.purged == 0 and voc.n_searchable == len(voc) == 150


def test_a_restored_vocabulary_finds_what_the_original_finds_and_purges_on():
    """restore() (a restarted daemon): the same searchable words, purged ones
    not found, and purging goes on from where it was."""
    rng = np.random.default_rng(9)
    params = VocabularyParams(word_radius_bits=40, purge_after=3)
    voc = Vocabulary(dim=32, binary=True, params=params)
    imgs = [rng.integers(0, 256, (4, 32), dtype=np.uint8) for _ in range(6)]
    descs = []
    for k, d in enumerate(imgs):
        voc.add(d if k != 5 else np.vstack([d, imgs[4][:1]]))  # image 5 sees a word of image 4 again
        descs.append(voc.last_new[1])
    all_desc = np.vstack(descs)
    born = np.repeat(np.arange(6), [len(x) for x in descs])
    purged = np.zeros(len(voc), bool)
    purged[:voc.purged] = True  # purged in creation order: images 0-2 were due, seen once
    seen = np.ones(len(voc), np.int64)
    seen[16] = 2  # the word of image 4 found again at image 5
    again = Vocabulary(dim=32, binary=True, params=params)
    again.restore(all_desc, born, purged, seen, n_images=6)
    assert voc.purged == 12 and again.purged == 12 and len(again) == len(voc) == 24
    probe = np.vstack(imgs)
    np.testing.assert_array_equal(again.quantize(probe), voc.quantize(probe))
    assert (again.quantize(probe)[:12] == -1).all()
    again.add(rng.integers(0, 256, (1, 32), dtype=np.uint8))  # image 6: image 3's words fall due
    voc.add(rng.integers(0, 256, (1, 32), dtype=np.uint8))
    assert again.purged == voc.purged == 16


def test_dropped_postings_change_no_score_of_the_other_words():
    rng = np.random.default_rng(10)
    idx, ref = InvertedIndex(), InvertedIndex()
    words = [rng.integers(0, 40, 12) for _ in range(8)]
    for i, w in enumerate(words):
        idx.add_image(i, w)
        ref.add_image(i, w)
    only_once = [w for w in range(40) if idx.document_frequency(w) == 1]
    idx.drop_postings(np.array(only_once))
    query = np.array([w for w in range(40) if w not in only_once])
    np.testing.assert_array_equal(idx.vote(query)[0], ref.vote(query)[0])
    idx.add_image(8, np.array(only_once[:2]))  # a dropped word coming back gets postings again
    assert idx.document_frequency(only_once[0]) == 2 and idx.vote(np.array(only_once[:1]))[0][8] > 0


def test_dropped_postings_free_their_memory():
    rng = np.random.default_rng(12)
    idx = InvertedIndex()
    for i in range(300):
        idx.add_image(i, rng.integers(0, 100, 20))
    postings = sum(idx.document_frequency(w) for w in range(100))
    before = idx.memory_bytes()
    idx.drop_postings(np.arange(100))
    assert idx.memory_bytes() <= before - 4 * postings  # 4 bytes a posting, all of them gone
    assert idx.vote(np.arange(100))[0].max() == 0.0


def test_postings_take_four_bytes_and_a_word_repeated_beyond_their_count_still_votes():
    idx = InvertedIndex()
    idx.add_image(0, np.array([3, 3, 5]))
    before = idx.memory_bytes()
    for i in range(1, 101):  # 100 more postings of word 3, and 100 more images
        idx.add_image(i, np.array([3]))
    grown = idx.memory_bytes() - before
    # 4 bytes a posting, 12 an image (its words' count, its id, its slot), 1,600 in all;
    # the arrays' room from the start and their spare room (an eighth) either way
    assert 800 <= grown < 2400
    # n(w, i) is kept up to 1023: an image holding word 5 1100 times counts it 1023 times ...
    idx.add_image(101, np.array([5] * 1100 + [3]))
    scores, _ = idx.vote(np.array([5]))
    idf5 = math.log(idx.n_images / 2)
    assert scores[101] == pytest.approx(1023 / 1101 * idf5)
    assert scores[0] == pytest.approx(1 / 3 * idf5)
    # ... and the image leaves the index as it came in
    idx.remove_image(101, np.array([5] * 1100 + [3]))
    assert idx.document_frequency(5) == 1 and idx.n_images == 101


def test_virtual_image_skips_unused_word_ids_and_words_whose_images_left():
    """The virtual image is chosen among the words in use without a list of them: ids
    never added (gaps) and words whose every image was removed must not enter it, and the
    result equals a brute-force ranking (most occurrences first, ties: the lower id)."""
    rng = np.random.default_rng(5)
    idx = InvertedIndex()
    images = {i: rng.choice(np.arange(0, 400, 3), size=40) for i in range(30)}  # ids 1, 2, 4, ... never used
    for i, w in images.items():
        idx.add_image(i, w)
    for i in (3, 8, 9, 20):
        idx.remove_image(i, images.pop(i))

    def brute() -> list[int]:
        occ: dict[int, int] = {}
        for w in images.values():
            for x in w.tolist():
                occ[x] = occ.get(x, 0) + 1
        n = round(sum(len(w) for w in images.values()) / len(images))
        return sorted(occ, key=lambda x: (-occ[x], x))[:n]

    assert list(idx.virtual_image()) == brute()
    for i in list(images)[:20]:  # most images leave: many words fall to df 0
        idx.remove_image(i, images.pop(i))
    assert list(idx.virtual_image()) == brute()
    idx.add_image(40, np.array([1, 1, 1, 2]))  # a gap id comes into use
    images[40] = np.array([1, 1, 1, 2])
    assert list(idx.virtual_image()) == brute()


def test_virtual_image_from_its_candidates_is_the_choice_over_all_words():
    """The virtual image is chosen among kept candidates: it must be the ``n`` most frequent
    words over all words (ties to the older word), image after image, after removals too
    (counts fall) and as ``n`` (the mean words per image) changes."""
    rng = np.random.default_rng(5)
    idx = InvertedIndex()
    occ: dict[int, int] = {}
    kept: dict[int, np.ndarray] = {}

    def reference() -> np.ndarray:
        n = max(1, round(sum(len(w) for w in kept.values()) / len(kept)))
        used = sorted((-c, w) for w, c in occ.items() if c > 0)
        return np.array([w for _, w in used[:n]], np.int64)

    for t in range(400):
        size = int(rng.integers(5, 40 if t < 200 else 80))  # n grows in the second half
        # a few frequent words, many rare ones, and new words: ties everywhere
        w = np.concatenate([rng.integers(0, 30, size // 4), rng.integers(0, 3 * t + 50, size - size // 4)])
        idx.add_image(t, w)
        kept[t] = w
        for x in w.tolist():
            occ[x] = occ.get(x, 0) + 1
        if t % 50 == 49:  # a working memory moving places out: two, or most of them once
            for gone in ([t - 30, t - 10] if t != 299 else [g for g in list(kept) if g < 290]):
                idx.remove_image(gone, kept[gone])
                for x in kept.pop(gone).tolist():
                    occ[x] -= 1
        np.testing.assert_array_equal(idx.virtual_image(), reference())


@pytest.mark.parametrize("seed", range(4))
def test_sorted_union_and_isin_give_numpy_s_answers(seed):
    """The vote's and the index's set operations on sorted unique word ids, against
    ``np.union1d`` and ``np.isin``: overlapping, disjoint, empty and one-sided inputs."""
    rng = np.random.default_rng(seed)
    for n_a, n_b, top in ((300, 40, 2000), (50, 300, 400), (0, 30, 100), (30, 0, 100), (0, 0, 10), (1, 1, 2)):
        a = np.unique(rng.integers(0, top, n_a)).astype(np.int64)
        b = np.unique(rng.integers(0, top, n_b)).astype(np.int64)
        u = sorted_union(a, b)
        assert u.dtype == np.union1d(a, b).dtype and np.array_equal(u, np.union1d(a, b))
        got = sorted_isin(a, b)
        assert got.dtype == bool and np.array_equal(got, np.isin(a, b))
        assert np.array_equal(sorted_isin(b, a), np.isin(b, a))
    # values past either end of b, and a's repeats
    b = np.array([5, 9, 12], np.int64)
    a = np.array([0, 5, 5, 7, 12, 13, 99], np.int64)
    assert sorted_isin(a, b).tolist() == [False, True, True, False, True, False, False]


def test_occurrences_past_the_narrow_counters_widen_them():
    idx = InvertedIndex()
    for i in range(40):  # word 2: 1000 times an image, 40,000 in all (past int16)
        idx.add_image(i, np.array([2] * 1000 + [1]))
    assert idx.occurrences()[2] == 40_000 and idx.occurrences()[1] == 40
    assert list(idx.virtual_image()) == [2, 1]  # most frequent first
    idx.remove_image(0, np.array([2] * 1000 + [1]))
    assert idx.occurrences()[2] == 39_000


def test_growing_bits_set_read_and_span_as_a_bool_array_does():
    """The per-word "found again" bits (eight to a byte): set with repeats, read one by
    one and over any span, across growth, as a bool array answers."""
    from robotd.forward.vocabulary import _GrowingBits

    rng = np.random.default_rng(2)
    bits, ref = _GrowingBits(), np.zeros(0, bool)
    for _ in range(40):
        n = len(ref) + int(rng.integers(0, 90))
        bits.resize(n)
        ref = np.concatenate([ref, np.zeros(n - len(ref), bool)])
        if n:
            at = rng.integers(0, n, int(rng.integers(0, 30)))
            bits.set(np.concatenate([at, at[:3]]))
            ref[at] = True
            lo = int(rng.integers(0, n))
            hi = int(rng.integers(lo, n + 1))
            assert bits.between(lo, hi).tolist() == ref[lo:hi].tolist()
            probe = rng.integers(0, n, 20)
            assert bits.get(probe).tolist() == ref[probe].tolist()
    assert bits.between(0, len(ref)).tolist() == ref.tolist()
    assert bits.nbytes <= (len(ref) + 7) // 8 + (len(ref) + 7) // 8 // 32 + 16
