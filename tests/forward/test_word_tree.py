"""The binary word tree (robotd.forward.vocabulary.BinaryWordTree): the vocabulary's own
nearest-word search over ORB words, its purging that frees memory, and the grouping of an
image's new descriptors."""

from __future__ import annotations

import numpy as np
import pytest

from pathlib import Path

from robotd.forward.vocabulary import (BinaryWordTree, TreeParams, Vocabulary, VocabularyParams, hamming_bits,
                                       pack_bits)
from tests.shared_data import require


DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def _clustered(rng: np.random.Generator, n_centres: int, per: int, flips: int) -> np.ndarray:
    """``n_centres * per`` 256-bit descriptors: random centres, each copy with ``flips``
    random bits changed (``(N, 32) uint8``)."""
    centres = rng.integers(0, 256, (n_centres, 32), dtype=np.uint8)
    bits = np.unpackbits(np.repeat(centres, per, axis=0), axis=1)
    for row in bits:
        row[rng.choice(256, flips, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def _exact(words: np.ndarray, ids: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = hamming_bits(pack_bits(q)[:, None, :], pack_bits(words)[None, :, :])
    j = d.argmin(axis=1)
    return ids[j], d[np.arange(len(q)), j]


def test_hamming_bits_counts_differing_bits():
    a = np.zeros((1, 32), np.uint8)
    b = a.copy()
    b[0, 0], b[0, 31] = 0b1011, 0xFF
    full = np.full((1, 32), 0xFF, np.uint8)
    assert hamming_bits(pack_bits(a), pack_bits(b)).tolist() == [11]
    assert hamming_bits(pack_bits(a), pack_bits(full)).tolist() == [256]  # no wrap at 256


@pytest.mark.parametrize("shape_a, shape_b", [((7, 1), (7, 5)), ((6, 1), (1, 9)), ((5,), ()), ((), (4,)),
                                               ((3, 1, 2), (1, 4, 1)), ((0, 1), (1, 3)), ((4,), (4,))])
def test_hamming_bits_broadcasts_as_numpy_does(shape_a, shape_b):
    """Every broadcast (the repeated operands of the tree's searches) against each pair's
    bits counted one by one; the all-different pair counts 256."""
    rng = np.random.default_rng(len(shape_a) * 10 + len(shape_b))
    a = rng.integers(0, 256, shape_a + (32,), dtype=np.uint8)
    b = rng.integers(0, 256, shape_b + (32,), dtype=np.uint8)
    if a.size and b.size:
        a.reshape(-1, 32)[0] = 0xFF
        b.reshape(-1, 32)[0] = 0
    got = hamming_bits(pack_bits(a.reshape(-1, 32)).reshape(shape_a + (4,)),
                       pack_bits(b.reshape(-1, 32)).reshape(shape_b + (4,)))
    want = np.unpackbits(a[..., None, :] ^ b[..., None, :], axis=-1).sum(axis=(-2, -1))
    assert got.dtype == np.int32 and got.shape == np.broadcast_shapes(shape_a, shape_b)
    assert np.array_equal(got, want)
    if a.size and b.size:
        assert got.reshape(-1)[0] == 256


def test_the_tree_finds_every_stored_word_and_mostly_the_nearest():
    rng = np.random.default_rng(0)
    words = _clustered(rng, 300, 10, 30)           # 3000 words in clusters of 10
    tree = BinaryWordTree(TreeParams(branching=8, leaf_size=32, beam=4))
    ids = np.arange(len(words)) * 3 + 5             # ids need not be 0..n-1
    for k in range(0, len(words), 250):             # incrementally, as images come
        tree.add(ids[k:k + 250], pack_bits(words[k:k + 250]))
    assert len(tree) == 3000 and tree._n_nodes > 50  # it did split
    found, dist = tree.nearest(pack_bits(words))
    assert (found == ids).all() and (dist == 0).all()  # a stored word is its own nearest
    got, gd = tree.nearest(pack_bits(_clustered(rng, 50, 1, 0)))  # unrelated: about 128 bits from all
    assert ((got == -1) | (gd > 40)).all()


def test_on_real_orb_words_the_tree_finds_a_word_where_an_exact_search_does():
    """The search is approximate: on the real corridor's ORB descriptors (300 per image),
    of the descriptors of later images that have a word within the radius, the tree finds
    one for nearly all (0.95 measured over the whole sequence with the default
    parameters), never a word beyond the radius, and always a word at least as far as the
    exact nearest."""
    from robotd.forward.features import FeatureExtractor, FeatureParams
    from robotd.io.sequence import list_images, read_image

    samples = require(DATA / "forward" / "rtabmap_samples", "the rtabmap_samples corridor")
    files = list_images(samples, exclude=(samples / "ground_truth.bmp",))
    ex = FeatureExtractor(FeatureParams(kind="orb", max_features=300))
    descs = [ex(read_image(f)).descriptors for f in files[:36]]
    voc = Vocabulary(dim=32, binary=True, params=VocabularyParams())
    for d in descs[:30]:
        voc.add(d)
    keys, words = np.arange(len(voc)), np.zeros((len(voc), 32), np.uint8)
    voc2 = Vocabulary(dim=32, binary=True, params=VocabularyParams())  # the same words, to read them back
    for d in descs[:30]:
        voc2.add(d)
        ids, new = voc2.last_new
        words[ids] = new
    q = np.vstack(descs[30:])
    want, wd = _exact(words, keys, q)
    got = voc.quantize(q)
    has = wd <= 40
    assert has.sum() > 300
    found = got >= 0
    assert np.mean(found[has]) > 0.88
    assert not found[~has].any()
    gd = hamming_bits(pack_bits(q[found]), pack_bits(words[got[found]]))
    assert (gd >= wd[found]).all() and (gd <= 40).all()


def test_removed_words_are_not_found_and_their_memory_is_reused():
    rng = np.random.default_rng(1)
    tree = BinaryWordTree(TreeParams(branching=4, leaf_size=16, beam=2))
    a = rng.integers(0, 256, (400, 32), dtype=np.uint8)
    tree.add(np.arange(400), pack_bits(a))
    size = tree.memory_bytes()
    tree.remove(np.arange(0, 400, 2))
    assert len(tree) == 200
    found, dist = tree.nearest(pack_bits(a))
    assert (found[1::2] == np.arange(1, 400, 2)).all() and (dist[1::2] == 0).all()
    assert not np.isin(found[::2], np.arange(0, 400, 2)).any()  # removed words are never answered
    b = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    tree.add(np.arange(400, 600), pack_bits(b))     # as many new words: the freed slots take them
    assert tree._n_slots == 400
    assert tree.memory_bytes() <= size * 1.3       # grows only by the tree's new nodes
    assert (tree.nearest(pack_bits(b))[0] == np.arange(400, 600)).all()


def test_the_tree_is_deterministic():
    rng = np.random.default_rng(2)
    d = _clustered(rng, 100, 8, 25)
    q = _clustered(rng, 50, 2, 0)
    out = []
    for _ in range(2):
        t = BinaryWordTree(TreeParams(branching=8, leaf_size=24, beam=3))
        for k in range(0, len(d), 100):
            t.add(np.arange(k, min(k + 100, len(d))), pack_bits(d[k:k + 100]))
        out.append(t.nearest(pack_bits(q)))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])


def _greedy_reference(d: np.ndarray, radius: float) -> np.ndarray:
    """The grouping as first written: one pass over every unmatched descriptor."""
    dist = hamming_bits(pack_bits(d)[:, None, :], pack_bits(d)[None, :, :])
    owner = np.full(len(d), -1)
    n = 0
    for k in range(len(d)):
        if owner[k] >= 0:
            continue
        claim = (owner < 0) & (dist[k] <= radius)
        claim[:k] = False
        owner[claim] = n
        owner[k] = n
        n += 1
    return owner


def test_grouping_an_images_new_descriptors_is_the_greedy_pass():
    rng = np.random.default_rng(3)
    d = _clustered(rng, 40, 4, 18)[rng.permutation(160)]  # groups within the radius, in any order
    d = np.vstack([d, rng.integers(0, 256, (60, 32), dtype=np.uint8)])  # and loners
    voc = Vocabulary(dim=32, binary=True, params=VocabularyParams(word_radius_bits=40))
    rank, founders = voc._group(d)
    ref = _greedy_reference(d, 40)
    np.testing.assert_array_equal(rank, ref)
    assert len(founders) == ref.max() + 1 < len(d)
    words, new = voc.add(d)
    np.testing.assert_array_equal(words, ref)


def test_first_k_is_the_stable_argsorts_first_columns() -> None:
    """The descent's partial selection equals the stable sort it replaces, ties (many in
    Hamming distances) to the lower column, the -1 of the greedy child first."""
    from robotd.forward.vocabulary import _first_k

    rng = np.random.default_rng(8)
    for m, k in ((64, 4), (16, 4), (5, 8), (48, 1), (4096, 6)):
        d = rng.integers(0, 6, (200, m)).astype(np.int32)
        d[rng.random(d.shape) < 0.1] = 1 << 20      # missing children (the descent's _FAR)
        d[np.arange(200), rng.integers(0, m, 200)] = -1
        np.testing.assert_array_equal(_first_k(d, k), np.argsort(d, axis=1, kind="stable")[:, :k])


def test_words_added_at_the_searchs_greedy_leaves_build_the_same_tree():
    """A vocabulary passes the search's greedy leaves to ``add`` instead of descending
    again: the tree must come out the same as when ``add`` finds them itself (including
    the leaves that split)."""
    rng = np.random.default_rng(3)
    words = _clustered(rng, 200, 12, 25)
    a = BinaryWordTree(TreeParams(branching=8, leaf_size=32, beam=4))
    b = BinaryWordTree(TreeParams(branching=8, leaf_size=32, beam=4))
    for k in range(0, len(words), 300):
        q = pack_bits(words[k:k + 300])
        ids = np.arange(k, k + len(q))
        a.nearest(q)
        a.add(ids, q, a.last_greedy)
        b.add(ids, q)
    assert a._n_nodes == b._n_nodes > 20
    probe = pack_bits(_clustered(rng, 100, 3, 20))
    for x, y in zip(a.nearest(probe), b.nearest(probe)):
        assert (x == y).all()
    assert (a.nearest(pack_bits(words))[0] == np.arange(len(words))).all()


def _scan_reference(tree: BinaryWordTree, q: np.ndarray, beam: int) -> tuple[np.ndarray, np.ndarray]:
    """What :meth:`BinaryWordTree.nearest` must answer, one query at a time in plain loops:
    the leaves the descent reaches, their words whose first 64 bits differ by at most the
    prefilter's 20, the nearest of those, ties to the lowest slot."""
    leaves = tree._descend(q, beam)
    words, dist = np.full(len(q), -1, np.int64), np.full(len(q), 1 << 20, np.int32)
    for i in range(len(q)):
        best = None
        for node in leaves[i].tolist():
            if node < 0:
                continue
            for s in tree.leaf_slots(node).tolist():
                if int(np.bitwise_count(q[i, 0] ^ tree._desc[s, 0])) > 20:
                    continue
                d = int(np.bitwise_count(q[i] ^ tree._desc[s]).sum())
                if best is None or (d, s) < best:
                    best = (d, s)
        if best is not None:
            words[i], dist[i] = tree.slot_words()[best[1]], best[0]
    return words, dist


def test_the_vectorised_leaf_scan_is_the_plain_scan_after_removals():
    """The search's gathers over the leaves (prefilter, full distance, nearest per query
    with ties to the lowest slot) answer what a plain per-query scan of the same leaves
    does, also once removals have moved words inside their leaves and freed slots were
    reused."""
    rng = np.random.default_rng(11)
    tree = BinaryWordTree(TreeParams(branching=4, leaf_size=24, beam=3))
    a = _clustered(rng, 60, 12, 12)
    tree.add(np.arange(len(a)), pack_bits(a))
    tree.remove(rng.choice(len(a), 300, replace=False))
    b = _clustered(rng, 30, 8, 12)
    tree.add(np.arange(len(a), len(a) + len(b)), pack_bits(b))
    q = pack_bits(np.concatenate([_clustered(rng, 20, 5, 10), a[::7], b[::5]]))
    got = tree.nearest(q)
    ref = _scan_reference(tree, q, 3)
    assert (ref[0] >= 0).sum() > len(q) // 2         # the prefilter lets words through
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])


