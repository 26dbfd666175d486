"""The forward stage's heading graph (:class:`robotd.app.stages.forward_loops.HeadingGraph`)
as the map grows: CPU time of one :meth:`relative` call and the memory it keeps.

A synthetic chain of N keyframes, one odometry link each and, from the second lap on
(every 500 keyframes), two floor loops per keyframe to the same place of earlier laps
(the demo's office route has about 3 links per keyframe). The stage asks the graph for
the relative heading of a ridge loop's two keyframes, here 1,500 keyframes apart ending at
the newest. Compared in the same run: the default window (links among the last 2,000
keyframes solved, older ones forgotten) and no window (every link kept and solved, as
before the window). Memory is what ``tracemalloc`` sees allocated by the graph after it is
fed, and the peak of one call.

Run: ``python bench/bench_heading_graph.py [--sizes 1000 3000 10000] [--out DIR]``
(about a minute); ``--full`` adds 30,000 keyframes. Writes ``heading_graph.json``.

``--baseline-rev REV`` measures the solve against the code of git revision ``REV`` instead
(its ``forward_loops.py`` read from git, its ``HeadingGraph`` fed the same links): on graphs
of ``--sizes`` keyframes (the demo's office route has about 800), ``--calls`` calls of
either code alternating in one process, each call's pair of keyframes drawn within the
window, thread CPU time; every answer must be the same to the bit. Each call of the current
code is a solve: its answer from the last solve (a forward keyframe's further views, the same
figures up to rounding) is cleared before the call, as the baseline has none. Writes
``heading_graph_vs_baseline.json`` with the median ratio current / baseline.
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import REPO_ROOT, machine_info, module_at_revision, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import REPO_ROOT, machine_info, module_at_revision, write_json

LAP = 500


def build(n: int, window: int, seed: int = 0) -> Any:
    """The heading graph of ``n`` keyframes (module notes)."""
    from robotd.app.stages.forward_loops import HeadingGraph
    from robotd.base.messages import Link

    rng = np.random.default_rng(seed)
    g = HeadingGraph(window=window)
    info, loop_info = np.diag([1e4, 1e4, 1e4]), np.diag([1e4, 1e4, 1e5])
    g.add_keyframe(0, 0.0, 0.0)
    for k in range(1, n):
        g.add_link(Link("odometry", k - 1, k, np.array([0.15, 0.0, 0.01 + rng.normal(0.0, 1e-3)]), info))
        if k >= LAP:
            for _ in range(2):
                old = k - LAP * (1 + int(rng.integers(0, k // LAP))) + int(rng.integers(-2, 3))
                if 0 <= old < k:
                    dyaw = (0.01 * (k - old) + np.pi) % (2 * np.pi) - np.pi + rng.normal(0.0, 3e-3)
                    g.add_link(Link("loop", old, k, np.array([0.0, 0.0, dyaw]), loop_info))
        g.add_keyframe(k, 0.01 * k, 1e-4 * k)
    return g


def measure(n: int, window: int, repeats: int = 5) -> dict[str, Any]:
    tracemalloc.start()
    g = build(n, window)
    kept, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    a, b = max(0, n - 1500), n - 1
    g.relative(a, b)  # warm-up (imports)
    runs = []
    for _ in range(repeats):
        t0 = time.thread_time()
        got = g.relative(a, b)
        runs.append((time.thread_time() - t0) * 1e3)
    tracemalloc.start()
    g.relative(a, b)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {"keyframes": n, "window": window, "links": len(g), "links_held": g._n,
            "kept_mb": round(kept / 1e6, 3), "call_peak_mb": round(peak / 1e6, 3),
            "call_cpu_ms_median": round(float(np.median(runs)), 2), "call_cpu_ms_runs": [round(r, 2) for r in runs],
            "answer": None if got is None else [round(got[0], 6), round(got[1], 6)]}


def _baseline_class(rev: str) -> Any:
    """``HeadingGraph`` as it is at git revision ``rev`` (its module read from git)."""
    return module_at_revision(rev, "robotd/app/stages/forward_loops.py", "baseline_forward_loops").HeadingGraph


def against_baseline(rev: str, sizes: list[int], calls: int, out: Path) -> int:
    """The solve of the current code against ``rev``'s (module notes)."""
    import subprocess

    from robotd.app.stages.forward_loops import HeadingGraph

    base_cls = _baseline_class(rev)
    rows = []
    for n in sizes:
        cur = build(n, HeadingGraph().window)
        base = base_cls(window=cur.window)
        base._f, base._t, base._d, base._v = cur._f.copy(), cur._t.copy(), cur._d.copy(), cur._v.copy()
        base._n, base._dropped, base._newest, base._odom = cur._n, cur._dropped, cur._newest, dict(cur._odom)
        rng = np.random.default_rng(n)
        lo = max(0, n - 1 - cur.window)
        pairs = [(int(a), n - 1 - int(k)) for a, k in zip(rng.integers(lo, n - 1, calls), rng.integers(0, 3, calls))]
        cur.relative(*pairs[0])
        base.relative(*pairs[0])  # warm-up (imports)
        t_cur, t_base, same = [], [], True
        for i, (a, b) in enumerate(pairs):
            order = (cur, base) if i % 2 == 0 else (base, cur)
            got = {}
            for g in order:
                if g is cur:
                    cur._last = None  # a solve each call, not the further-view answer (module notes)
                t0 = time.thread_time()
                got[id(g)] = g.relative(a, b)
                (t_cur if g is cur else t_base).append((time.thread_time() - t0) * 1e3)
            x, y = got[id(cur)], got[id(base)]
            same &= (x is None and y is None) or (x is not None and y is not None and
                                                  x[0].hex() == y[0].hex() and x[1].hex() == y[1].hex())
        ratios = [c / b for c, b in zip(t_cur, t_base) if b > 0]
        r = {"keyframes": n, "links": len(cur), "calls": calls, "same_answers": bool(same),
             "current_cpu_ms_median": round(float(np.median(t_cur)), 3),
             "baseline_cpu_ms_median": round(float(np.median(t_base)), 3),
             "ratio_median": round(float(np.median(ratios)), 3)}
        rows.append(r)
        print(f"{n:>6} keyframes, {r['links']} links: current {r['current_cpu_ms_median']:.3f} ms, baseline "
              f"{r['baseline_cpu_ms_median']:.3f} ms per call, ratio {r['ratio_median']:.3f}, same answers: {same}")
    commit = subprocess.run(["git", "rev-parse", rev], cwd=REPO_ROOT, capture_output=True, text=True).stdout.strip()
    path = write_json(out / "heading_graph_vs_baseline.json",
                      {"machine": machine_info(), "baseline_rev": rev, "baseline_commit": commit, "rows": rows})
    print(f"wrote {path}")
    return 0 if all(r["same_answers"] for r in rows) else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 3000, 10000])
    ap.add_argument("--full", action="store_true", help="also 30,000 keyframes")
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results")
    ap.add_argument("--baseline-rev", help="measure the solve against this git revision's (module notes)")
    ap.add_argument("--calls", type=int, default=200, help="with --baseline-rev: calls per size")
    args = ap.parse_args(argv)
    if args.baseline_rev:
        return against_baseline(args.baseline_rev, args.sizes, args.calls, args.out)
    from robotd.app.stages.forward_loops import HeadingGraph

    sizes = args.sizes + ([30000] if args.full else [])
    default = HeadingGraph().window
    rows = []
    print(f"{'keyframes':>9} {'links':>6} | {'window':>8} {'held':>6} {'kept MB':>8} {'call MB':>8} "
          f"{'call ms':>8} | answer (rad)")
    for n in sizes:
        for window in (default, 10**9):
            r = measure(n, window)
            rows.append(r)
            print(f"{n:>9} {r['links']:>6} | {'none' if window == 10**9 else window:>8} {r['links_held']:>6} "
                  f"{r['kept_mb']:>8.2f} {r['call_peak_mb']:>8.2f} {r['call_cpu_ms_median']:>8.2f} | {r['answer']}")
    ratio = {str(n): round(next(r["call_cpu_ms_median"] for r in rows if r["keyframes"] == n and r["window"] == default)
                           / max(next(r["call_cpu_ms_median"] for r in rows if r["keyframes"] == n
                                      and r["window"] == 10**9), 1e-9), 3) for n in sizes}
    print("call time, window / no window:", ratio)
    path = write_json(args.out / "heading_graph.json", {"machine": machine_info(), "rows": rows,
                                                          "call_time_ratio_window_to_none": ratio})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
