"""The floor query on repeated laps against the code of another git revision, in one process.

``FloorIndex.query`` of this checkout and of ``--baseline-rev`` (its ``robotd/floor/match.py``
and ``robotd/floor/index.py`` read from git and imported beside this checkout's) on the same
in-RAM index: a map's keyframes (``bench_daemon.py --memory``'s laps, the floor descriptors as
stored) repeated to each of ``--sizes`` keyframes, its last ``--queries`` keyframes queried in
the order driven with the loop threshold of the shipped calibration, the detector's default
shortlist, ``k`` 5, and the
keyframes of the 20 s around the query excluded (as ``bench_daemon.py --residency`` queries).
The two codes alternate query by query (which goes first alternates by round), thread CPU
time; RANSAC at the config's default confidence (``--ransac-confidence``). Every query's
candidates must be the same in every field (ids, global and local scores, reasons, counts,
inliers, points, transforms): the digests are compared and printed.

Run: ``python bench/bench_floor_query_batch.py --baseline-rev REV [--map MAP] [--rounds 3]``
(a few minutes). Writes ``floor_query_batch.json`` (``--out``, ``--name``): per size the
median ms per query of each code, their ratio overall and by round, and the digests.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import machine_info, module_at_revision, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, module_at_revision, write_json

DEFAULT_MAP = Path.home() / ".cache" / "robotd-bench" / "office-3laps-new-frames-map.sqlite"


def _baseline(rev: str) -> tuple[Any, Any]:
    """``(index module, match module)`` at ``rev``; its index imports its own match."""
    old_match = module_at_revision(rev, "robotd/floor/match.py", "floor_match_baseline")
    saved = sys.modules["robotd.floor.match"]
    sys.modules["robotd.floor.match"] = old_match  # the baseline index's import resolves to it
    try:
        old_index = module_at_revision(rev, "robotd/floor/index.py", "floor_index_baseline")
    finally:
        sys.modules["robotd.floor.match"] = saved
    return old_index, old_match


def _update(h: Any, got: list[Any]) -> None:
    for c in got:
        r = c.local
        h.update(repr((c.keyframe_id, c.global_score, r.score, str(r.reason), r.n_matches, r.n_inliers)).encode())
        for a in (r.inliers_a, r.inliers_b, r.xy_a, r.xy_b):
            h.update(a.dtype.str.encode() + a.tobytes())
        h.update(b"-" if r.transform is None else r.transform.tobytes())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline-rev", required=True, help="git revision of the code to compare with")
    ap.add_argument("--map", type=Path, default=DEFAULT_MAP, help=f"a map of laps (default {DEFAULT_MAP})")
    ap.add_argument("--sizes", default="1000,10000", help="keyframes in the index, comma-separated")
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--ransac-confidence", type=float, default=None,
                    help="MatchParams.confidence of both (default: the config's)")
    ap.add_argument("--out", type=Path, default=Path("bench-out"))
    ap.add_argument("--name", default="floor_query_batch")
    args = ap.parse_args(argv)

    from robotd.app.demo import shipped_calibration
    from robotd.base.blas import one_blas_thread
    from robotd.base.config import FloorDetectorConfig
    from robotd.floor import index as new_index
    from robotd.floor import match as new_match
    from robotd.floor.descriptor import decode
    from robotd.floor.detector import FloorDetectorParams
    from robotd.io.calibfile import read_calibration
    from robotd.io.store import MapStore

    one_blas_thread()
    old_index, old_match = _baseline(args.baseline_rev)
    confidence = (FloorDetectorConfig().ransac_confidence if args.ransac_confidence is None
                  else args.ransac_confidence)
    with MapStore.open(args.map, create=False, read_only=True) as store:
        recs = [r for r in store.keyframes() if r.descriptor is not None]
    mode = int(recs[0].descriptor_mode)
    min_score = read_calibration(shipped_calibration()).loop.for_mode(mode)
    n0 = len(recs)
    stamps = np.array([r.stamp_ns for r in recs], np.int64)
    decoded = [decode(r.descriptor) for r in recs]
    qrows = list(range(n0 - args.queries, n0))
    shortlist = FloorDetectorParams().shortlist
    rows: list[dict[str, Any]] = []
    print(f"map {args.map} ({n0} keyframes, mode {mode}), threshold {min_score:.2f}, confidence {confidence}, "
          f"baseline {args.baseline_rev}", flush=True)
    for n in (int(s) for s in args.sizes.split(",") if s):
        codes = {"baseline": (old_index, old_match), "current": (new_index, new_match)}
        idx = {}
        for name, (im, mm) in codes.items():
            params = im.IndexParams(shortlist=shortlist, match_params=mm.MatchParams(confidence=confidence))
            index = im.FloorIndex(params)
            for i in range(n):
                index.add(i, decoded[i % n0])
            idx[name] = index
        ids = np.arange(n)
        excluded = [ids[np.abs(stamps[ids % n0] - stamps[q]) < int(20e9)] for q in qrows]
        ms: dict[str, list[list[float]]] = {k: [] for k in codes}
        digest = {k: hashlib.sha256() for k in codes}
        for r in range(args.rounds):
            order = list(codes) if r % 2 == 0 else list(reversed(codes))
            for name in codes:
                ms[name].append([])
            for q, ex in zip(qrows, excluded):
                for name in order:
                    t0 = time.thread_time()
                    got = idx[name].query(decoded[q], k=5, min_score=min_score, exclude_ids=ex)
                    ms[name][-1].append((time.thread_time() - t0) * 1e3)
                    if r == 0:
                        _update(digest[name], got)
        med = {k: float(np.median(np.concatenate(v))) for k, v in ms.items()}
        by_round = [float(np.median(c) / np.median(b)) for b, c in zip(ms["baseline"], ms["current"])]
        same = digest["baseline"].hexdigest() == digest["current"].hexdigest()
        row = {"keyframes": n, "median_ms": med, "ratio": med["current"] / med["baseline"], "ratio_by_round": by_round,
               "identical": same, "digest": {k: v.hexdigest() for k, v in digest.items()},
               "local_matches": {k: v.local_matches for k, v in idx.items()}}
        rows.append(row)
        print(f"{n} keyframes: median ms per query {med['baseline']:.2f} (baseline) -> {med['current']:.2f} "
              f"(ratio {row['ratio']:.3f}; by round {', '.join(f'{x:.2f}' for x in by_round)}); "
              f"every query's candidates identical: {same} ({row['digest']['current'][:8]})", flush=True)
    payload = {"machine": machine_info(), "map": str(args.map), "baseline_rev": args.baseline_rev,
               "confidence": confidence, "min_score": min_score, "shortlist": shortlist, "queries": len(qrows),
               "rounds": args.rounds, "sizes": rows}
    path = write_json(args.out / f"{args.name}.json", payload)
    print(f"wrote {path}")
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
