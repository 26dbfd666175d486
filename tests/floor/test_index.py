"""The map index: shortlist by global Hamming similarity, local scoring of the shortlist only,
exclusions, growth, rebuilding from a map file, and finding the true revisit on a rendered run."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pytest

from robotd.floor.index import FloorIndex, IndexParams


@dataclass(frozen=True, eq=False)
class _Desc:
    """A stand-in descriptor: the index reads only ``global_bits``; the scorer gets the rest."""

    global_bits: np.ndarray
    tag: int = 0


@dataclass(frozen=True)
class _Result:
    score: float


class _CountingScorer:
    """Local scorer that records every pair it is asked about; score = ``tag`` of the stored one."""

    def __init__(self) -> None:
        self.calls: list[int] = []

    def __call__(self, query: _Desc, stored: _Desc) -> _Result:
        self.calls.append(stored.tag)
        return _Result(float(stored.tag))


def _hamming(a: np.ndarray, b: np.ndarray) -> int:
    """Bit differences counted the slow, obvious way."""
    return sum(bin(int(x) ^ int(y)).count("1") for x, y in zip(a.tolist(), b.tolist()))


def _random_index(n: int, n_bytes: int, seed: int, **params) -> tuple[FloorIndex, _CountingScorer, list[_Desc]]:
    rng = np.random.default_rng(seed)
    scorer = _CountingScorer()
    index = FloorIndex(IndexParams(**params), scorer=scorer)
    descs = [_Desc(rng.integers(0, 256, n_bytes, dtype=np.uint8), tag=i) for i in range(n)]
    for i, d in enumerate(descs):
        index.add(100 + i, d)
    return index, scorer, descs


def test_global_scores_are_one_minus_normalised_hamming():
    index = FloorIndex(scorer=_CountingScorer())
    a = np.array([0b1111_0000, 0b0000_0000], np.uint8)
    b = np.array([0b1111_0000, 0b0000_0111], np.uint8)  # 3 bits from a
    c = np.array([0b0000_1111, 0b1111_1111], np.uint8)  # all 16 bits from a
    for kf, bits in enumerate((a, b, c)):
        index.add(kf, _Desc(bits))
    assert index.global_scores(_Desc(a)).tolist() == [1.0, 1.0 - 3 / 16, 0.0]


def test_shortlist_bounds_local_matches_and_takes_the_globally_nearest():
    index, scorer, descs = _random_index(300, 64, seed=1)
    rng = np.random.default_rng(2)
    query = _Desc(rng.integers(0, 256, 64, dtype=np.uint8))
    cands = index.query(query, k=3, shortlist=7)
    assert len(scorer.calls) == 7 and index.local_matches == 7
    dist = np.array([_hamming(query.global_bits, d.global_bits) for d in descs])
    nearest = set(np.argsort(dist, kind="stable")[:7].tolist())
    assert set(scorer.calls) == nearest  # the 7 scored are the 7 nearest by Hamming
    # Candidates: the best 3 of the 7 by local score (here the tag), best first.
    assert [c.score for c in cands] == sorted((float(t) for t in nearest), reverse=True)[:3]
    assert [c.keyframe_id for c in cands] == [100 + int(c.score) for c in cands]
    for c in cands:
        assert c.global_score == pytest.approx(1.0 - dist[c.keyframe_id - 100] / 512)
    index.query(query, shortlist=7)
    assert index.local_matches == 14  # the counter accumulates


def test_default_k_and_shortlist_come_from_params():
    index, scorer, _ = _random_index(50, 8, seed=3, k=2, shortlist=4)
    cands = index.query(_Desc(np.zeros(8, np.uint8)))
    assert len(cands) == 2 and len(scorer.calls) == 4
    cands = index.query(_Desc(np.zeros(8, np.uint8)), k=10, shortlist=100)
    assert len(cands) == 10 and len(scorer.calls) == 4 + 50  # a shortlist beyond the map: all of it


def test_brute_force_scores_every_keyframe():
    index, scorer, _ = _random_index(40, 8, seed=4)
    best = index.brute_force(_Desc(np.zeros(8, np.uint8)), k=1)
    assert len(scorer.calls) == 40
    assert best[0].keyframe_id == 139 and best[0].score == 39.0  # the highest tag anywhere


def test_recent_keyframes_are_excluded_even_when_they_match_best():
    index, scorer, descs = _random_index(30, 16, seed=5)
    query = descs[-1]  # identical to the newest keyframe (id 129)
    cands = index.query(query, k=30, shortlist=30, exclude_after_id=119)
    ids = [c.keyframe_id for c in cands]
    assert len(ids) == 20 and max(ids) == 119 and 129 not in ids
    assert all(tag <= 19 for tag in scorer.calls)
    # Without the exclusion the newest keyframe tops the global shortlist.
    assert index.shortlist(query, size=1) == [(129, 1.0)]


@pytest.mark.parametrize("as_callable", [False, True])
def test_exclude_ids_as_set_or_predicate(as_callable):
    index, scorer, descs = _random_index(30, 16, seed=6)
    banned = {100, 105, 129}
    excl = (lambda kf: kf in banned) if as_callable else banned
    short = index.shortlist(descs[5], size=5, exclude_ids=excl)
    assert len(short) == 5 and not banned & {kf for kf, _ in short}
    # Excluded ids never reach the local scorer, however many are asked for.
    index.query(descs[5], k=30, shortlist=30, exclude_ids=excl)
    assert len(scorer.calls) == 27 and not {0, 5, 29} & set(scorer.calls)


def test_predicate_rejecting_the_whole_top_falls_through_to_the_rest():
    index, _, descs = _random_index(40, 16, seed=7)
    sims = index.global_scores(descs[0])
    order = np.argsort(-sims, kind="stable")
    top_ids = {100 + int(i) for i in order[:10]}
    short = index.shortlist(descs[0], size=3, exclude_ids=lambda kf: kf in top_ids)
    assert [kf for kf, _ in short] == [100 + int(i) for i in order[10:13]]


def test_array_grows_by_doubling_and_keeps_every_row():
    index, _, descs = _random_index(9, 24, seed=8, initial_capacity=4)
    assert index.capacity == 16 and len(index) == 9
    assert index.ids.tolist() == list(range(100, 109))
    for i, d in enumerate(descs):
        sims = index.global_scores(d)
        assert sims[i] == 1.0 and int(np.argmax(sims)) == i
    # 24 bytes = 3 words per row: the array holds capacity x 24 bytes plus the ids.
    assert index.nbytes >= 16 * 24 + 16 * 8


def test_adding_twice_or_another_length_is_refused():
    index = FloorIndex(scorer=_CountingScorer())
    index.add(1, _Desc(np.zeros(8, np.uint8)))
    with pytest.raises(ValueError, match="already"):
        index.add(1, _Desc(np.zeros(8, np.uint8)))
    with pytest.raises(ValueError, match="bits"):
        index.add(2, _Desc(np.zeros(16, np.uint8)))
    assert len(index) == 1 and 1 in index and 2 not in index


def test_empty_index_and_everything_excluded_give_no_candidates():
    scorer = _CountingScorer()
    index = FloorIndex(scorer=scorer)
    assert index.query(_Desc(np.zeros(8, np.uint8))) == []
    index.add(5, _Desc(np.zeros(8, np.uint8)))
    assert index.query(_Desc(np.zeros(8, np.uint8)), exclude_after_id=4) == []
    assert scorer.calls == []


def test_params_are_validated():
    with pytest.raises(ValueError, match="shortlist"):
        IndexParams(shortlist=0)
    with pytest.raises(ValueError, match="k"):
        IndexParams(k=0)


# ------------------------------------------------------------ with real descriptors


@pytest.fixture(scope="module")
def gravel_run():
    """Keyframes every 0.1 m along a 4 m straight run on a gravel floor, and a query frame
    taken later at 2.03 m, turned by 0.5 rad: the revisit the index must find."""
    import skimage.data

    from robotd.base.camera import FloorCameraModel, overlap_ratios
    from sim.world.floor import Floor
    from sim.pairs import straight_run
    from sim.cameras.floor import FloorRenderer, RenderParams

    floor = Floor.from_photos([skimage.data.gravel()], seed=3)
    cam = FloorCameraModel.default()
    poses, images = straight_run(floor, cam, np.random.default_rng(0), (0.0, 0.0, 0.0), 4.0, 0.1)
    q_pose = np.array([2.03, 0.02, 0.5])
    q_image = FloorRenderer(floor, cam, RenderParams(), np.random.default_rng(1)).render(q_pose, 0.1, 0.0, 30.0)
    overlap = overlap_ratios(cam, np.repeat(q_pose[None], len(poses), axis=0), poses)
    return images, q_image, overlap


def test_true_revisit_is_among_the_candidates_on_a_rendered_run(gravel_run):
    from robotd.floor.descriptor import decode, extract

    images, q_image, overlap = gravel_run
    mode = 4
    index = FloorIndex()
    for kf, image in enumerate(images):
        index.add(kf, decode(extract(image, mode)))
    query = decode(extract(q_image, mode))
    shortlist = 8
    cands = index.query(query, k=3, shortlist=shortlist)
    assert index.local_matches == shortlist  # 8 of the 41 keyframes scored, not all
    true = set(np.flatnonzero(overlap >= 0.33).tolist())
    assert len(true) >= 2  # the ground truth has revisits to find (about 1.8 to 2.2 m)
    assert cands[0].keyframe_id in true
    assert cands[0].local.score > 0
    assert all(a.score >= b.score for a, b in zip(cands, cands[1:]))
    # A keyframe far from the query (0 m vs 2.03 m) scores below the true revisit.
    far = index.brute_force(query, k=len(images))
    by_id = {c.keyframe_id: c.score for c in far}
    assert overlap[0] == 0.0 and by_id[0] < cands[0].score


def test_from_store_round_trip_skips_a_corrupt_descriptor(gravel_run, tmp_path, caplog):
    from robotd.floor.descriptor import decode, extract
    from robotd.io.store import MapStore

    images = gravel_run[0][:6]
    mode = 3
    blobs = [extract(im, mode) for im in images]
    path = tmp_path / "map.db"
    with MapStore.open(path, image_codec="png", synchronous="NORMAL") as store:
        run = store.begin_run("", started_ns=0)
        ids = [store.add_keyframe(run, k, (0.1 * k, 0.0, 0.0), np.eye(3), None, b, mode)
               for k, b in enumerate(blobs)]
        bad = store.add_keyframe(run, 10, (0.0, 0.0, 0.0), np.eye(3), None,
                                 blobs[2][: len(blobs[2]) // 2], mode)  # truncated bytes
        other = store.add_keyframe(run, 11, (0.0, 0.0, 0.0), np.eye(3), None, extract(images[0], 1), 1)
        bare = store.add_keyframe(run, 12, (0.0, 0.0, 0.0), np.eye(3), None)  # no descriptor yet
    with MapStore.open(path, create=False) as store, caplog.at_level(logging.WARNING):
        index = FloorIndex.from_store(store, mode)
    assert index.ids.tolist() == ids
    assert index.load_report.corrupt_ids == (bad,)
    assert index.load_report.loaded == 6 and index.load_report.other_mode == 2
    assert any(str(bad) in rec.getMessage() for rec in caplog.records)
    assert other not in index and bare not in index
    # The rebuilt index answers like one built directly from the same bytes.
    direct = FloorIndex()
    for kf, b in zip(ids, blobs):
        direct.add(kf, decode(b))
    q = decode(blobs[4])
    assert np.array_equal(index.global_scores(q), direct.global_scores(q))
    a = index.query(q, k=3, shortlist=6)
    b = direct.query(q, k=3, shortlist=6)
    assert [c.keyframe_id for c in a] == [c.keyframe_id for c in b] and a[0].keyframe_id == ids[4]
    assert [c.score for c in a] == [c.score for c in b]
    # With two descriptors kept decoded the others are read back from the map, and score the same.
    with MapStore.open(path, create=False) as store:
        lazy = FloorIndex.from_store(store, mode, IndexParams(resident=2))
        c = lazy.query(q, k=3, shortlist=6)
        assert lazy.on_demand and lazy.loads >= 4 and lazy.load_failures == 0
    assert [(x.keyframe_id, x.score) for x in c] == [(x.keyframe_id, x.score) for x in a]
    with MapStore.open(path, create=False, read_only=True) as store:
        assert not FloorIndex.from_store(store, mode, on_demand=False).on_demand


def test_read_back_from_a_map_finds_the_loops_of_the_index_in_ram(gravel_run, tmp_path):
    """Two passes over the gravel run stored in a map, every keyframe of the second queried
    as the detector queries (the loop threshold as ``min_score``, the stop at ``k``): the
    index that reads its descriptors back (4 kept decoded) returns the same candidates, with
    the same scores and matched points, as the one holding every descriptor."""
    from robotd.app.demo import shipped_calibration
    from robotd.floor.descriptor import decode, extract
    from robotd.io.calibfile import read_calibration
    from robotd.io.store import MapStore

    mode = 4
    threshold = read_calibration(shipped_calibration()).loop.for_mode(mode)
    blobs = [extract(im, mode) for im in gravel_run[0]]
    path = tmp_path / "map.db"
    with MapStore.open(path, synchronous="NORMAL") as store:
        run = store.begin_run("", started_ns=0)
        ids = [store.add_keyframe(run, k, (0.1 * k, 0.0, 0.0), np.eye(3), None, b, mode)
               for k, b in enumerate(blobs + blobs[::-1])]
    in_ram = FloorIndex(IndexParams(shortlist=10))
    for kf, b in zip(ids, blobs + blobs[::-1]):
        in_ram.add(kf, decode(b))
    loops = 0
    with MapStore.open(path, create=False, read_only=True) as store:
        lazy = FloorIndex.from_store(store, mode, IndexParams(shortlist=10, resident=4))
        for kf in ids[len(blobs):]:
            q = decode(store.keyframe_descriptor(kf)[0])
            want = in_ram.query(q, k=5, exclude_after_id=ids[len(blobs) - 1], min_score=threshold)
            got = lazy.query(q, k=5, exclude_after_id=ids[len(blobs) - 1], min_score=threshold)
            assert [(c.keyframe_id, c.global_score, c.score, c.local.reason) for c in got] == \
                [(c.keyframe_id, c.global_score, c.score, c.local.reason) for c in want]
            assert all(np.array_equal(a.local.xy_a, b.local.xy_a) and np.array_equal(a.local.xy_b, b.local.xy_b)
                       for a, b in zip(got, want))
            loops += sum(c.score >= threshold for c in got)
    assert lazy.loads > len(blobs) and lazy.load_failures == 0  # most of the first pass was read back
    assert loops >= len(blobs)  # every keyframe of the second pass finds its first-pass self, at least


def _fields_equal(a, b) -> bool:
    from dataclasses import fields

    for f in fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            if x.dtype != y.dtype or x.shape != y.shape or not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


def test_packed_descriptors_come_back_equal_and_widen_when_they_must(gravel_run):
    from dataclasses import replace

    from robotd.floor.descriptor import decode, extract

    descs = [decode(extract(im, 2)) for im in gravel_run[0][:4]]
    index = FloorIndex()
    for kf, d in enumerate(descs):
        index.add(kf, d)
    assert index._packed.xy_dtype == np.float16 and index._packed.angle_coded
    assert all(_fields_equal(d, index.descriptor(kf)) for kf, d in enumerate(descs))
    # 2 bit planes + float16 x, y + an angle code per keypoint: about 21 of 28 bytes in mode 2 (one
    # word per plane), the chunk's unused rows apart.
    kp = sum(len(d) for d in descs)
    assert index._packed.chunks[0]["pos"].nbytes == 8 * index._packed.CHUNK and index._packed.used == kp
    # A position float16 cannot hold and an orientation off the 5-bit grid: everything widens,
    # earlier keyframes still come back equal.
    odd = replace(descs[0], xy_px=descs[0].xy_px + np.float32(0.001),
                  angle_rad=descs[0].angle_rad + np.float32(0.01))
    index.add(10, odd)
    assert index._packed.xy_dtype == np.float32 and not index._packed.angle_coded
    assert all(_fields_equal(d, index.descriptor(kf)) for kf, d in enumerate(descs))
    assert _fields_equal(odd, index.descriptor(10))
    # Queries score the packed descriptors as the originals.
    from robotd.floor.match import local_score

    got = {c.keyframe_id: c.score for c in index.query(descs[1], k=5, shortlist=5)}
    want = {kf: local_score(descs[1], d).score for kf, d in enumerate(descs)} | {10: local_score(descs[1], odd).score}
    assert got == want and got[1] > 0


def test_on_demand_descriptors_answer_as_resident_ones_and_count_reads(caplog):
    from robotd.base.errors import DescriptorError

    rng = np.random.default_rng(5)
    descs = {100 + i: _Desc(rng.integers(0, 256, 16, dtype=np.uint8), tag=i) for i in range(40)}
    reads: list[int] = []
    broken: set[int] = set()

    def loader(kf: int) -> _Desc:
        reads.append(kf)
        if kf in broken:
            raise DescriptorError(f"keyframe {kf}: bad bytes")
        return descs[kf]

    resident = FloorIndex(IndexParams(shortlist=8), scorer=_CountingScorer())
    lazy = FloorIndex(IndexParams(shortlist=8, resident=3), scorer=_CountingScorer(), loader=loader)
    for kf, d in descs.items():
        resident.add(kf, d)
        lazy.add(kf, d)
    assert lazy.on_demand and not resident.on_demand and not reads  # added: nothing read back
    q = _Desc(descs[117].global_bits.copy())
    want = [(c.keyframe_id, c.score) for c in resident.query(q, k=8)]
    got = [(c.keyframe_id, c.score) for c in lazy.query(q, k=8)]
    assert got == want
    # Only the three newest were resident: every other shortlisted keyframe was read once.
    short = {kf for kf, _ in lazy.shortlist(q)}
    assert sorted(reads) == sorted(short - {137, 138, 139}) and lazy.loads == len(reads)
    assert len(lazy._recent) == 3  # bounded, whatever was read
    assert lazy.descriptor(want[0][0]) is descs[want[0][0]]
    # A descriptor that cannot be read leaves that keyframe out of the query, logged and counted.
    broken.add(want[0][0])
    lazy._recent.clear()
    with caplog.at_level(logging.WARNING):
        got = [c.keyframe_id for c in lazy.query(q, k=8)]
    assert want[0][0] not in got and got == [kf for kf, _ in want if kf != want[0][0]]
    assert lazy.load_failures == 1 and any(str(want[0][0]) in r.getMessage() for r in caplog.records)


def test_a_query_stops_once_k_candidates_reach_min_score():
    """With ``enough`` (the default) and a ``min_score``, the shortlist is scored in global
    order until ``k`` candidates reach it: the rest is not scored (nor read back); without
    ``min_score``, or with ``enough`` off, every shortlisted keyframe is scored."""
    rng = np.random.default_rng(9)
    q = rng.integers(0, 256, 16, dtype=np.uint8)
    # global bits at 0, 1, 2, ... flipped bits from the query: shortlist order is the id order;
    # local score (the tag): 5 for every keyframe but the second and the fifth (1).
    tags = [5, 1, 5, 5, 1, 5, 5, 5, 5, 5]
    descs = []
    for i, tag in enumerate(tags):
        g = np.unpackbits(q.copy())
        g[:i] ^= 1
        descs.append(_Desc(np.packbits(g), tag=tag))

    def index(**params: object) -> tuple[FloorIndex, _CountingScorer]:
        scorer = _CountingScorer()
        ix = FloorIndex(IndexParams(shortlist=10, **params), scorer=scorer)
        for i, d in enumerate(descs):
            ix.add(i, d)
        return ix, scorer

    ix, scorer = index()
    got = ix.query(_Desc(q), k=3, min_score=3.0)
    # 0, 2, 3 reach 3.0 (1 does not): 4 scored, not 10
    assert [c.keyframe_id for c in got] == [0, 2, 3] and len(scorer.calls) == 4
    ix, scorer = index()
    assert len(ix.query(_Desc(q), k=3)) == 3 and len(scorer.calls) == 10  # no min_score: all scored
    ix, scorer = index(enough=False)
    full = ix.query(_Desc(q), k=3, min_score=3.0)
    assert len(scorer.calls) == 10 and [c.score for c in full] == [5.0] * 3
    ix, scorer = index()
    few = ix.query(_Desc(q), k=9, min_score=3.0)  # only 8 reach it: the whole shortlist is scored
    assert len(scorer.calls) == 10 and sum(c.score >= 3.0 for c in few) == 8


def test_a_query_that_stops_at_k_scores_the_resident_descriptors_first():
    """With a loader and ``enough`` stopping the query, the resident shortlisted keyframes
    are scored first: a query that finds its ``k`` loops among them reads nothing back
    (the same scores, the loops among the resident ones); ``resident_first`` off, the
    shortlist goes in global order (the default) and reads the older keyframes it scores."""
    rng = np.random.default_rng(9)
    q = rng.integers(0, 256, 16, dtype=np.uint8)
    descs = {}
    for i in range(20):  # global order = id order; every keyframe a loop (tag 5)
        g = np.unpackbits(q.copy())
        g[:i] ^= 1
        descs[i] = _Desc(np.packbits(g), tag=5)
    reads: list[int] = []

    def loader(kf: int) -> _Desc:
        reads.append(kf)
        return descs[kf]

    def index(**params: object) -> FloorIndex:
        ix = FloorIndex(IndexParams(shortlist=20, resident=4, **params), scorer=_CountingScorer(), loader=loader)
        for kf, d in descs.items():
            ix.add(kf, d)  # 16-19 stay resident
        return ix

    first = index(resident_first=True).query(_Desc(q), k=3, min_score=3.0)
    assert not reads and [c.keyframe_id for c in first] == [16, 17, 18]
    assert [c.score for c in first] == [5.0] * 3
    plain = index().query(_Desc(q), k=3, min_score=3.0)  # the default: global order
    assert reads == [0, 1, 2] and [c.keyframe_id for c in plain] == [0, 1, 2]
    reads.clear()
    more = index(resident_first=True).query(_Desc(q), k=6, min_score=3.0)  # 4 resident, then the best two read back
    assert reads == [0, 1] and sorted(c.keyframe_id for c in more) == [0, 1, 16, 17, 18, 19]


def test_resident_must_be_positive():
    with pytest.raises(ValueError):
        IndexParams(resident=0)


def test_a_query_scores_with_its_own_match_params(gravel_run):
    """``match_params`` of a query replaces the index's for that query only: with a match
    count no pair reaches every candidate is dismissed, the next query scores as before;
    RANSAC's adaptive stop finds the same revisit."""
    from robotd.floor.descriptor import decode, extract
    from robotd.floor.match import MatchParams

    images, q_image, overlap = gravel_run
    index = FloorIndex()
    for kf, image in enumerate(images):
        index.add(kf, decode(extract(image, 4)))
    query = decode(extract(q_image, 4))
    before = index.query(query, k=3, shortlist=8)
    refused = index.query(query, k=3, shortlist=8, match_params=MatchParams(min_matches=10_000))
    assert before[0].score > 0 and overlap[before[0].keyframe_id] >= 0.33
    assert [c.local.reason for c in refused] == ["TOO_FEW_MATCHES"] * 3
    again = index.query(query, k=3, shortlist=8)
    assert [(c.keyframe_id, c.score) for c in again] == [(c.keyframe_id, c.score) for c in before]
    adaptive = index.query(query, k=3, shortlist=8, match_params=MatchParams(confidence=0.99))
    assert adaptive[0].keyframe_id == before[0].keyframe_id and adaptive[0].local.n_inliers >= 10


