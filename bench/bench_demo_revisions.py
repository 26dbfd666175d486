"""The demo's figures of two revisions of the code, seed by seed: whether the odometry, the
live fused pose and the map are better than they were (the odometry issue's "fused end
error and ATE better than today's on every seed", the daemon issue's "the demo's loop and
accuracy figures unchanged or better").

Each seed runs ``robotd demo --route office --seed N --no-plot`` with the code of
``--before REV`` (a ``git archive`` snapshot in ``--work``) and with this tree, one demo at
a time, the order alternated from seed to seed (a subprocess each; its CPU time is the
children's user + system time). Each revision runs with its own shipped calibration file
and defaults, as a user of that revision would. From each run's ``summary.json`` and TUM
files:

- keyframes, loop edges accepted, refused by the gate;
- wheel-only end error (the calibrated model when the revision has one, as the demo
  prints it);
- the live fused pose (``fused.tum``) against the truth: end error, APE anchored at the
  start, ATE after the rigid fit (evo ``--align``);
- the graph's combined odometry edges chained without loops and the loop-corrected
  keyframes: APE anchored (and ATE aligned where the revision reports it; the demo's own
  figures).

``bench/bench_demo_revisions.py --before REV [--seeds 0,1] [--work DIR] [--out JSON]
[--markdown PAGE]``; ``--full``: seeds 0-4. The default (two seeds, four demos) takes
about ten minutes on a quiet two-core machine. ``--reuse`` keeps a run whose
``summary.json`` exists in ``--work``; ``--page-from JSON`` writes the page only.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.bench_kidnap import run_demo, truth_at
    from bench.common import machine_info, print_table, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from bench_kidnap import run_demo, truth_at
    from common import machine_info, print_table, write_json, write_page

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robotd.evaluation.metrics import Alignment, align_origin, ape_translation_rmse  # noqa: E402
from robotd.io.trajectory import read_tum  # noqa: E402

DEFAULT_OUT = REPO / "docs" / "benchmarks" / "demo_revisions.json"


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def snapshot(rev: str, work: Path) -> tuple[Path, str]:
    """The tree of ``rev`` exported into ``work/tree-<commit>`` (kept for ``--reuse``); its
    path and full commit. Raises ``SystemExit`` with one line when ``rev`` is unknown."""
    done = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"], cwd=REPO,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"bench_demo_revisions: unknown revision {rev!r}")
    commit = done.stdout.strip()
    tree = work / f"tree-{commit[:12]}"
    if not (tree / "robotd").is_dir():
        tree.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile() as tar:
            subprocess.run(["git", "archive", "--format=tar", commit], cwd=REPO, stdout=tar, check=True)
            tar.seek(0)
            with tarfile.open(fileobj=tar) as t:
                t.extractall(tree, filter="data")
    return tree, commit


def fused_errors(out: Path) -> dict[str, float]:
    """The live fused pose of a demo's ``fused.tum`` against its ``groundtruth.tum``: the end
    error and APE anchored at the first true pose (as the demo prints them) and the ATE
    after the rigid fit."""
    stamps, est = read_tum(out / "fused.tum")
    truth = truth_at(out, stamps)
    anchored = align_origin(truth[0], est)
    return {"end_m": float(np.hypot(*(anchored[-1, :2] - truth[-1, :2]))),
            "ape_anchored_m": ape_translation_rmse(truth, est, Alignment.ORIGIN),
            "ate_aligned_m": ape_translation_rmse(truth, est, Alignment.ALIGNED), "poses": int(len(est))}


def graph_errors(column: dict[str, Any]) -> dict[str, float | None]:
    """A keyframe column of the demo's graph figures: APE anchored (older revisions name it
    ``ate_rmse_m``) and ATE aligned (None where the revision did not report it)."""
    return {"ape_anchored_m": column.get("ape_origin_rmse_m", column.get("ate_rmse_m")),
            "ate_aligned_m": column.get("ate_aligned_rmse_m")}


def figures(run: dict[str, Any], out: Path) -> dict[str, Any]:
    """One demo's figures (see the module notes)."""
    s = run["summary"]
    g = s.get("pose_graph") or {}
    odo, lc = g.get("odometry") or {}, g.get("loop_corrected") or {}
    return {"keyframes": s["keyframes"], "loops_accepted": g.get("loops_accepted"),
            "loops_refused": g.get("loops_failed_gate"),
            "wheel_end_m": s["wheel_only"]["end_position_error_m"],
            "fused": fused_errors(out),
            "combined_edges": graph_errors(odo), "loop_corrected": graph_errors(lc),
            "cpu_s": run["cpu_s"], "wall_s": run["wall_s"]}


def verdict(before: dict[str, Any], after: dict[str, Any]) -> dict[str, bool]:
    """Which of the judged figures this tree makes better (strictly lower) than ``before``."""
    b, a = before["fused"], after["fused"]
    return {"fused_end": a["end_m"] < b["end_m"], "fused_ape_anchored": a["ape_anchored_m"] < b["ape_anchored_m"],
            "fused_ate_aligned": a["ate_aligned_m"] < b["ate_aligned_m"],
            "loop_corrected_ape": (after["loop_corrected"]["ape_anchored_m"] or np.inf)
            <= (before["loop_corrected"]["ape_anchored_m"] or np.inf),
            "no_loop_refused": not after["loops_refused"]}


def mm(x: float | None) -> str:
    return "-" if x is None else f"{1e3 * x:.1f}"


