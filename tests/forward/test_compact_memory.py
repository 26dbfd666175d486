"""The forward detector's memory per image on the real corridor
(../shared/data/forward/rtabmap_samples, 84 images): the inverted index's flat postings
answer as one list of postings per word does, the memory held stays within what the
structures need and is what Python allocated for them, a past image's descriptors lent to
the word search read back as they were given (through purges, images leaving memory and a
bounded working memory), and a detector restored from a map file holds the same index and
the same images."""

from __future__ import annotations

import gc
import sys
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from robotd.forward import FeatureExtractor, ForwardDetector, method_params
from robotd.forward.features import CompactFeatures, Features, LentFeatures, compact
from robotd.forward.memory import MemoryParams
from robotd.forward.vocabulary import _COUNT_BITS, _COUNT_MASK, InvertedIndex, Vocabulary, _block_room, _grown
from robotd.io.sequence import list_images, read_image
from tests.shared_data import require

SAMPLES = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "forward" / "rtabmap_samples"


@pytest.fixture(scope="module")
def corridor():
    """The default detector's features of the corridor's 84 images."""
    gt = require(SAMPLES / "ground_truth.bmp", "real corridor images")
    params = method_params("default")
    ex = FeatureExtractor(params.features)
    return [ex(read_image(f)) for f in list_images(SAMPLES, exclude=(gt,))]


class _Lists:
    """The inverted index as it was kept before its flat arrays: one list of postings per
    word (slot << _COUNT_BITS | n(w, i), in the order they came), df and occurrences; the
    vote computed as that index computed it (the postings joined word after word)."""

    def __init__(self) -> None:
        self.post: dict[int, list[int]] = {}
        self.df: dict[int, int] = {}
        self.occ: dict[int, int] = {}
        self.image_len: dict[int, int] = {}

    def add(self, slot: int, words: np.ndarray) -> None:
        self.image_len[slot] = len(words)
        uw, cnt = np.unique(words, return_counts=True)
        for w, c in zip(uw.tolist(), cnt.tolist()):
            self.post.setdefault(w, []).append(slot << _COUNT_BITS | min(c, _COUNT_MASK))
            self.df[w] = self.df.get(w, 0) + 1
            self.occ[w] = self.occ.get(w, 0) + c

    def remove(self, slot: int, words: np.ndarray) -> None:
        uw, cnt = np.unique(words, return_counts=True)
        for w, c in zip(uw.tolist(), cnt.tolist()):
            self.post[w].remove(slot << _COUNT_BITS | min(c, _COUNT_MASK))
            self.df[w] -= 1
            self.occ[w] -= c
        self.image_len[slot] = 0

    def drop(self, words: np.ndarray) -> None:
        for w in words.tolist():
            self.post[w] = []

    def vote(self, words: np.ndarray, n_images: int, n_slots: int) -> np.ndarray:
        uw, cq = np.unique(words, return_counts=True)
        df = np.array([self.df.get(w, 0) for w in uw.tolist()], np.int64)
        keep = df > 0
        uw, cq, df = uw[keep], cq[keep], df[keep]
        scores = np.zeros(n_slots)
        if not len(uw):
            return scores
        lists = [self.post[w] for w in uw.tolist()]
        packed = np.array([p for ps in lists for p in ps], np.int64)
        slots = packed >> _COUNT_BITS
        image_len = np.array([self.image_len[s] for s in slots.tolist()], np.float64)
        weights = np.repeat(cq * np.log(n_images / df), [len(ps) for ps in lists]) * (packed & _COUNT_MASK) / image_len
        return scores + np.bincount(slots, weights=weights, minlength=n_slots)