# ------------------------------------------------------------ the shortlist's ranking


def _reference_shortlist(index: FloorIndex, query: _Desc, size: int, excluded: set[int],
                         after: int | None) -> list[tuple[int, float]]:
    """Every keyframe's Hamming distance counted the slow way, sorted by (distance, row)."""
    ids = index.ids.tolist()
    rows = [r for r, kf in enumerate(ids)
            if kf not in excluded and (after is None or kf <= after)]
    bits = 8 * query.global_bits.size
    dist = {r: _hamming(query.global_bits, index._global[:, r].view(np.uint8)[: query.global_bits.size])
            for r in rows}
    ranked = sorted(rows, key=lambda r: (dist[r], r))[:size]
    return [(ids[r], 1.0 - dist[r] / bits) for r in ranked]


@pytest.mark.parametrize("increasing", [True, False])
def test_the_shortlist_is_the_stable_ranking_with_every_tie_and_exclusion(increasing):
    """Two-byte global descriptors (hundreds of ties in 600 keyframes): the shortlist without a
    predicate (one key per row, excluded rows found by bisection while ids only grow) is the
    first ``size`` of the full ranking by distance then insertion order, as the predicate's
    path (the sort it replaced) gives it, for exclusions as a set, an array and an id bound."""
    rng = np.random.default_rng(11)
    index = FloorIndex(IndexParams(), scorer=_CountingScorer())
    ids = np.arange(1000, 1600) if increasing else rng.permutation(np.arange(1000, 1600))
    for kf in ids.tolist():
        index.add(kf, _Desc(rng.integers(0, 256, 2, dtype=np.uint8)))
    assert index._ids_increasing == increasing
    for trial in range(20):
        query = _Desc(rng.integers(0, 256, 2, dtype=np.uint8))
        size = int(rng.integers(1, 40))
        excluded = set(rng.choice(ids, int(rng.integers(0, 300)), replace=False).tolist())
        excluded |= {5, 99999}  # ids not in the index
        after = int(rng.integers(1000, 1700)) if trial % 3 == 0 else None
        want = _reference_shortlist(index, query, size, excluded, after)
        as_array = np.array(sorted(excluded), np.int64)
        for exclude in (excluded, as_array):
            assert index.shortlist(query, size, exclude, after) == want
        assert index.shortlist(query, size, lambda kf: kf in excluded, after) == want
    everything = index.shortlist(query, 700)
    assert len(everything) == 600 and everything == _reference_shortlist(index, query, 700, set(), None)
    assert index.shortlist(query, 5, exclude_after_id=999) == []


