"""The floor index's read back in two steps (``decode_local``): the local descriptors from the
stored bytes at once, the keypoints' positions only for a pair that passes the local score's
bound; the same descriptor, the same scores and the same candidates as a whole decode."""

from __future__ import annotations

import logging
import struct
import zlib

import numpy as np
import pytest

from robotd.base.errors import DescriptorError
from robotd.floor.descriptor import MODES, FloorDescriptor, PartialDescriptor, decode, decode_local, extract
from robotd.floor.index import FloorIndex, IndexParams
from robotd.floor.match import Matcher

@pytest.fixture(scope="module")
def run_images() -> list[np.ndarray]:
    """Frames every 0.1 m along a 2 m straight run on a gravel floor, and the same run
    again 0.02 m aside and turned by 0.3 rad: pairs that pass the bound and pairs that fail."""
    import skimage.data

    from sim.cameras.floor import FloorRenderer, RenderParams
    from sim.world.floor import Floor
    from robotd.base.camera import FloorCameraModel

    floor = Floor.from_photos([skimage.data.gravel()], seed=3)
    renderer = FloorRenderer(floor, FloorCameraModel.default(), RenderParams(), np.random.default_rng(1))
    return [renderer.render(np.array([0.1 * i, dy, th]), 0.1, 0.0, 30.0)
            for dy, th in ((0.0, 0.0), (0.02, 0.3)) for i in range(20)]


def _with_crc(data: bytes | bytearray) -> bytes:
    """``data`` with its CRC-32 recomputed (a forgery the checksum cannot catch)."""
    b = bytearray(data)
    b[16:20] = struct.pack("<I", zlib.crc32(bytes(b[20:]), zlib.crc32(bytes(b[:16]))))
    return bytes(b)


def _bad_positions(data: bytes) -> bytes:
    """``data`` with one more zero in the Rice unary parts (one position code too many),
    checksum recomputed: every section but the positions' still reads."""
    b = bytearray(data)
    b[-1] = 0x00  # the last byte of the unary parts: its padding ones become code zeros
    return _with_crc(b)