def _same_index(idx: InvertedIndex, ref: _Lists) -> None:
    words = np.arange(idx.n_words, dtype=np.int64)
    got, held = idx._post.gather(words)
    want = [ref.post.get(w, []) for w in range(idx.n_words)]
    assert held.tolist() == [len(p) for p in want]
    assert got.tolist() == [p for ps in want for p in ps]
    assert idx._df.view.tolist() == [ref.df.get(w, 0) for w in range(idx.n_words)]
    assert idx._occ.view.tolist() == [ref.occ.get(w, 0) for w in range(idx.n_words)]


def test_flat_postings_hold_and_vote_what_per_word_lists_do_on_the_corridor(corridor):
    """Every image's words (the default vocabulary, purging as the detector does) go into
    the index and into per-word lists: the postings, counts and every vote agree to the
    bit, through purged words' postings dropped, and through images taken out and put
    back (a bounded working memory's moves), which shift postings inside their blocks."""
    params = method_params("default")
    voc = Vocabulary(dim=32, binary=True, params=params.vocabulary)
    idx, ref = InvertedIndex(), _Lists()
    kept = []
    for t, f in enumerate(corridor):
        words, _ = voc.add(f.descriptors)
        if t:  # the vote of image t against the images before it, as the detector asks
            got, _ = idx.vote(words)
            np.testing.assert_array_equal(got, ref.vote(words, idx.n_images, idx.n_slots))
        idx.add_image(t, words)
        ref.add(t, words)
        kept.append(words)
        idx.drop_postings(voc.last_purged)
        ref.drop(voc.last_purged)
    _same_index(idx, ref)
    assert int(idx._post.head.view.max()) >= 1 << 31  # words with blocks of postings are there
    # a working memory's moves: images out of the index and back in (postings re-added
    # after dropped ones are not: a bounded memory drops none); fresh index, no drops
    idx, ref = InvertedIndex(), _Lists()
    for t, w in enumerate(kept):
        idx.add_image(t, w)
        ref.add(t, w)
    for t in (3, 40, 41, 10, 83, 0):
        idx.remove_image(t, kept[t])
        ref.remove(t, kept[t])  # slot t: no image left before
    _same_index(idx, ref)
    for t in (41, 3, 0):  # back into the freed slots, lowest first
        slot = int(np.flatnonzero(idx.image_ids == -1)[0])
        idx.add_image(t, kept[t])
        ref.add(slot, kept[t])
    _same_index(idx, ref)
    for q in (kept[5], kept[41], kept[60]):
        np.testing.assert_array_equal(idx.vote(q)[0], ref.vote(q, idx.n_images, idx.n_slots))


def _capacity(n: int) -> int:
    """The most elements a growing array (:func:`_grown`) holds for ``n`` in use."""
    return _grown(n)