@pytest.mark.parametrize("spread", [1, 1000], ids=["narrow ids (a table)", "ids spread wider than the table"])
def test_slots_and_descriptors_of_words_are_where_the_words_were_put(spread):
    """``slots_of`` finds each held word's slot (after removals, freed slots taken by new
    words) and -1 for words not held (removed, never added, between held ids), whether
    the ids asked for lie close together or far apart; ``descriptors`` reads each held
    word's descriptor as added."""
    rng = np.random.default_rng(5)
    tree = BinaryWordTree(TreeParams(branching=4, leaf_size=16, beam=2))
    ids = np.arange(300, dtype=np.int64) * spread
    a = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    tree.add(ids[:200], pack_bits(a[:200]))
    tree.remove(ids[:200:3])
    tree.add(ids[200:], pack_bits(a[200:]))
    held = np.ones(300, bool)
    held[:200:3] = False
    ask = np.concatenate([ids, ids[1:] - 1 if spread > 1 else np.zeros(0, np.int64), [ids[-1] + 1]])
    slots = tree.slots_of(ask)
    want = {int(w): s for s, w in enumerate(tree.slot_words().tolist()) if w >= 0}
    assert slots.tolist() == [want.get(int(w), -1) for w in ask]
    assert (slots[:300] >= 0).tolist() == held.tolist()
    d, found = tree.descriptors(ids)
    assert found.tolist() == held.tolist()
    np.testing.assert_array_equal(d[held].view(np.uint8), a[held])
    assert not d[~held].any()