@pytest.mark.parametrize("mode", sorted(MODES))
def test_partial_descriptor_completes_to_the_decoded_one_in_every_mode(run_images, mode):
    data = extract(run_images[3], mode)
    whole, part = decode(data), decode_local(data)
    assert len(part) == len(whole) > 10 and not part.positions_decoded
    full = part.full()
    assert isinstance(full, FloorDescriptor) and part.positions_decoded
    for name in ("mode", "width_px", "height_px", "length", "position_step_px"):
        assert getattr(full, name) == getattr(whole, name)
    for name in ("xy_px", "angle_rad", "local_pos", "local_neg", "global_bits"):
        x, y = getattr(full, name), getattr(whole, name)
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), name
    # The trits are the stored section: element j of keypoint i is digit (i L + j) % 5 of byte (i L + j) // 5.
    i, j = len(whole) - 1, whole.length - 1
    flat = i * whole.length + j
    digit = (int(part.trits[flat // 5]) // 3 ** (flat % 5)) % 3 - 1
    assert digit == whole.ternary()[i, j]


def test_partial_descriptor_is_smaller_than_the_decoded_one_until_its_positions_are_read(run_images):
    part = decode_local(extract(run_images[0], 4))
    held = part.nbytes
    whole = decode(extract(run_images[0], 4))
    decoded_bytes = sum(getattr(whole, n).nbytes for n in ("xy_px", "angle_rad", "local_pos", "local_neg",
                                                           "global_bits"))
    assert held < 0.7 * decoded_bytes
    part.positions()
    assert part.nbytes > held  # the positions and orientations are kept once decoded


def test_decode_local_refuses_what_decode_refuses_and_defers_only_the_positions(run_images):
    data = extract(run_images[0], 4)
    for bad in (data[: len(data) // 2], b"XX" + data[2:], data[:30] + bytes([data[30] ^ 1]) + data[31:]):
        with pytest.raises(DescriptorError):
            decode(bad)
        with pytest.raises(DescriptorError):
            decode_local(bad)
    forged = _bad_positions(data)
    with pytest.raises(DescriptorError, match="position"):
        decode(forged)
    part = decode_local(forged)  # header, checksum, trits: fine
    with pytest.raises(DescriptorError, match="position"):
        part.positions()


def test_a_trit_byte_above_242_is_refused_at_once():
    from robotd.floor.descparams import HEADER

    data = extract(np.random.default_rng(0).integers(0, 256, (480, 640), dtype=np.uint8), 4)
    n, k = struct.unpack_from("<2sBBHHHHHBBI", data)[7:9]
    spec = MODES[4]
    trits_at = HEADER.size + spec.global_bits // 8 + -(-n * k // 8) + -(-n * 5 // 8)
    bad = bytearray(data)
    bad[trits_at + 3] = 243
    with pytest.raises(DescriptorError, match="descriptor code"):
        decode_local(_with_crc(bad))


def test_matcher_scores_a_partial_descriptor_exactly_as_the_decoded_one(run_images):
    """Every pair of the two runs, with and without the loop threshold: the same result field
    for field; the pairs dismissed at the bound leave the positions undecoded."""
    from robotd.app.demo import shipped_calibration
    from robotd.io.calibfile import read_calibration

    threshold = read_calibration(shipped_calibration()).loop.for_mode(4)
    blobs = [extract(im, 4) for im in run_images]
    reasons: set[str] = set()
    for qi in (2, 11, 25, 37):
        matcher = Matcher(decode(blobs[qi]))
        for b in blobs:
            for min_score in (0.0, threshold):
                want = matcher.score(decode(b), min_score)
                part = decode_local(b)
                got = matcher.score(part, min_score)
                assert (got.score, got.n_matches, got.n_inliers, got.reason) == \
                    (want.score, want.n_matches, want.n_inliers, want.reason)
                for name in ("inliers_a", "inliers_b", "xy_a", "xy_b"):
                    assert np.array_equal(getattr(got, name), getattr(want, name))
                assert (got.transform is None) == (want.transform is None)
                if want.transform is not None:
                    assert np.array_equal(got.transform, want.transform)
                if want.reason in ("BELOW_MIN_SCORE", "TOO_FEW_MATCHES"):
                    assert not part.positions_decoded
                reasons.add(str(want.reason))
    assert {"", "BELOW_MIN_SCORE"} <= reasons  # both kinds of pair were seen


def test_a_read_back_descriptor_with_a_bad_position_code_is_left_out_and_counted(run_images, tmp_path, caplog):
    """Bytes forged with a valid checksum whose positions do not decode: the map index's
    query leaves that keyframe out (logged, counted) and returns the others as before."""
    from robotd.io.store import MapStore

    blobs = [extract(im, 4) for im in run_images[:20]]
    good = FloorIndex(IndexParams(shortlist=20))
    for i, b in enumerate(blobs):
        good.add(i + 1, decode(b))
    query = decode(extract(run_images[25], 4))
    want = good.query(query, k=20)
    target = want[0].keyframe_id  # a pair that passes the bound: its positions are read
    path = tmp_path / "map.db"
    with MapStore.open(path, synchronous="NORMAL") as store:
        run = store.begin_run("", started_ns=0)
        ids = [store.add_keyframe(run, i, (0.1 * i, 0.0, 0.0), np.eye(3), None, b, 4) for i, b in enumerate(blobs)]
    assert ids == list(range(1, 21))
    with MapStore.open(path, create=False, read_only=True) as store:
        index = FloorIndex.from_store(store, 4, IndexParams(shortlist=20, resident=1))
        index.add(100, decode(blobs[0]))  # pushes every stored keyframe out of the resident set
    forged = {target: _bad_positions(blobs[target - 1])}

    def load(keyframe_id: int) -> PartialDescriptor:
        return decode_local(forged.get(keyframe_id, blobs[keyframe_id - 1]))

    index._loader = load
    with caplog.at_level(logging.WARNING):
        got = index.query(query, k=20, exclude_ids=[100])
    assert index.load_failures == 1 and any(str(target) in r.getMessage() for r in caplog.records)
    assert [(c.keyframe_id, c.score) for c in got] == [(c.keyframe_id, c.score) for c in want
                                                        if c.keyframe_id != target]


@pytest.mark.parametrize("resident", [6, 64])
def test_a_map_loaded_in_two_steps_answers_as_one_decoded_whole(run_images, tmp_path, resident):
    """``FloorIndex.from_store`` decodes the stored descriptors in two steps at load (the
    resident ones kept so, their positions decoded when first needed): on a map of the two
    rendered passes, every query of the second pass, with the loop threshold and without,
    returns what the index loaded by decoding every descriptor whole returns: the same
    candidates, scores, reasons, counts, matched points and transforms."""
    from robotd.app.demo import shipped_calibration
    from robotd.io.calibfile import read_calibration
    from robotd.io.store import MapStore

    mode = 4
    threshold = read_calibration(shipped_calibration()).loop.for_mode(mode)
    blobs = [extract(im, mode) for im in run_images]
    path = tmp_path / "map.db"
    with MapStore.open(path, synchronous="NORMAL") as store:
        run = store.begin_run("", started_ns=0)
        ids = [store.add_keyframe(run, i, (0.1 * i, 0.0, 0.0), np.eye(3), None, b, mode) for i, b in enumerate(blobs)]
    blob_of = dict(zip(ids, blobs))
    params = IndexParams(shortlist=12, resident=resident)
    # The load as it was: every stored descriptor decoded whole, the newest kept so.
    whole = FloorIndex(params, loader=lambda kf: decode(blob_of[kf]))
    for kf in ids:
        whole.add(kf, decode(blob_of[kf]))
    first = ids[len(ids) // 2 - 1]
    with MapStore.open(path, create=False, read_only=True) as store:
        index = FloorIndex.from_store(store, mode, params)
        assert index.load_report.loaded == len(ids) and index.loads == 0
        kept = [d for d, _ in index._recent.values()]
        assert len(kept) == min(resident, len(ids))
        assert all(isinstance(d, PartialDescriptor) and not d.positions_decoded for d in kept)
        assert index.descriptors_nbytes < whole.descriptors_nbytes
        checked = reasons = 0
        seen: set[str] = set()
        for kf in ids[len(ids) // 2:]:
            q = decode(blob_of[kf])
            for k, min_score in ((5, threshold), (12, 0.0)):
                want = whole.query(q, k=k, exclude_after_id=first, min_score=min_score)
                got = index.query(q, k=k, exclude_after_id=first, min_score=min_score)
                assert [(c.keyframe_id, c.global_score, c.score, c.local.reason, c.local.n_matches,
                         c.local.n_inliers) for c in got] == \
                    [(c.keyframe_id, c.global_score, c.score, c.local.reason, c.local.n_matches,
                      c.local.n_inliers) for c in want]
                for a, b in zip(got, want):
                    assert np.array_equal(a.local.xy_a, b.local.xy_a) and np.array_equal(a.local.xy_b, b.local.xy_b)
                    assert np.array_equal(a.local.inliers_b, b.local.inliers_b)
                    assert (a.local.transform is None) == (b.local.transform is None)
                    if a.local.transform is not None:
                        assert np.array_equal(a.local.transform, b.local.transform)
                    seen.add(str(a.local.reason))
                checked += len(got)
                reasons += sum(c.score >= threshold for c in got)
        assert index.load_failures == 0
    assert checked > 100 and reasons >= len(ids) // 2  # every second-pass keyframe finds loops
    assert {"", "BELOW_MIN_SCORE"} <= seen


def test_matchers_in_two_threads_score_as_one_thread(run_images):
    """The local score's scratch buffers are per thread: two threads scoring different
    pairs at once get exactly what one thread gets scoring them in turn."""
    import threading

    descs = [decode(extract(im, 4)) for im in run_images[:20]]
    queries = [decode(extract(im, 4)) for im in run_images[20:24]]
    jobs = [(q, d) for q in queries for d in descs]
    want = [Matcher(q).score(d) for q, d in jobs]
    got: list = [None] * len(jobs)

    def work(start: int) -> None:
        for _ in range(3):
            for i in range(start, len(jobs), 2):
                got[i] = Matcher(jobs[i][0]).score(jobs[i][1])

    threads = [threading.Thread(target=work, args=(s,)) for s in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sum(w.reason == "" for w in want) >= 4  # pairs checked geometrically among them
    for g, w in zip(got, want):
        assert (g.score, g.reason, g.n_matches, g.n_inliers) == (w.score, w.reason, w.n_matches, w.n_inliers)
        assert np.array_equal(g.inliers_a, w.inliers_a) and np.array_equal(g.xy_b, w.xy_b)