def test_queries_of_a_map_answer_as_scoring_the_ranked_keyframes_one_by_one(gravel_run, tmp_path):
    """The query's own paths (the shortlist by one key per row, the pairs scored together and
    refined together) against the plain one: every keyframe ranked by global distance then
    id, each scored alone by ``Matcher.score`` in that order until ``k`` reach the loop
    threshold, RANSAC at the daemon's confidence. Two passes over the gravel run in a map
    read back (4 resident), every keyframe of the second pass queried with the first pass
    alone allowed and then with an array of excluded ids: the same candidates, bit for bit
    (scores, counts, inlier indices and points, transforms)."""
    from robotd.app.demo import shipped_calibration
    from robotd.base.config import FloorDetectorConfig
    from robotd.floor.descriptor import decode, extract
    from robotd.floor.match import Matcher, MatchParams
    from robotd.io.calibfile import read_calibration
    from robotd.io.store import MapStore

    mode = 4
    threshold = read_calibration(shipped_calibration()).loop.for_mode(mode)
    mp = MatchParams(confidence=FloorDetectorConfig().ransac_confidence)
    blobs = [extract(im, mode) for im in gravel_run[0]]
    path = tmp_path / "map.db"
    with MapStore.open(path, synchronous="NORMAL") as store:
        run = store.begin_run("", started_ns=0)
        ids = [store.add_keyframe(run, k, (0.1 * k, 0.0, 0.0), np.eye(3), None, b, mode)
               for k, b in enumerate(blobs + blobs[::-1])]
    decoded = {kf: decode(b) for kf, b in zip(ids, blobs + blobs[::-1])}

    def plain(q, allowed: list[int], k: int = 5, shortlist: int = 10) -> list:
        gb = np.asarray(q.global_bits)
        dist = {kf: int(np.bitwise_count(gb ^ np.asarray(decoded[kf].global_bits)).sum()) for kf in allowed}
        ranked = sorted(allowed, key=lambda kf: (dist[kf], ids.index(kf)))[:shortlist]
        matcher, out = Matcher(q, mp), []
        for kf in ranked:
            result = matcher.score(decoded[kf], threshold)
            out.append((kf, 1.0 - dist[kf] / (8 * gb.size), result))
            if sum(r.score >= threshold for _kf, _g, r in out) == k:
                break
        out.sort(key=lambda c: (-c[2].score, -c[1], c[0]))
        return out[:k]

    def fields(kf, g, m) -> tuple:
        return (kf, g, m.score, m.n_matches, m.n_inliers, str(m.reason), m.inliers_a.tolist(), m.inliers_b.tolist(),
                m.xy_a.tobytes(), m.xy_b.tobytes(), None if m.transform is None else m.transform.tobytes())

    first = ids[: len(blobs)]
    loops = 0
    with MapStore.open(path, create=False, read_only=True) as store:
        index = FloorIndex.from_store(store, mode, IndexParams(shortlist=10, resident=4, match_params=mp))
        for i, kf in enumerate(ids[len(blobs):]):
            q = decoded[kf]
            got = index.query(q, k=5, exclude_after_id=first[-1], min_score=threshold)
            want = plain(q, first)
            assert [fields(c.keyframe_id, c.global_score, c.local) for c in got] == [fields(*w) for w in want]
            loops += sum(c.score >= threshold for c in got)
            banned = np.array(ids[len(blobs) + max(0, i - 3):], np.int64)  # the query's pass, as the bench excludes
            got = index.query(q, k=5, exclude_ids=banned, min_score=threshold)
            want = plain(q, [x for x in ids if x not in set(banned.tolist())])
            assert [fields(c.keyframe_id, c.global_score, c.local) for c in got] == [fields(*w) for w in want]
    assert loops >= len(blobs) and index.loads > len(blobs)
