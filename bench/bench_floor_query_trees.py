"""The floor query of two or more trees (the code before and after a change), alternated query by query.

Each tree runs in its own worker process (its own ``robotd`` first on ``sys.path``) that
holds the index as the daemon does (``FloorIndex.from_store`` on the laps map repeated to
each of ``--sizes``, 1,024 resident, RANSAC at the config's confidence) and answers the
parent's queries one at a time: the map's last ``--queries`` keyframes in the order driven,
the shipped calibration's loop threshold, the keyframes of the 20 s around the query
excluded, ``k`` candidates (as ``bench_floor_query_fewer.py`` queries its default). The
parent sends each query to every tree in turn (which goes first rotates by query), so the
trees share the machine's load; each worker times its query with thread CPU time.

Per tree: the median and p90 ms per query, the ratio of its median to the first tree's
(overall and by round), the median of its per-query ratios (each query's time over the
first tree's for the same query, measured back to back: less swayed by the load's swings
between queries), and whether its answers are the first tree's bit for bit (every
candidate's keyframe id, scores, match counts, reason, inlier indices and positions and
transform, compared as bytes). ``--profile N``: each worker also runs one more round under
cProfile and reports its ``N`` functions of most own time (not timed with the rounds).

Run: ``python bench/bench_floor_query_trees.py --tree before=/tmp/base --tree after=.``
(several minutes). Writes ``floor_query_trees.json`` (``--out``, ``--name``); ``--doc PAGE``
renders it (``--page JSON ...`` only renders, one section per run).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

DEFAULT_MAP = Path.home() / ".cache" / "robotd-bench" / "office-3laps-new-frames-map.sqlite"


def answer_digest(candidates: list[Any]) -> str:
    """A digest of a query's answer: every field of every candidate, floats and arrays as
    their bytes (equal digests: the same answer bit for bit)."""
    import numpy as np

    h = hashlib.sha256()
    for c in candidates:
        m = c.local
        h.update(repr((int(c.keyframe_id), float(c.global_score).hex(), float(m.score).hex(), int(m.n_matches),
                       int(m.n_inliers), str(m.reason))).encode())
        for arr in (m.inliers_a, m.inliers_b, m.xy_a, m.xy_b, m.transform):
            if arr is None:
                h.update(b"none")
            else:
                a = np.ascontiguousarray(arr)
                h.update(str((a.dtype.str, a.shape)).encode())
                h.update(a.tobytes())
    return h.hexdigest()


def worker(tree: Path, map_path: Path, source: Path, k: int, queries: int, exclude_recent_s: float) -> int:
    """Serve queries on stdin (one query number a line; ``profile N`` runs every query once
    under cProfile), answering one JSON line each on stdout."""
    sys.path.insert(0, str(tree.resolve()))
    import time

    import numpy as np

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
    with MapStore.open(source, create=False, read_only=True) as store:
        recs = [r for r in store.keyframes() if r.descriptor is not None]
    mode = int(recs[0].descriptor_mode)
    min_score = float(read_calibration(shipped_calibration()).loop.for_mode(mode))
    n0 = len(recs)
    stamps = np.array([r.stamp_ns for r in recs], np.int64)
    qrows = list(range(n0 - min(queries, n0), n0))
    decoded = {q: decode(recs[q].descriptor) for q in qrows}
    mstore = MapStore.open(map_path, create=False, read_only=True)
    mp = MatchParams(confidence=FloorDetectorConfig().ransac_confidence)
    index = FloorIndex.from_store(mstore, mode, IndexParams(shortlist=FloorDetectorParams().shortlist,
                                                             match_params=mp))
    kf_of = index.ids
    rows = np.arange(len(kf_of))
    excluded = {q: kf_of[rows[np.abs(stamps[rows % n0] - stamps[q]) < int(exclude_recent_s * 1e9)]] for q in qrows}

    def query(q: int) -> list[Any]:
        return index.query(decoded[q], k=k, min_score=min_score, exclude_ids=excluded[q])

    print(json.dumps({"ready": len(index), "min_score": min_score, "queries": len(qrows)}), flush=True)
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words[0] == "profile":
            import cProfile
            import pstats

            prof = cProfile.Profile()
            prof.enable()
            for q in qrows:
                query(q)
            prof.disable()
            st = pstats.Stats(prof)
            top = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[: int(words[1])]  # type: ignore[attr-defined]
            print(json.dumps({"profile": [
                {"function": f"{Path(f).name}:{ln}({fn})", "calls": nc, "own_ms_per_query": tt / len(qrows) * 1e3,
                 "cum_ms_per_query": ct / len(qrows) * 1e3} for (f, ln, fn), (_cc, nc, tt, ct, _callers) in top]}),
                flush=True)
            continue
        q = qrows[int(words[0])]
        t0 = time.thread_time()
        got = query(q)
        ms = (time.thread_time() - t0) * 1e3
        print(json.dumps({"ms": ms, "digest": answer_digest(got), "loops": sum(c.score >= min_score for c in got),
                          "reads": index.loads}), flush=True)
    mstore.close()
    return 0


def run(trees: list[tuple[str, Path]], map_path: Path, sizes: list[int], queries: int, rounds: int, k: int,
        profile: int, exclude_recent_s: float = 20.0) -> dict[str, Any]:
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd builds the map
    from bench.common import grow_repeated_map, git_commit
    from robotd.io.store import MapStore

    with MapStore.open(map_path, create=False, read_only=True) as store:
        recs = [r for r in store.keyframes() if r.descriptor is not None]
    mode = int(recs[0].descriptor_mode)
    blobs = [r.descriptor for r in recs]
    out: dict[str, Any] = {"map": str(map_path), "map_keyframes": len(recs), "mode": mode, "k": k,
                           "rounds": rounds, "trees": [{"label": lab, "path": str(p), "commit": git_commit(p)}
                                                       for lab, p in trees], "sizes": []}
    tmp = tempfile.TemporaryDirectory()
    big = Path(tmp.name) / "repeated.sqlite"
    kf_ids: list[int] = []
    env = dict(os.environ, PYTHONPATH="")
    for n in sorted(sizes):
        grow_repeated_map(big, blobs, mode, n, kf_ids)
        procs = {}
        for lab, path in trees:
            procs[lab] = subprocess.Popen(
                [sys.executable, str(Path(__file__).resolve()), "--worker", str(path), "--map", str(big),
                 "--source", str(map_path), "--k", str(k), "--queries", str(queries)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        ready = {lab: json.loads(p.stdout.readline()) for lab, p in procs.items()}  # type: ignore[union-attr]
        nq = ready[trees[0][0]]["queries"]
        out["min_score"] = ready[trees[0][0]]["min_score"]
        out["queries"] = nq
        ms: dict[str, list[float]] = {lab: [] for lab, _ in trees}
        same = {lab: 0 for lab, _ in trees}
        loops = {lab: 0 for lab, _ in trees}
        labels = [lab for lab, _ in trees]
        for r in range(rounds):
            for q in range(nq):
                order = labels[(r + q) % len(labels):] + labels[: (r + q) % len(labels)]
                got = {}
                for lab in order:
                    p = procs[lab]
                    p.stdin.write(f"{q}\n")  # type: ignore[union-attr]
                    p.stdin.flush()  # type: ignore[union-attr]
                    got[lab] = json.loads(p.stdout.readline())  # type: ignore[union-attr]
                    ms[lab].append(got[lab]["ms"])
                for lab in labels:
                    same[lab] += got[lab]["digest"] == got[labels[0]]["digest"]
                    loops[lab] += got[lab]["loops"] if r == 0 else 0
            print(f"{n} keyframes, round {r + 1}: " + ", ".join(
                f"{lab} {statistics.median(ms[lab][r * nq:]):.2f} ms" for lab in labels), flush=True)
        row: dict[str, Any] = {"keyframes": n, "trees": {}}
        base = statistics.median(ms[labels[0]])
        for lab in labels:
            med = statistics.median(ms[lab])
            row["trees"][lab] = {
                "query_ms": {"median": med, "p90": statistics.quantiles(ms[lab], n=10)[-1]},
                "ratio": med / base,
                "paired_ratio": statistics.median(x / y for x, y in zip(ms[lab], ms[labels[0]])),
                "ratio_by_round": [statistics.median(ms[lab][i * nq: (i + 1) * nq]) /
                                   statistics.median(ms[labels[0]][i * nq: (i + 1) * nq]) for i in range(rounds)],
                "answers_same_as_first": same[lab], "answers": rounds * nq, "loops_first_round": loops[lab]}
        if profile:
            for lab in labels:
                p = procs[lab]
                p.stdin.write(f"profile {profile}\n")  # type: ignore[union-attr]
                p.stdin.flush()  # type: ignore[union-attr]
                row["trees"][lab]["profile"] = json.loads(p.stdout.readline())["profile"]  # type: ignore[union-attr]
        for lab, p in procs.items():
            p.stdin.close()  # type: ignore[union-attr]
            p.wait(timeout=60)
        for lab in labels:
            v = row["trees"][lab]
            print(f"{n} keyframes, {lab}: {v['query_ms']['median']:.2f} ms median (ratio {v['ratio']:.3f}, paired "
                  f"{v['paired_ratio']:.3f}; by round "
                  f"{', '.join(f'{x:.2f}' for x in v['ratio_by_round'])}), answers as {labels[0]}'s "
                  f"{v['answers_same_as_first']}/{v['answers']}", flush=True)
        out["sizes"].append(row)
    tmp.cleanup()
    return out


def page(payloads: list[dict[str, Any]]) -> str:
    """The benchmark page of one or more runs, each its own section."""
    lines = ["# Floor query: the code before and after, alternated", ""]
    for i, payload in enumerate(payloads):
        if len(payloads) > 1:
            lines += [f"## Run {i + 1}", ""]
        lines += _run_section(payload, "###" if len(payloads) > 1 else "##")
    return "\n".join(lines)


def _run_section(payload: dict[str, Any], head: str) -> list[str]:
    r, m = payload["result"], payload["machine"]
    trees = ", ".join(f"{t['label']} (commit {str(t['commit'])[:10]})" for t in r["trees"])
    lines = [f"`bench/bench_floor_query_trees.py`: the {r['map_keyframes']} keyframes of `{r['map']}` (mode "
             f"{r['mode']}) repeated to each size and read from the map as the daemon holds them (1,024 resident), "
             f"the last {r['queries']} queried in the order driven (loop threshold {r['min_score']:.2f}, k "
             f"{r['k']}); trees {trees}, one worker process each, alternated query by query, {r['rounds']} rounds, "
             f"thread CPU. Ratio: the tree's median over the first tree's in the same run; paired ratio: the median "
             f"of each query's time over the first tree's for the same query. Same answers: queries "
             f"whose candidates are the first tree's bit for bit.", "",
             f"Machine: {m['platform']} ({m.get('cpu_model')}), load {payload.get('load_start')} -> "
             f"{payload.get('load_end')}.", ""]
    for row in r["sizes"]:
        lines += [f"{head} {row['keyframes']} keyframes", "",
                  "| tree | median ms | ratio (by round) | paired ratio | p90 ms | same answers | loops (first round) |",
                  "|---|---:|---|---:|---:|---:|---:|"]
        for lab, v in row["trees"].items():
            lines.append(f"| {lab} | {v['query_ms']['median']:.2f} | {v['ratio']:.3f} "
                         f"({', '.join(f'{x:.2f}' for x in v['ratio_by_round'])}) | {v.get('paired_ratio', float('nan')):.3f} "
                         f"| {v['query_ms']['p90']:.2f} | "
                         f"{v['answers_same_as_first']}/{v['answers']} | {v['loops_first_round']} |")
        lines.append("")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tree", action="append", default=None, metavar="LABEL=PATH",
                    help="a tree to measure (two or more; the first is the reference)")
    ap.add_argument("--map", type=Path, default=DEFAULT_MAP, help=f"a map of laps (default {DEFAULT_MAP})")
    ap.add_argument("--sizes", default="1000,10000", help="keyframes in the index, comma-separated")
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--k", type=int, default=5, help="candidates a query returns ([floor_detector] candidates)")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="also report each tree's N functions of most own time under cProfile")
    ap.add_argument("--out", type=Path, default=Path("bench-out"))
    ap.add_argument("--name", default="floor_query_trees")
    ap.add_argument("--doc", type=Path, default=None, help="also write the page here")
    ap.add_argument("--page", type=Path, nargs="+", default=None, metavar="JSON",
                    help="only render the page of these runs")
    ap.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--source", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker is not None:
        return worker(args.worker, args.map, args.source, args.k, args.queries, 20.0)
    if args.page is not None:
        text = page([json.loads(p.read_text(encoding="utf-8")) for p in args.page])
    else:
        trees = []
        for spec in args.tree or []:
            label, sep, path = spec.partition("=")
            if not sep or not label or not Path(path, "robotd").is_dir():
                ap.error(f"--tree {spec!r}: LABEL=PATH of a tree holding robotd/")
            trees.append((label, Path(path)))
        if len(trees) < 2:
            ap.error("two or more --tree LABEL=PATH")
        if not args.map.is_file():
            ap.error(f"--map {args.map}: no such map (bench_daemon.py --memory 1500 --memory-seeds 0,0,0 "
                     "--keep-map writes it)")
        sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
        from bench.common import machine_info, write_json

        load_start = [round(v, 2) for v in os.getloadavg()]
        res = run(trees, args.map, [int(s) for s in args.sizes.split(",") if s], args.queries, args.rounds,
                  args.k, args.profile)
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
