"""Where the daemon's costliest forward keyframes spend their CPU: ``robotd demo --forward``
run in this process with each forward keyframe of the forward stage
(:class:`robotd.app.stages.forward_loops.ForwardLoopStage`) under its own ``cProfile``
profiler on the thread's CPU clock (the pipeline thread's only: a profiler follows one
thread; its wall clock is mostly waits for the interpreter's lock beside the renderer).

The ``--top`` keyframes that cost the detector's call the most CPU as the stage times it
(``ForwardLoopStage.cpu_ms``: features, words, verification and the stage's level test,
scan, ridge fits and heading graph inside it; the profiler's own overhead included, so the
figures are larger than an unprofiled run's and the ranking may differ a little) have
their profiles summed; the script prints, for them, the stage's parts as the stage timed
them, the functions by their own time and by their time with what they call. It also splits the
detector's call over all forward keyframes (median and p99) into the stage's own parts in
it (match, scan, level, ridge with the heading graph's solve) and the rest, the detector's:
what the p99 would be with the stage's work free. ``--no-profile`` runs without the
profiler (the figures as the demo's own, the split and the costliest keyframes' parts only).

Run: ``python bench/bench_forward_keyframe_profile.py [--top 6] [--lines 40] [--stats FILE]
[--no-profile] -- --forward --route office --no-plot --seed 0 --out DIR --config C`` (the arguments after
``--`` are ``robotd demo``'s; about twice the demo's time). ``--stats`` keeps the summed
profile (``pstats`` format) for a later look; ``--json FILE [--page FILE.md]`` writes the
figures (the split, the costliest keyframes' parts, the summed profile's main pieces per
keyframe) and their page; ``--page-from JSON --page FILE.md`` the page of a kept JSON.
"""

from __future__ import annotations

import argparse
import cProfile
import heapq
import io
import json
import math
import os
import pstats
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import git_commit, machine_info, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from common import git_commit, machine_info, write_json, write_page  # type: ignore[no-redef]


class TopKeyframes:
    """The ``n`` costliest of a stream of ``(cost, index, item)``: kept in a heap, read back
    costliest first (on a tie the earlier index first)."""

    def __init__(self, n: int) -> None:
        self.n = int(n)
        self._heap: list[tuple[float, int, Any]] = []

    def offer(self, cost: float, index: int, item: Any) -> None:
        if self.n <= 0:
            return
        entry = (float(cost), -int(index), item)
        if len(self._heap) < self.n:
            heapq.heappush(self._heap, entry)
        elif entry[:2] > self._heap[0][:2]:
            heapq.heapreplace(self._heap, entry)

    def items(self) -> list[tuple[float, int, Any]]:
        return [(c, -i, item) for c, i, item in sorted(self._heap, key=lambda e: (-e[0], -e[1]))]


#: The stage's own parts inside the detector's call (its level test's hook): what is left of a
#: keyframe's CPU without them is the detector's (features, words, verification, filter).
STAGE_PARTS = ("match", "scan", "level", "ridge")


def install(top: TopKeyframes, profile: bool = True) -> list[Any]:
    """Profile every forward keyframe the stage runs (its ``_take``; without ``profile``
    only the stage is kept) and offer the ones the detector ran on to ``top`` as
    ``(cpu_ms, keyframe number, (parts, profile or None))``. Returns the list the stage
    is put in once it runs (for :func:`split`)."""
    from robotd.app.stages import forward_loops

    stage_cls = forward_loops.ForwardLoopStage
    take = stage_cls._take
    stages: list[Any] = []

    def profiled(self: Any, *args: Any, **kwargs: Any) -> None:
        if not stages:
            stages.append(self)
        n = len(self.cpu_ms)
        prof = cProfile.Profile(time.thread_time) if profile else None  # the thread's CPU (the wall clock waits)
        if prof is not None:
            prof.enable()
        try:
            take(self, *args, **kwargs)
        finally:
            if prof is not None:
                prof.disable()
        if len(self.cpu_ms) > n:
            parts = {k: round(v[-1], 2) for k, v in self.part_cpu_ms.items() if v}
            top.offer(self.cpu_ms[-1], n, (parts, prof))

    stage_cls._take = profiled  # type: ignore[method-assign]
    return stages


