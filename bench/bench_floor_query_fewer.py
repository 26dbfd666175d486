"""Fewer pairs per floor query on repeated laps: each lever against the default, in one process.

The index as the daemon holds it (``FloorIndex.from_store`` on a map of the laps' keyframes
repeated to each of ``--sizes``, 1,024 resident, RANSAC at the config's confidence), its
last ``--queries`` keyframes queried in the order driven with the shipped calibration's
loop threshold, the keyframes of the 20 s around the query excluded (as
``bench_daemon.py --residency`` queries). The variants, one index each, alternate query by
query (which goes first rotates by round), thread CPU time:

* ``default``: ``k`` 5, the shortlist in order (the daemon's default);
* ``k N``: the query stops at ``N`` loops (``[floor_detector] candidates``);

One loop per place (a shortlisted keyframe within ``S`` ids of one that gave the query a loop
left unscored) was a third lever here; measured at 0.89x / 1.00x of the default's query at
1,000 / 10,000 keyframes, it was removed from the index (docs/performance.md, "Tried and not
taken"), and the pages of those runs keep its rows.

Per variant: median and p90 ms per query and their ratio to ``default``, pairs scored and
loops per query, the loops' distinct places (older ends ``--place-ids`` ids apart) and
passes (copies of the map) per query, and how many queries found none.

Run: ``python bench/bench_floor_query_fewer.py [--map MAP] [--variants "k 3,k 2"]``
(several minutes). Writes ``floor_query_fewer.json`` (``--out``, ``--name``); ``--doc PAGE``
renders it (``--page JSON ...`` only renders, one section per run).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import grow_repeated_map, machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import grow_repeated_map, machine_info, write_json

DEFAULT_MAP = Path.home() / ".cache" / "robotd-bench" / "office-3laps-new-frames-map.sqlite"


def parse_variant(text: str) -> int:
    """``"k 3"``-style names (``default``: ``k`` 5) -> ``k``."""
    k = 5
    words = [] if text == "default" else text.split()
    if len(words) % 2:
        raise ValueError(f"variant {text!r}: pairs of lever and value")
    for key, value in zip(words[::2], words[1::2]):
        if key == "k":
            k = int(value)
        else:
            raise ValueError(f"unknown lever {key!r} in {text!r}")
    return k


def places(ids: list[int], spacing: int) -> int:
    """How many places ``ids`` fall in: runs of sorted ids less than ``spacing`` apart."""
    if not ids:
        return 0
    s = sorted(ids)
    return 1 + sum(b - a >= spacing for a, b in zip(s, s[1:]))


def run(map_path: Path, sizes: list[int], variants: list[str], queries: int, rounds: int,
        place_ids: int, exclude_recent_s: float = 20.0) -> dict[str, Any]:
    from robotd.app.demo import shipped_calibration
    from robotd.base.blas import one_blas_thread
    from robotd.base.config import FloorDetectorConfig
    from robotd.floor.descriptor import decode
    from robotd.floor.detector import FloorDetectorParams
    from robotd.floor.index import FloorIndex, IndexParams
    from robotd.floor.match import MatchParams
    from robotd.io.calibfile import read_calibration
    from robotd.io.store import MapStore

    one_blas_thread()
    confidence = FloorDetectorConfig().ransac_confidence
    shortlist = FloorDetectorParams().shortlist
    mp = MatchParams(confidence=confidence)
    names = ["default", *variants]
    levers = {name: parse_variant(name) for name in names}
    with MapStore.open(map_path, create=False, read_only=True) as store:
        recs = [r for r in store.keyframes() if r.descriptor is not None]
    mode = int(recs[0].descriptor_mode)
    min_score = float(read_calibration(shipped_calibration()).loop.for_mode(mode))
    n0 = len(recs)
    stamps = np.array([r.stamp_ns for r in recs], np.int64)
    decoded = [decode(r.descriptor) for r in recs]
    blobs = [r.descriptor for r in recs]
    qrows = list(range(n0 - min(queries, n0), n0))
    out: dict[str, Any] = {"map": str(map_path), "map_keyframes": n0, "mode": mode, "min_score": min_score,
                           "confidence": confidence, "shortlist": shortlist, "queries": len(qrows),
                           "rounds": rounds, "place_ids": place_ids, "sizes": []}
    print(f"map {map_path} ({n0} keyframes, mode {mode}), threshold {min_score:.2f}, confidence {confidence}, "
          f"shortlist {shortlist}", flush=True)
    tmp = tempfile.TemporaryDirectory()
    big = Path(tmp.name) / "repeated.sqlite"
    kf_ids: list[int] = []
    for n in sorted(sizes):
        kf_of = np.asarray(grow_repeated_map(big, blobs, mode, n, kf_ids), np.int64)  # as the daemon loads it
        mstore = MapStore.open(big, create=False, read_only=True)
        idx = {name: FloorIndex.from_store(mstore, mode, IndexParams(shortlist=shortlist, match_params=mp))
               for name in names}
        ids = np.arange(n)
        excluded = [kf_of[ids[np.abs(stamps[ids % n0] - stamps[q]) < int(exclude_recent_s * 1e9)]] for q in qrows]
        ms: dict[str, list[float]] = {k: [] for k in names}
        stats: dict[str, dict[str, list[int]]] = {k: {"pairs": [], "loops": [], "places": []} for k in names}
        for r in range(rounds):
            order = names[r % len(names):] + names[: r % len(names)]
            for q, ex in zip(qrows, excluded):
                for name in order:
                    index = idx[name]
                    m0 = index.local_matches
                    t0 = time.thread_time()
                    got = index.query(decoded[q], k=levers[name], min_score=min_score, exclude_ids=ex)
                    ms[name].append((time.thread_time() - t0) * 1e3)
                    if r == 0:
                        rows = [int(np.searchsorted(kf_of, c.keyframe_id)) for c in got if c.score >= min_score]
                        st = stats[name]
                        st["pairs"].append(index.local_matches - m0)
                        st["loops"].append(len(rows))
                        st["places"].append(places(rows, place_ids))
        row: dict[str, Any] = {"keyframes": n, "variants": {}}
        base = statistics.median(ms["default"])
        for name in names:
            med = statistics.median(ms[name])
            st = stats[name]
            row["variants"][name] = {
                "k": levers[name],
                "query_ms": {"median": med, "p90": float(np.quantile(ms[name], 0.9))},
                "ratio": med / base,
                "ratio_by_round": [statistics.median(ms[name][i * len(qrows): (i + 1) * len(qrows)]) /
                                   statistics.median(ms["default"][i * len(qrows): (i + 1) * len(qrows)])
                                   for i in range(rounds)],
                "pairs_per_query": float(np.mean(st["pairs"])), "loops_per_query": float(np.mean(st["loops"])),
                "loops": int(np.sum(st["loops"])), "places_per_query": float(np.mean(st["places"])),
                "queries_without_loop": int(sum(v == 0 for v in st["loops"])),
                "reads_per_query": idx[name].loads / (rounds * len(qrows))}
            v = row["variants"][name]
            print(f"{n} keyframes, {name}: {med:.2f} ms median (ratio {v['ratio']:.3f}; by round "
                  f"{', '.join(f'{x:.2f}' for x in v['ratio_by_round'])}), {v['pairs_per_query']:.2f} pairs, "
                  f"{v['loops_per_query']:.2f} loops ({v['places_per_query']:.2f} places) per query, "
                  f"{v['queries_without_loop']} queries without a loop", flush=True)
        out["sizes"].append(row)
        del idx
        mstore.close()
    tmp.cleanup()
    return out


def page(payloads: list[dict[str, Any]]) -> str:
    """The benchmark page of one or more runs, each its own section."""
    lines = ["# Floor query: fewer pairs on repeated laps", ""]
    for i, payload in enumerate(payloads):
        if len(payloads) > 1:
            lines += [f"## Run {i + 1}", ""]
        lines += _run_section(payload, "###" if len(payloads) > 1 else "##")
    return "\n".join(lines)


def _run_section(payload: dict[str, Any], head: str) -> list[str]:
    r, m = payload["result"], payload["machine"]
    lines = [f"`bench/bench_floor_query_fewer.py`: the {r['map_keyframes']} keyframes of `{r['map']}` (mode "
             f"{r['mode']}, laps of new frames) repeated to each size and read from the map as the daemon holds "
             f"them (1,024 resident), the last {r['queries']} queried in the order driven (loop threshold "
             f"{r['min_score']:.2f}, shortlist {r['shortlist']}, RANSAC confidence {r['confidence']}); the variants "
             f"alternate query by query, {r['rounds']} rounds, thread CPU. Ratio: the variant's median over the "
             f"default's in the same run. Places: the loops' older ends at least {r['place_ids']} ids apart.",
             "", f"Machine: {m['platform']} ({m.get('cpu_model')}), commit {str(m.get('git_commit'))[:10]}, "
             f"load {payload.get('load_start')} -> {payload.get('load_end')}.", ""]
    for row in r["sizes"]:
        lines += [f"{head} {row['keyframes']} keyframes", "",
                  "| variant | median ms | ratio (by round) | p90 ms | pairs / query | loops / query | places / query "
                  "| queries without a loop |",
                  "|---|---:|---|---:|---:|---:|---:|---:|"]
        for name, v in row["variants"].items():
            lines.append(f"| {name} | {v['query_ms']['median']:.2f} | {v['ratio']:.3f} "
                         f"({', '.join(f'{x:.2f}' for x in v['ratio_by_round'])}) | {v['query_ms']['p90']:.2f} | "
                         f"{v['pairs_per_query']:.2f} | {v['loops_per_query']:.2f} | {v['places_per_query']:.2f} | "
                         f"{v['queries_without_loop']} |")
        lines.append("")
    return lines


def main(argv: list[str] | None = None) -> int:
    import os

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", type=Path, default=DEFAULT_MAP, help=f"a map of laps (default {DEFAULT_MAP})")
    ap.add_argument("--sizes", default="1000,10000", help="keyframes in the index, comma-separated")
    ap.add_argument("--variants", default="k 3,k 2,k 1",
                    help="comma-separated; each 'k N'")
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--place-ids", type=int, default=10, help="ids apart that make two loops' older ends two places")
    ap.add_argument("--out", type=Path, default=Path("bench-out"))
    ap.add_argument("--name", default="floor_query_fewer")
    ap.add_argument("--doc", type=Path, default=None, help="also write the page here")
    ap.add_argument("--page", type=Path, nargs="+", default=None, metavar="JSON",
                    help="only render the page of these runs")
    args = ap.parse_args(argv)
    if args.page is not None:
        import json
        text = page([json.loads(p.read_text(encoding="utf-8")) for p in args.page])
    else:
        load_start = [round(v, 2) for v in os.getloadavg()]
        variants = [v.strip() for v in args.variants.split(",") if v.strip()]
        res = run(args.map, [int(s) for s in args.sizes.split(",") if s], variants, args.queries, args.rounds,
                  args.place_ids)
        payload = {"machine": machine_info(), "load_start": load_start,
                   "load_end": [round(v, 2) for v in os.getloadavg()], "result": res}
        print(f"wrote {write_json(args.out / f'{args.name}.json', payload)}")
        text = page([payload])
    if args.doc is not None:
        args.doc.write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