def _structure_bound(det: ForwardDetector) -> dict[str, int]:
    """What the detector's parts may hold, from what they contain: each growing array at
    most a thirty-second (plus one) beyond its use, the blocks left behind at most a third
    of the live ones (compaction at a quarter of the store), a block of postings its count
    (its word's df) rounded up to a power of two; the working memory's three arrays per
    place (weight and last use int32, in WM one byte), a bounded one's stored words; the
    word tree's slots their descriptors, and their word ids once a slot holds another word
    than its number, their rows and positions once a word was removed; a bit per word for
    whether it was found again."""
    idx, voc = det.index, det.vocabulary
    tree = voc._tree
    n_words, n_slots, n_images = idx.n_words, idx.n_slots, len(det)
    h = idx._post.head.view
    block = h >= (1 << 31)
    count = idx._df.view[np.flatnonzero(block)].astype(np.int64)  # a block's postings: its word's df
    live = int(_block_room(count).sum()) if len(count) else 0
    df_occ = _width(int(idx._df.view.max(initial=0))) + _width(int(idx.occurrences().max(initial=0)))
    index = (_capacity(n_words) * (4 + df_occ)                 # head, df, occurrences (as narrow as they fit)
             + _capacity(live * 4 // 3) * 4                     # blocks of postings, those left behind
             + _capacity(n_slots) * 4)                          # words per image
    wm = det.memory
    stored = sum(sys.getsizeof(w) for w in wm._words) + (_list_bytes(len(wm._words)) if wm._words else 0)
    sorted_ids = 8 * len(wm) if wm._wm_sorted is not None else 0
    index += (_capacity(n_slots) * 4 + _capacity(n_images) * 4             # image per slot, slot per image
              + (len(idx._v_cand) * (2 if n_words <= 0x10000 else 4)        # the virtual image's candidates
                 if idx._v_cand is not None else 0)
              + _capacity(wm.n_places) * (4 + 4 + 1) + stored + sorted_ids)  # the working memory
    nodes, rows, slots = tree._n_nodes, tree._n_rows, tree._n_slots
    blocks = int(tree._row_cap[:rows].sum())
    n_free = len(tree._free_rows) + len(tree._free_slots)
    per_slot = (32 + (0 if tree.slots_are_words else 4)                   # descriptor, word id once kept
                + (0 if tree._slot_row is None else 2 + 1))                 # row and position once kept
    search = (_capacity(nodes + 2) * (32 + 2 + 4)                           # centre, row of children, leaf row
              + _capacity(tree._n_inner) * 2 * tree.params.branching        # inner nodes' children (int16)
              + _capacity(rows) * 3 * 4                                     # block start and length, fill
              + _capacity(blocks * 4 // 3) * (2 if slots <= 0x7FFF else 4)  # the leaves' blocks (int16 while it fits)
              + _capacity(slots) * per_slot + 32                            # the slots, a spare descriptor
              + 2 * _list_bytes(n_free) + _INT * n_free                     # free rows and slots: lists of ints
              + _capacity((n_words + 7) // 8) + _capacity(n_images) * 4     # found again, first word per image
              + (0 if tree.slots_are_words else 4)                          # the last add's slots
              * (n_words - voc.image_words(n_images - 1)[0] if n_images else 0)
              + (8 + 32) * len(voc.last_purged))                            # and the words it purged
    # a lent image: its keypoints (4 bytes each), the lent keypoints (2 bytes) and their
    # words' ranks unless they are 0 .. k - 1 (2 bytes), the other descriptors (32 bytes),
    # one object and one array header; otherwise word ids, keypoints and descriptors
    record = sys.getsizeof(LentFeatures(b"", 0, 0, (0, 0))) + sys.getsizeof(b"")
    images = 0
    for f in det._features:
        if isinstance(f, LentFeatures):
            images += 4 * f.n + 2 * f.k + (2 * f.k if f.ranked else 0) + 32 * (f.n - f.k) + record
        elif f is not None:
            images += f.nbytes
    latest = det.features_of(n_images - 1).words if n_images else np.zeros(0)
    images += (_list_bytes(n_images) + n_images + 2 * (n_images + n_images // 32 + 1) * 3 * 8  # the list, flags, poses
               + 8 * (len(det._posterior) + len(det._hyp_ids))                    # the filter's state
               + (2 if len(latest) and int(latest.max()) <= 0xFFFF else 4) * len(latest))  # the latest's words
    return {"images": images, "index": index, "vocabulary": search}


_INT = sys.getsizeof(1 << 20)


def _width(top: int) -> int:
    """Bytes per entry of a counter whose largest value is ``top`` (int8, int16, int32, int64)."""
    return 1 if top <= 127 else 2 if top <= 32767 else 4 if top < 2**31 else 8


def _list_bytes(n: int) -> int:
    """The most a Python list of ``n`` items holds (CPython grows it by an eighth and a few)."""
    return sys.getsizeof([]) + 8 * (n + n // 8 + 8)


def _lent_words(det: ForwardDetector) -> tuple[int, int]:
    """Descriptors the images in memory lend, and the searchable words made by those images."""
    lent = made = 0
    voc = det.vocabulary
    for t, f in enumerate(det._features):
        if isinstance(f, LentFeatures):
            lent += f.k
            lo, hi = voc.image_words(t)
            made += int(voc.searchable(np.arange(lo, hi)).sum())
    return lent, made


def test_memory_per_image_on_the_corridor_is_what_the_structures_need(corridor):
    """After each of the corridor's first images (where fixed and spare room weigh most
    per image) and after all 84, each part holds no more than its contents need (the
    bound above, computed from the counts), and the whole is within the 16 kB per image
    of the target."""
    det = ForwardDetector(method_params("default"))
    for t, f in enumerate(corridor):
        det.process_features(f)
        if t < 12 or t == len(corridor) - 1:
            mem, bound = det.memory_bytes(), _structure_bound(det)
            assert mem["images"] <= bound["images"], t
            assert mem["index"] <= bound["index"], t
            assert mem["vocabulary"] <= bound["vocabulary"], t
    assert sum(mem.values()) / len(corridor) <= 16_000


def test_the_latest_image_lends_at_once_and_keeps_its_words(corridor):
    """The latest image lends the descriptors that made its words as soon as it joined
    (the search holds them once), and reads back with its word ids (as the vocabulary
    gave them) and its keypoints and descriptors as given; the image before it no longer
    has word ids."""
    det = ForwardDetector(method_params("default"))
    voc = Vocabulary(dim=32, binary=True, params=method_params("default").vocabulary)
    for t, f in enumerate(corridor[:6]):
        det.process_features(f)
        words, made = voc.add(f.descriptors)
        kept = det._features[t]
        assert isinstance(kept, LentFeatures) and kept.k == made > 0
        got = det.features_of(t)
        np.testing.assert_array_equal(got.words, words)
        np.testing.assert_array_equal(got.descriptors, f.descriptors)
        np.testing.assert_array_equal(got.keypoints_q, compact(f, words).keypoints_q)
        ids, descs = det.vocabulary.last_new  # the new words, as the daemon's store reads them
        lo, hi = det.vocabulary.image_words(t)
        np.testing.assert_array_equal(ids, np.arange(lo, hi))
        np.testing.assert_array_equal(descs, f.descriptors[voc.last_new_at])  # the same words, made alike
        assert len(det.vocabulary.last_new_at) == 0  # handed to the image, not kept twice
        if t:
            assert len(det.features_of(t - 1).words) == 0


def test_a_detector_restored_from_its_map_holds_the_same_index_and_votes_alike(corridor, tmp_path):
    """The detector's images and words written to a map file as the daemon writes them,
    read back into a new detector after 60 images: its inverted index holds the same
    postings and counts, and the last 24 images' words (as the first detector's vocabulary
    quantises them; the restored word tree is built anew, so its own approximate search
    may answer differently) get the same votes to the bit."""
    from robotd.io.store import MapStore

    params = method_params("default")
    det = ForwardDetector(params)
    path = tmp_path / "map.sqlite"
    with MapStore.open(path) as store:
        run = store.begin_run("test = 1\n", started_ns=1)
        for t, f in enumerate(corridor[:60]):
            det.process_features(f)
            kf = store.add_keyframe(run, 10 + t, (0.1 * t, 0.0, 0.0), np.eye(3) * 1e-4, None)
            ids, descs = det.vocabulary.last_new
            c = det.features_of(t)
            store.add_forward_image(t, kf, params.features.kind, c.image_size_px, c.words, c.keypoints_q,
                                    c.descriptors, new_words=[(int(i), d.tobytes()) for i, d in zip(ids, descs)],
                                    purged=[int(i) for i in det.vocabulary.last_purged])
    with MapStore.open(path, read_only=True) as store:
        images, words = store.forward_memory()
    feats = [CompactFeatures(w, kq, np.frombuffer(d, np.uint8).reshape(-1, 32), size)
             for (_, _, _, size, w, kq, d) in images]
    wd = np.zeros((len(words), 32), np.uint8)
    for k, w in enumerate(words):
        if not w[4]:
            wd[k] = np.frombuffer(w[2], np.uint8)
    again = ForwardDetector(params)
    again.restore(feats, wd, np.array([w[3] for w in words], np.int64), np.array([w[4] for w in words], bool))
    all_words = np.arange(det.index.n_words, dtype=np.int64)
    for a, b in zip(det.index._post.gather(all_words), again.index._post.gather(all_words)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(det.index.occurrences(), again.index.occurrences())
    assert det.vocabulary.n_searchable == again.vocabulary.n_searchable
    for f in corridor[60:]:
        q = det.vocabulary.quantize(f.descriptors)
        (s1, v1), (s2, v2) = det.index.vote(q), again.index.vote(q)
        np.testing.assert_array_equal(s1, s2)
        assert v1 == v2
    b1, b2 = _structure_bound(again), again.memory_bytes()
    assert b2["index"] <= b1["index"] and b2["vocabulary"] <= b1["vocabulary"] and b2["images"] <= b1["images"]
    # the same images: each lends the same descriptors to the same words (the latest,
    # whole in the first detector, lends in the restored one), and reads back the same
    for t in range(60):
        a, b = det._features[t], again._features[t]
        lo, hi = det.vocabulary.image_words(t)
        assert isinstance(b, LentFeatures) == bool(det.vocabulary.searchable(np.arange(lo, hi)).any())
        if t < 59:
            assert type(a) is type(b)
            if isinstance(a, LentFeatures):
                assert a.data == b.data
        got, want = again.features_of(t), det.features_of(t)
        np.testing.assert_array_equal(got.keypoints_q, want.keypoints_q)
        np.testing.assert_array_equal(got.descriptors, want.descriptors)
    assert _lent_words(again)[0] == _lent_words(again)[1] == again.vocabulary.n_searchable


def _copies(f: Features) -> Features:
    return Features(f.keypoints_px.copy(), f.descriptors.copy(), f.image_size_px)


def test_memory_counted_is_what_python_allocated_for_the_detector(corridor):
    """What ``memory_bytes`` counts after 20 and after the 84 images is within 3 % of what the
    interpreter allocated for the detector while it ran (tracemalloc; each image's
    features made inside the run so that what the detector keeps of them counts): nothing
    it holds per image is left out (a dict of image ids, lists of Python ints, object and
    array headers), and nothing is counted twice. The cycle collector runs before each
    reading: what processing the images left in reference cycles (their Detection records
    among it) waits for it, and the detector does not hold it."""
    warm = ForwardDetector(method_params("default"))
    for f in corridor:  # imports and caches before the measurement (the verification's too)
        warm.process_features(_copies(f))
    del warm
    tracemalloc.start()
    try:
        det = ForwardDetector(method_params("default"))
        start = tracemalloc.get_traced_memory()[0]
        for t, f in enumerate(corridor):
            det.process_features(_copies(f))
            f = None
            if t == 19:  # early, where what an image leaves behind for one image weighs most
                gc.collect()
                early = tracemalloc.get_traced_memory()[0] - start, sum(det.memory_bytes().values())
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - start
    finally:
        tracemalloc.stop()
    counted = sum(det.memory_bytes().values())
    assert 0.97 * grown <= counted <= 1.03 * grown, (counted, grown)
    assert 0.97 * early[0] <= early[1] <= 1.03 * early[0], early


@pytest.mark.parametrize("memory", [MemoryParams(), MemoryParams(max_places=30)], ids=["unbounded", "bounded"])
def test_lent_descriptors_read_back_as_given_through_purges(corridor, memory):
    """Every past image's features read back as they were given (the same keypoints in
    1/16 px, the same descriptors) while the images lend the descriptors that made words
    the word search still holds: each of those words' descriptors is held once, by the
    search (the images lend as many as their words are searchable); images whose words
    were purged (50 images on) have them back. With a bounded working memory, images
    moved out of the index keep theirs the same way."""
    params = replace(method_params("default"), memory=memory)
    det = ForwardDetector(params)
    for t, f in enumerate(corridor):
        det.process_features(f)
        if t in (40, 83):
            lent, made = _lent_words(det)
            assert lent == made > 1000
    assert det.vocabulary.purged > 1000  # words of the first 34 images seen once: gone
    # images 34-83 are not examined yet: they lend every word they made (an image that
    # made none lends nothing); the older ones had the words seen once given back (all of
    # them, or they keep lending the rest)
    voc = det.vocabulary
    for t in range(84):  # the latest, 83, lends its words already
        lo, hi = voc.image_words(t)
        f = det._features[t]
        lent = f.k if isinstance(f, LentFeatures) else 0
        assert lent == (hi - lo if t >= 34 else int(voc.searchable(np.arange(lo, hi)).sum()))
    if memory.bounded:
        assert det.memory.transferred > 0
    for t, f in enumerate(corridor):
        got, want = det.features_of(t), compact(f, np.zeros(0))
        np.testing.assert_array_equal(got.keypoints_q, want.keypoints_q)
        np.testing.assert_array_equal(got.descriptors, want.descriptors)
        assert got.image_size_px == want.image_size_px


def test_words_of_images_out_of_memory_keep_their_descriptors(corridor):
    """With a loader (the daemon's map), images older than the last 8 leave memory with
    what they lent: the words they made that the search still holds keep their
    descriptors there (the founding keypoint's), so later images still find them; the
    images come back whole from the loader."""
    stored = {}
    det = ForwardDetector(method_params("default"), loader=lambda t: stored[t], resident=8)
    founding = {}
    for t, f in enumerate(corridor):
        det.process_features(f)
        stored[t] = det.features_of(t)
        lo, hi = det.vocabulary.image_words(t)
        w = stored[t].words.astype(np.int64)
        for word in range(lo, hi):
            founding[word] = f.descriptors[int(np.flatnonzero(w == word)[0])]
        det.mark_stored(t)
    assert [t for t, f in enumerate(det._features) if f is not None] == list(range(76, 84))
    voc = det.vocabulary
    old = np.array([w for w in range(voc.image_words(76)[0]) if voc.searchable(np.array([w]))[0]], np.int64)
    assert len(old) > 500
    np.testing.assert_array_equal(voc.word_descriptors(old), np.stack([founding[w] for w in old.tolist()]))
    found = voc.quantize(voc.word_descriptors(old))
    assert np.mean(found == old) > 0.9  # the tree's search is approximate; the words are there
    for t in (0, 40, 75):
        np.testing.assert_array_equal(det.features_of(t).descriptors, corridor[t].descriptors)


def test_words_purged_after_one_image_are_given_back(corridor):
    """With purging one image on, an image's words seen once leave the search at the next
    image: the image lent every word it made while it was the latest, and gets those
    back then, so the images lend exactly the words the search still holds (the latest
    all it made, the older ones only those seen again), and every image reads back as
    given."""
    params = method_params("default")
    params = replace(params, vocabulary=replace(params.vocabulary, purge_after=1))
    det = ForwardDetector(params)
    for f in corridor[:30]:
        det.process_features(f)
    lent, made = _lent_words(det)
    assert 0 < lent == made == det.vocabulary.n_searchable
    voc = det.vocabulary
    lo, hi = voc.image_words(29)
    assert det._features[29].k == hi - lo  # the latest: all it made
    lo, hi = voc.image_words(28)
    older = det._features[28]
    assert (older.k if isinstance(older, LentFeatures) else 0) < hi - lo  # some given back
    for t, f in enumerate(corridor[:30]):
        np.testing.assert_array_equal(det.features_of(t).descriptors, f.descriptors)