def _descend_every_query(tree: BinaryWordTree, q: np.ndarray, beam: int) -> np.ndarray:
    """The beam's leaves with every query taken down every level until all fronts are
    leaves (each query's front kept, ranked again, at the levels below its leaves)."""
    from robotd.forward.vocabulary import _FAR, _first_k

    n = len(q)
    front = np.zeros((n, 1), np.int32)
    b = tree.params.branching
    while True:
        kids = tree._children(front)
        if np.array_equal(kids[:, :, 0], front):
            return front
        cand = kids.reshape(n, -1)
        dist = hamming_bits(q[:, None, :], tree._centre.take(cand, axis=0))
        dist[cand < 0] = _FAR
        dist[np.arange(n), np.argmin(dist[:, :b], axis=1)] = -1
        front = np.take_along_axis(cand, _first_k(dist, beam), axis=1)


@pytest.mark.parametrize("branching, leaf_size, beam", [(16, 32, 4), (4, 6, 2), (2, 3, 4), (3, 4, 8), (2, 2, 1)])
def test_queries_that_reached_their_leaves_stop_with_the_front_a_further_level_gives(branching, leaf_size, beam):
    """A tree whose branches differ in depth (small leaves, words in clusters of different
    sizes, some removed): the search's leaves and nearest words are those of taking every
    query down every level, beams wider than the branching included."""
    rng = np.random.default_rng(branching * 100 + leaf_size)
    tree = BinaryWordTree(TreeParams(branching=branching, leaf_size=leaf_size, beam=beam))
    words = np.concatenate([_clustered(rng, 4, 60, 20), _clustered(rng, 30, 3, 30)])
    ids = np.arange(len(words))
    for at in range(0, len(words), 37):
        tree.add(ids[at:at + 37], pack_bits(words[at:at + 37]))
    tree.remove(rng.choice(ids, 40, replace=False))
    q = pack_bits(np.concatenate([_clustered(rng, 4, 25, 25), rng.integers(0, 256, (50, 32), dtype=np.uint8)]))
    got = tree._descend(q, beam)
    want = _descend_every_query(tree, q, beam)
    assert np.array_equal(got, want)
    leaf_depth = []
    for node in np.unique(want[want >= 0]).tolist():  # the leaves reached lie at different depths
        d, cur = 0, node
        while cur != 0:
            cur = int(np.flatnonzero((tree._children(np.arange(tree._n_nodes)) == cur).any(axis=1) & (np.arange(tree._n_nodes) != cur))[0])
            d += 1
        leaf_depth.append(d)
    assert len(set(leaf_depth)) > 1