def split(cpu_ms: list[float], parts: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """Median and p99 (ms) over the forward keyframes of the detector's call as the stage
    times it (``cpu``), of the stage's own parts in it (``stage``: :data:`STAGE_PARTS`)
    and of what is left (``detector``: the call without them)."""
    cpu = np.asarray(cpu_ms, np.float64)
    own = np.zeros(len(cpu))
    for k in STAGE_PARTS:
        if len(parts.get(k, [])) == len(cpu):
            own += np.asarray(parts[k], np.float64)
    out = {}
    for name, a in (("cpu", cpu), ("stage", own), ("detector", cpu - own)):
        out[name] = {"median": round(float(np.median(a)), 2) if len(a) else math.nan,
                     "p99": round(float(np.percentile(a, 99)), 2) if len(a) else math.nan}
    return out


def summed(profiles: list[cProfile.Profile]) -> pstats.Stats | None:
    """The profiles' statistics summed (None without any)."""
    stats = None
    for prof in profiles:
        if stats is None:
            stats = pstats.Stats(prof, stream=io.StringIO())
        else:
            stats.add(prof)
    return stats


def report(stats: pstats.Stats, order: str, lines: int) -> str:
    out = io.StringIO()
    stats.stream = out  # type: ignore[attr-defined]
    stats.sort_stats(order).print_stats(lines)
    return out.getvalue()


#: The stage's and the detector's pieces the page lists for the kept keyframes, by file and
#: function (each name is one function in its file).
PIECES = (
    ("detector.py", "process", "the detector's call (the level test inside)"),
    ("features.py", "__call__", "ORB features"),
    ("vocabulary.py", "quantize", "the word search"),
    ("verify.py", "verify_pair", "the verification"),
    ("forward_loops.py", "_level", "the stage's level test (its hook)"),
    ("forward_loops.py", "_scan", "the planar refit's heading scan"),
    ("planefit.py", "fit_planar_scans", "the scan's fits"),
    ("forward_loops.py", "_settle", "the ridge (fits and the graph's heading)"),
    ("planefit.py", "fit_planar_fixed", "the ridge's fixed-heading fits"),
    ("forward_loops.py", "relative", "the heading graph's solve"),
    ("forward_loops.py", "_links", "its links gathered"),
    ("forward_loops.py", "tree_yaws", "its spanning tree's yaws"),
    ("forward_loops.py", "_step", "its normal matrix and factorisation"),
    ("linsolve.py", "splu", "SuperLU's factorisation"),
    ("planefit.py", "_refine", "the planar fits' Gauss-Newton refinements"),
    ("planefit.py", "_scores", "the scan's candidates scored"),
    ("forward_loops.py", "_store_image", "the map write (after the detector's call)"),
)


def pieces(stats: pstats.Stats, n_keyframes: int) -> list[dict[str, Any]]:
    """:data:`PIECES` in ``stats``: calls, own and cumulative ms per kept keyframe."""
    out = []
    table = stats.stats  # type: ignore[attr-defined]
    for file, func, what in PIECES:
        hits = [v for (f, _line, name), v in table.items() if name == func and f.endswith("/" + file)]
        calls = sum(v[1] for v in hits)
        own = sum(v[2] for v in hits) * 1e3 / max(n_keyframes, 1)
        cum = sum(v[3] for v in hits) * 1e3 / max(n_keyframes, 1)
        out.append({"function": f"{file}:{func}", "what": what, "calls": int(calls), "own_ms": round(own, 2),
                    "cum_ms": round(cum, 2)})
    return out


def page(result: dict[str, Any]) -> list[str]:
    """The Markdown page of one run's JSON."""
    sp = result["split"]
    lines = ["# The daemon's costliest forward keyframes", "",
             f"`bench/bench_forward_keyframe_profile.py` on `robotd demo {' '.join(result['demo_args'])}` "
             f"({'profiled on the thread CPU clock: the profiler inflates every figure' if result['profiled'] else 'no profiler'}; "
             f"load {result['load'][0]}-{result['load'][1]}, {result['machine'].get('cpu_model') or 'machine'}).", "",
             "The detector's call per forward keyframe (CPU ms) and its split into the stage's own parts in it "
             "(match, scan, level, ridge with the heading graph) and the rest (the detector's):", "",
             "| | median | p99 |", "|---|---:|---:|"]
    for name in ("cpu", "stage", "detector"):
        lines.append(f"| {name} | {sp[name]['median']:.2f} | {sp[name]['p99']:.2f} |")
    lines += ["", f"The {len(result['top'])} costliest keyframes (CPU ms of the call, the stage's parts):", "",
              "| keyframe | CPU ms | " + " | ".join(PARTS_SHOWN) + " |", "|---:|---:|" + "---:|" * len(PARTS_SHOWN)]
    for row in result["top"]:
        lines.append(f"| {row['keyframe']} | {row['cpu_ms']:.1f} | "
                     + " | ".join(f"{row['parts'].get(k, 0.0):.1f}" for k in PARTS_SHOWN) + " |")
    if result.get("pieces"):
        lines += ["", "Their profile summed, per keyframe (ms; own: in the function itself, cumulative: with what "
                  "it calls):", "", "| function | what | calls | own | cumulative |", "|---|---|---:|---:|---:|"]
        for r in result["pieces"]:
            lines.append(f"| `{r['function']}` | {r['what']} | {r['calls']} | {r['own_ms']:.2f} | {r['cum_ms']:.2f} |")
    return lines + [""]


#: The stage's parts the page shows per keyframe (ForwardLoopStage.part_cpu_ms).
PARTS_SHOWN = ("match", "scan", "level", "ridge", "graph", "store", "stage")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    own, demo = (argv[: argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--top", type=int, default=6, help="the costliest keyframes summed (default 6)")
    ap.add_argument("--lines", type=int, default=40, help="functions printed per order (default 40)")
    ap.add_argument("--stats", type=Path, help="write the summed profile here (pstats format)")
    ap.add_argument("--no-profile", action="store_true",
                    help="no profiler: the costliest keyframes' parts and the split of the p99 only")
    ap.add_argument("--json", type=Path, help="write the figures here (JSON)")
    ap.add_argument("--page", type=Path, help="write the Markdown page here (with --json, or of --page-from)")
    ap.add_argument("--page-from", type=Path, help="the page of a kept JSON only (no run)")
    args = ap.parse_args(own)
    if args.page_from is not None:
        if args.page is None:
            ap.error("--page-from needs --page")
        write_page(args.page, page(json.loads(args.page_from.read_text())))
        return 0
    top = TopKeyframes(args.top)
    stages = install(top, profile=not args.no_profile)
    from robotd.app.cli import main as robotd_main

    load0 = round(os.getloadavg()[0], 1)
    rc = robotd_main(["--log-level", "info", "demo", *demo])
    kept = top.items()
    print(f"\nthe {len(kept)} costliest forward keyframes (CPU ms{', profiled' if not args.no_profile else ''}, "
          "keyframe number, the stage's parts):")
    for cost, index, (parts, _) in kept:
        print(f"  {cost:7.1f}  #{index:<4d} {parts}")
    fig = split(stages[0].cpu_ms, stages[0].part_cpu_ms) if stages else {}
    for name, f in fig.items():
        print(f"{name:>9}: median {f['median']:.2f} ms, p99 {f['p99']:.2f} ms")
    stats = summed([prof for _, _, (_, prof) in kept if prof is not None])
    if stats is not None:
        if args.stats is not None:
            stats.dump_stats(str(args.stats))
        print(report(stats, "tottime", args.lines))
        print(report(stats, "cumulative", args.lines))
    if args.json is not None and fig:
        result = {"machine": machine_info(), "commit": git_commit(), "demo_args": demo,
                  "profiled": not args.no_profile, "load": [load0, round(os.getloadavg()[0], 1)],
                  "keyframes": len(stages[0].cpu_ms), "split": fig,
                  "top": [{"keyframe": i, "cpu_ms": round(c, 2), "parts": parts} for c, i, (parts, _) in kept],
                  "pieces": pieces(stats, len(kept)) if stats is not None else []}
        write_json(args.json, result)
        if args.page is not None:
            write_page(args.page, page(result))
    return rc


if __name__ == "__main__":
    sys.exit(main())