def markdown(payload: dict[str, Any]) -> list[str]:
    p = payload["params"]
    rows = payload["seeds"]
    lines = [f"# The demo, this code against the code of {p['before'][:12]} (generated by "
             "bench/bench_demo_revisions.py --markdown)", "",
             f"Per seed of the virtual robot, `robotd demo --route office --seed N --no-plot` with the code of "
             f"`{p['before'][:12]}` (before) and of `{(payload['machine'].get('git_commit') or '?')[:12]}` (now), "
             "each with its own shipped calibration and defaults, one demo at a time, the order alternated. "
             "The live fused pose (`fused.tum`) against the truth; the graph's figures are the demo's own "
             f"(mm unless marked). Load average {payload.get('load_start')} at the start, "
             f"{payload.get('load_end')} at the end.", "",
             "| seed | keyframes before / now | loop edges (refused) before / now | wheel-only end (m) before / now "
             "| fused end | fused APE anchored | fused ATE aligned | combined edges APE anchored | loop-corrected APE anchored "
             "| fused better (end, ATE) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b, a, v = r["before"], r["now"], r["better"]
        lines.append(
            f"| {r['seed']} | {b['keyframes']} / {a['keyframes']} | {b['loops_accepted']} ({b['loops_refused']}) / "
            f"{a['loops_accepted']} ({a['loops_refused']}) | {b['wheel_end_m']:.3f} / {a['wheel_end_m']:.3f} | "
            f"{mm(b['fused']['end_m'])} / {mm(a['fused']['end_m'])} | "
            f"{mm(b['fused']['ape_anchored_m'])} / {mm(a['fused']['ape_anchored_m'])} | "
            f"{mm(b['fused']['ate_aligned_m'])} / {mm(a['fused']['ate_aligned_m'])} | "
            f"{mm(b['combined_edges']['ape_anchored_m'])} / {mm(a['combined_edges']['ape_anchored_m'])} | "
            f"{mm(b['loop_corrected']['ape_anchored_m'])} / {mm(a['loop_corrected']['ape_anchored_m'])} | "
            f"{'yes' if v['fused_end'] else 'no'}, {'yes' if v['fused_ate_aligned'] else 'no'} |")
    n = len(rows)
    both = sum(r["better"]["fused_end"] and r["better"]["fused_ate_aligned"] for r in rows)
    lines += ["", f"The fused end error and ATE better than before on {both} of {n} seeds; "
              f"no loop refused now on {sum(r['better']['no_loop_refused'] for r in rows)} of {n}. "
              f"CPU per demo {min(r[k]['cpu_s'] for r in rows for k in ('before', 'now')):.0f}-"
              f"{max(r[k]['cpu_s'] for r in rows for k in ('before', 'now')):.0f} s (user + system).", ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", help="the revision to compare against (a commit, tag or branch)")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--full", action="store_true", help="seeds 0-4")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench-demo-revisions"), help="snapshots and demo outputs")
    ap.add_argument("--reuse", action="store_true", help="keep a run whose summary.json is in --work")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--page-from", type=Path, default=None, help="measure nothing: write --markdown from this JSON")
    args = ap.parse_args(argv)
    if args.page_from is not None:
        if args.markdown is None:
            ap.error("--page-from needs --markdown")
        write_page(args.markdown, markdown(json.loads(args.page_from.read_text())))
        return 0
    if not args.before:
        ap.error("--before REV is needed")
    seeds = [0, 1, 2, 3, 4] if args.full else [int(s) for s in args.seeds.split(",")]
    work = args.work.resolve()
    tree, commit = snapshot(args.before, work)
    load_start = os.getloadavg()
    rows = []
    for seed in seeds:
        runs: dict[str, dict[str, Any]] = {}
        order = (("before", tree), ("now", REPO)) if seed % 2 == 0 else (("now", REPO), ("before", tree))
        for name, repo in order:
            out = work / f"seed{seed}-{name}"
            log(f"seed {seed} {name}: {out}")
            env_commit = {"ROBOTD_GIT_COMMIT": commit} if name == "before" else {}
            os.environ.update(env_commit)
            try:
                runs[name] = figures(run_demo(out, seed, None, None, None, args.reuse, repo=repo), out)
            finally:
                for k in env_commit:
                    os.environ.pop(k, None)
        row = {"seed": seed, **runs, "better": verdict(runs["before"], runs["now"])}
        rows.append(row)
        log(f"seed {seed}: fused end {mm(runs['before']['fused']['end_m'])} -> {mm(runs['now']['fused']['end_m'])} mm, "
            f"ATE {mm(runs['before']['fused']['ate_aligned_m'])} -> {mm(runs['now']['fused']['ate_aligned_m'])} mm")
    print_table(["seed", "fused end mm", "fused APE mm", "fused ATE mm", "loop-corr. APE mm", "loops (refused)"],
                [[r["seed"], f"{mm(r['before']['fused']['end_m'])} -> {mm(r['now']['fused']['end_m'])}",
                  f"{mm(r['before']['fused']['ape_anchored_m'])} -> {mm(r['now']['fused']['ape_anchored_m'])}",
                  f"{mm(r['before']['fused']['ate_aligned_m'])} -> {mm(r['now']['fused']['ate_aligned_m'])}",
                  f"{mm(r['before']['loop_corrected']['ape_anchored_m'])} -> {mm(r['now']['loop_corrected']['ape_anchored_m'])}",
                  f"{r['before']['loops_accepted']} ({r['before']['loops_refused']}) -> "
                  f"{r['now']['loops_accepted']} ({r['now']['loops_refused']})"] for r in rows])
    payload = {"machine": machine_info(), "params": {"before": commit, "seeds": seeds, "route": "office"},
               "load_start": [round(x, 2) for x in load_start], "load_end": [round(x, 2) for x in os.getloadavg()],
               "seeds": rows}
    path = write_json(args.out, payload)
    print(f"\nwrote {path}")
    if args.markdown is not None:
        write_page(args.markdown, markdown(payload))
    return 0


if __name__ == "__main__":
    sys.exit(main())