def _places_agree(tree: BinaryWordTree) -> None:
    """Every held word's slot sits in its leaf's block where its row and position say, and
    every leaf's filled entries are held slots."""
    rows = tree._leaf_row[:tree._n_nodes]
    rows = rows[rows >= 0]
    listed = np.concatenate([tree._pool[tree._row_start[r]:tree._row_start[r] + tree._fill[r]] for r in rows])
    held = np.flatnonzero(tree.slot_words() >= 0)
    assert sorted(listed.tolist()) == held.tolist()
    at = tree._row_start[tree._slot_row[held]].astype(np.int64) + tree._slot_pos[held]
    np.testing.assert_array_equal(tree._pool[at], held)
    assert (tree._fill[tree._slot_row[held]] > tree._slot_pos[held]).all()


def test_a_young_tree_keeps_descriptors_and_leaves_only_and_the_rest_from_its_first_removal():
    """While words come in id order and none was removed, slot s holds word s and the tree
    keeps no per-slot word id, row or position (4 + 2 + 1 bytes a word): it holds the
    descriptors, the leaves' blocks (2 bytes an entry while the slots fit int16) and the
    nodes. Its first removal builds the rows and positions from the leaves; from then on
    each removal moves a leaf's last entry into the hole, words land in freed slots, and
    every word is found where it was put."""
    rng = np.random.default_rng(21)
    tree = BinaryWordTree(TreeParams(branching=4, leaf_size=24, beam=2))
    a = _clustered(rng, 40, 10, 14)
    tree.add(np.arange(len(a)), pack_bits(a))
    assert tree.slots_are_words and tree._slot_row is None and tree._slot_pos is None
    assert tree._pool.dtype == np.int16 and tree._n_nodes > 20
    slots = len(a)
    per_slot = (tree._desc.nbytes - 32) / slots                      # the spare descriptor row aside
    assert per_slot <= 32 * (1 + 1 / 32 + 16 / slots)
    assert (tree.nearest(pack_bits(a))[0] == np.arange(len(a))).all()
    assert tree.slots_of(np.array([-1, 0, len(a) - 1, len(a)])).tolist() == [-1, 0, len(a) - 1, -1]
    gone = rng.choice(len(a), 150, replace=False)
    tree.remove(gone)
    assert not tree.slots_are_words and tree._slot_row is not None
    _places_agree(tree)
    b = _clustered(rng, 20, 10, 14)
    ids_b = np.arange(len(a), len(a) + len(b))
    tree.add(ids_b, pack_bits(b))                                     # into the freed slots first
    assert tree._n_slots == len(a) + len(b) - 150
    _places_agree(tree)
    tree.remove(np.concatenate([ids_b[::3], np.setdiff1d(np.arange(len(a)), gone)[::5]]))
    _places_agree(tree)
    left = np.setdiff1d(np.concatenate([np.arange(len(a)), ids_b]),
                        np.concatenate([gone, ids_b[::3], np.setdiff1d(np.arange(len(a)), gone)[::5]]))
    both = np.concatenate([a, b])
    assert (tree.nearest(pack_bits(both[left]))[0] == left).all()


def test_a_word_added_out_of_id_order_keeps_the_slots_word_ids():
    """Slot s holds word s only while words come in id order: a tree given other ids
    (a vocabulary restored without its purged words) keeps each slot's word id and
    answers those ids."""
    rng = np.random.default_rng(4)
    a = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    ids = np.arange(300) * 3 + 1
    tree = BinaryWordTree(TreeParams(branching=4, leaf_size=32, beam=2))
    tree.add(ids[:100], pack_bits(a[:100]))
    assert not tree.slots_are_words
    tree.add(ids[100:], pack_bits(a[100:]))
    assert (tree.nearest(pack_bits(a))[0] == ids).all()
    assert tree.slots_of(ids).tolist() == list(range(300))


def test_the_leaves_pool_widens_when_the_slots_pass_int16():
    """The leaves' blocks hold slots as int16 until a slot passes 32,767, then int32; every
    word is found before and after."""
    rng = np.random.default_rng(8)
    a = rng.integers(0, 256, (33_000, 32), dtype=np.uint8)
    tree = BinaryWordTree(TreeParams(branching=16, leaf_size=256, beam=1))
    tree.add(np.arange(32_000), pack_bits(a[:32_000]))
    assert tree._pool.dtype == np.int16
    tree.add(np.arange(32_000, 33_000), pack_bits(a[32_000:]))
    assert tree._pool.dtype == np.int32
    probe = np.concatenate([np.arange(0, 33_000, 97), np.arange(32_700, 33_000)])
    assert (tree.nearest(pack_bits(a[probe]))[0] == probe).all()
