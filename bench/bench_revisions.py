"""Two revisions of the code side by side, as a user runs each: whether the product is better
than it was (the odometry issue's "fused end error and ATE better than today's on every
seed"; the daemon issue's "a third of today's CPU per metre driven" and "the demo's loop
and accuracy figures unchanged or better"). The code of ``--before REV`` is a ``git
archive`` snapshot in ``--work``; each revision runs with its own defaults and shipped
calibration file; one run at a time, the order alternated (a subprocess each; its CPU time
is the children's user + system time).

``demo`` (the default): ``robotd demo --route office --seed N --no-plot`` per seed. From each
run's ``summary.json`` and TUM files:

- keyframes, loop edges accepted, refused by the gate;
- wheel-only end error (the calibrated model when the revision has one, as the demo
  prints it);
- the live fused pose (``fused.tum``) against the truth: end error, APE anchored at the
  start, ATE after the rigid fit (evo ``--align``);
- the keyframes' own poses (the wheel + gyro filter's, as the demo's "wheel+gyro" column)
  and the loop-corrected keyframes: APE anchored (and ATE aligned where the revision reports it; the demo's own
  figures).

``replay``: ``robotd replay`` of the recorded 60 s office drive (the one ``./dev bench
daemon`` keeps), ``--pairs`` times each, with the default config (as the daemon issue
measured it) and with a config that names the revision's shipped demo calibration (its
loop thresholds: loops declared): CPU seconds per robot second and keyframes, and the
ratio of this tree's to the code before's, pair by pair.

``describe``: the floor descriptor's ``extract`` (mode 4, the daemon's) of ``--frames`` floor
frames spread over that drive, each revision in a process of its own, ``--pairs`` times
alternated: the wall-clock median per frame and the ratio pair by pair (the daemon
issue's describe target against the describe it was filed with).

``bench/bench_revisions.py --before REV [demo|replay|describe] [--seeds 0,1] [--pairs 3] [--work DIR]
[--out JSON] [--markdown PAGE]``; ``--full``: seeds 0-4 (demo). The defaults take about ten
minutes on a quiet two-core machine. ``--reuse`` keeps a demo whose ``summary.json`` exists
in ``--work``; ``--page-from JSON`` writes the page only.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tarfile
import tempfile
import time
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

DEFAULT_OUT = {part: REPO / "docs" / "benchmarks" / f"{part}_revisions.json" for part in ("demo", "replay", "describe")}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def snapshot(rev: str, work: Path) -> tuple[Path, str]:
    """The tree of ``rev`` exported into ``work/tree-<commit>`` (kept for ``--reuse``); its
    path and full commit. Raises ``SystemExit`` with one line when ``rev`` is unknown."""
    done = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"], cwd=REPO,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"bench_revisions: unknown revision {rev!r}")
    commit = done.stdout.strip()
    tree = work / f"tree-{commit[:12]}"
    if not tree.is_dir():  # extracted beside it and renamed: an interrupted export leaves no half tree
        work.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=work) as part, tempfile.TemporaryFile() as tar:
            subprocess.run(["git", "archive", "--format=tar", commit], cwd=REPO, stdout=tar, check=True)
            tar.seek(0)
            with tarfile.open(fileobj=tar) as t:
                t.extractall(part, filter="data")
            os.rename(part, tree)
            os.mkdir(part)  # for the context's own clean-up
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
            "wheel_gyro": graph_errors(odo), "loop_corrected": graph_errors(lc),
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
             "bench/bench_revisions.py demo --markdown)", "",
             f"Per seed of the virtual robot, `robotd demo --route office --seed N --no-plot` with the code of "
             f"`{p['before'][:12]}` (before) and of `{(payload['machine'].get('git_commit') or '?')[:12]}` (now), "
             "each with its own shipped calibration and defaults, one demo at a time, the order alternated. "
             "The live fused pose (`fused.tum`) against the truth; the graph's figures are the demo's own "
             f"(mm unless marked). Load average {payload.get('load_start')} at the start, "
             f"{payload.get('load_end')} at the end.", "",
             "| seed | keyframes before / now | loop edges (refused) before / now | wheel-only end (m) before / now "
             "| fused end | fused APE anchored | fused ATE aligned | wheel + gyro at the keyframes, APE anchored | loop-corrected APE anchored "
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
            f"{mm(b['wheel_gyro']['ape_anchored_m'])} / {mm(a['wheel_gyro']['ape_anchored_m'])} | "
            f"{mm(b['loop_corrected']['ape_anchored_m'])} / {mm(a['loop_corrected']['ape_anchored_m'])} | "
            f"{'yes' if v['fused_end'] else 'no'}, {'yes' if v['fused_ate_aligned'] else 'no'} |")
    n = len(rows)
    both = sum(r["better"]["fused_end"] and r["better"]["fused_ate_aligned"] for r in rows)
    lines += ["", f"The fused end error and ATE better than before on {both} of {n} seeds; "
              f"no loop refused now on {sum(r['better']['no_loop_refused'] for r in rows)} of {n}. "
              f"CPU per demo {min(r[k]['cpu_s'] for r in rows for k in ('before', 'now')):.0f}-"
              f"{max(r[k]['cpu_s'] for r in rows for k in ('before', 'now')):.0f} s (user + system).", ""]
    return lines


def alternated(i: int, tree: Path) -> tuple[tuple[str, Path], tuple[str, Path]]:
    """The two revisions in the order of run ``i``: the code before first on even runs."""
    return (("before", tree), ("now", REPO)) if i % 2 == 0 else (("now", REPO), ("before", tree))


def recorded_drive() -> Path:
    """The recorded 60 s office drive ``./dev bench daemon`` keeps (recorded if missing)."""
    try:
        from bench.bench_floor_descriptor import office_recording
    except ImportError:
        from bench_floor_descriptor import office_recording
    return office_recording(argparse.Namespace(recording=None))


def demo_part(tree: Path, work: Path, seeds: list[int], reuse: bool) -> list[dict[str, Any]]:
    """The demo rows (see the module notes), one seed at a time."""
    rows = []
    for seed in seeds:
        runs: dict[str, dict[str, Any]] = {}
        for name, repo in alternated(seed, tree):
            out = work / f"seed{seed}-{name}"
            log(f"seed {seed} {name}: {out}")
            runs[name] = figures(run_demo(out, seed, None, None, None, reuse, repo=repo), out)
        rows.append({"seed": seed, **runs, "better": verdict(runs["before"], runs["now"])})
        log(f"seed {seed}: fused end {mm(runs['before']['fused']['end_m'])} -> {mm(runs['now']['fused']['end_m'])} mm, "
            f"ATE {mm(runs['before']['fused']['ate_aligned_m'])} -> {mm(runs['now']['fused']['ate_aligned_m'])} mm")
    print_table(["seed", "fused end mm", "fused APE mm", "fused ATE mm", "loop-corr. APE mm", "loops (refused)"],
                [[r["seed"], f"{mm(r['before']['fused']['end_m'])} -> {mm(r['now']['fused']['end_m'])}",
                  f"{mm(r['before']['fused']['ape_anchored_m'])} -> {mm(r['now']['fused']['ape_anchored_m'])}",
                  f"{mm(r['before']['fused']['ate_aligned_m'])} -> {mm(r['now']['fused']['ate_aligned_m'])}",
                  f"{mm(r['before']['loop_corrected']['ape_anchored_m'])} -> "
                  f"{mm(r['now']['loop_corrected']['ape_anchored_m'])}",
                  f"{r['before']['loops_accepted']} ({r['before']['loops_refused']}) -> "
                  f"{r['now']['loops_accepted']} ({r['now']['loops_refused']})"] for r in rows])
    return rows


def replay_once(tree: Path, recording: Path, work: Path, config: Path | None) -> dict[str, Any]:
    """``robotd replay RECORDING`` with the code of ``tree`` into a fresh map in ``work``; its
    CPU seconds (user + system of the child) and keyframes (from its last line)."""
    map_path = work / "replay-map.sqlite"
    for f in work.glob("replay-map.sqlite*"):
        f.unlink()
    cmd = [sys.executable, "-m", "robotd.app.cli", "replay", str(recording), "--map", str(map_path)]
    if config is not None:
        cmd += ["--config", str(config)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)})
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    last = (done.stdout.strip().splitlines() or [""])[-1]
    m = re.search(r"(\d+) keyframes", last)
    if done.returncode != 0 or m is None:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {done.returncode}): "
                           f"{(done.stderr.strip().splitlines() or [''])[-1]}")
    return {"cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            "wall_s": wall, "keyframes": int(m.group(1))}


def loop_config(tree: Path, work: Path, name: str) -> Path:
    """A config that names ``tree``'s shipped demo calibration (its loop thresholds)."""
    path = work / f"loops-{name}.toml"
    cal = tree / "robotd" / "app" / "data" / "demo_calibration.yml"
    path.write_text(f'[calibration]\npath = "{cal}"\n')
    return path


def replay_part(tree: Path, work: Path, pairs: int) -> list[dict[str, Any]]:
    """The replay rows (see the module notes): per config, ``pairs`` alternated pairs."""
    recording = recorded_drive()
    robot_s = 60.0  # the length of the drive recorded_drive gives
    rows = []
    for cname in ("defaults", "the shipped calibration's loop thresholds"):
        runs: dict[str, list[dict[str, Any]]] = {"before": [], "now": []}
        for i in range(pairs):
            for name, repo in alternated(i, tree):
                config = None if cname == "defaults" else loop_config(repo, work, name)
                r = replay_once(repo, recording, work, config)
                runs[name].append(r)
                log(f"replay, {cname}, pair {i + 1}, {name}: {r['cpu_s']:.2f} CPU-s, {r['keyframes']} keyframes")
        ratios = [a["cpu_s"] / b["cpu_s"] for a, b in zip(runs["now"], runs["before"])]
        rows.append({"config": cname, "robot_s": robot_s, "recording": str(recording), **runs,
                     "ratios": ratios,
                     "per_robot_s": {k: float(np.mean([r["cpu_s"] for r in v])) / robot_s for k, v in runs.items()}})
    return rows


DESCRIBE_CHILD = """
import json, sys, time
import numpy as np
from robotd.floor.descriptor import extract
frames, mode = np.load(sys.argv[1]), int(sys.argv[2])
for f in frames[:5]:
    extract(f, mode)
ts = []
for f in frames:
    t = time.perf_counter()
    extract(f, mode)
    ts.append(time.perf_counter() - t)
print(json.dumps({"median_ms": 1e3 * float(np.median(ts)), "p90_ms": 1e3 * float(np.percentile(ts, 90)),
                  "frames": len(ts)}))
"""
"""The describe part's child: ``extract`` of every frame in the ``.npy`` file, timed, as JSON."""


def describe_part(tree: Path, work: Path, pairs: int, frames: int, mode: int = 4) -> dict[str, Any]:
    """The describe rows (see the module notes)."""
    try:
        from bench.bench_describe_compiled import office_frames
    except ImportError:
        from bench_describe_compiled import office_frames
    recording = recorded_drive()
    path = work / f"floor-frames-{frames}.npy"
    if not path.is_file():
        np.save(path, np.stack(office_frames(recording, frames)))
    runs: dict[str, list[dict[str, Any]]] = {"before": [], "now": []}
    for i in range(pairs):
        for name, repo in alternated(i, tree):
            done = subprocess.run([sys.executable, "-c", DESCRIBE_CHILD, str(path), str(mode)], capture_output=True,
                                  text=True, cwd=repo, env={**os.environ, "PYTHONPATH": str(repo)})
            if done.returncode != 0:
                raise RuntimeError(f"describe with the code of {repo} failed: "
                                   f"{(done.stderr.strip().splitlines() or [''])[-1]}")
            runs[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
            log(f"describe, pair {i + 1}, {name}: {runs[name][-1]['median_ms']:.2f} ms median")
    return {"mode": mode, "frames": frames, "recording": str(recording), **runs,
            "ratios": [a["median_ms"] / b["median_ms"] for a, b in zip(runs["now"], runs["before"])]}


def replay_markdown(payload: dict[str, Any]) -> list[str]:
    p = payload["params"]
    lines = [f"# robotd replay, this code against the code of {p['before'][:12]} (generated by "
             "bench/bench_revisions.py replay --markdown)", "",
             f"`robotd replay` of the recorded 60 s office drive with the code of `{p['before'][:12]}` (before) and "
             f"of `{(payload['machine'].get('git_commit') or '?')[:12]}` (now), each with its own defaults, "
             f"{p['pairs']} pairs alternated; CPU is the process's user + system time, start-up included. "
             f"Load average {payload.get('load_start')} at the start, {payload.get('load_end')} at the end.", "",
             "| config | keyframes before / now | CPU-s per robot second, before | now | ratio now / before (each pair) |",
             "|---|---|---|---|---|"]
    for r in payload.get("replay", []):
        lines.append(f"| {r['config']} | {r['before'][0]['keyframes']} / {r['now'][0]['keyframes']} | "
                     f"{r['per_robot_s']['before']:.3f} | {r['per_robot_s']['now']:.3f} | "
                     f"{', '.join(f'{x:.3f}' for x in r['ratios'])} |")
    return lines + [""]


def describe_markdown(payload: dict[str, Any]) -> list[str]:
    p, d = payload["params"], payload["describe"]
    return [f"# The floor describe, this code against the code of {p['before'][:12]} (generated by "
            "bench/bench_revisions.py describe --markdown)", "",
            f"`extract` in mode {d['mode']} of {d['frames']} floor frames spread over the recorded 60 s office drive, "
            f"with the code of `{p['before'][:12]}` (before) and of "
            f"`{(payload['machine'].get('git_commit') or '?')[:12]}` (now), each in a process of its own, "
            f"{p['pairs']} pairs alternated; wall-clock time per frame. Load average {payload.get('load_start')} "
            f"at the start, {payload.get('load_end')} at the end.", "",
            "| pair | before, median / 90th percentile (ms) | now (ms) | ratio of the medians |", "|---|---|---|---|",
            *[f"| {i + 1} | {b['median_ms']:.2f} / {b['p90_ms']:.2f} | {a['median_ms']:.2f} / {a['p90_ms']:.2f} | "
              f"{r:.3f} |" for i, (b, a, r) in enumerate(zip(d["before"], d["now"], d["ratios"]))], ""]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", nargs="?", choices=("demo", "replay", "describe"), default="demo")
    ap.add_argument("--before", help="the revision to compare against (a commit, tag or branch)")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--full", action="store_true", help="seeds 0-4")
    ap.add_argument("--pairs", type=int, default=3, help="replay, describe: alternated pairs (default 3)")
    ap.add_argument("--frames", type=int, default=200, help="describe: floor frames timed (default 200)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench-revisions"), help="snapshots and outputs")
    ap.add_argument("--reuse", action="store_true", help="keep a demo whose summary.json is in --work")
    ap.add_argument("--out", type=Path, default=None, help="JSON (default docs/benchmarks/PART_revisions.json)")
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--page-from", type=Path, default=None, help="measure nothing: write --markdown from this JSON")
    args = ap.parse_args(argv)
    page = {"demo": markdown, "replay": replay_markdown, "describe": describe_markdown}[args.part]
    if args.page_from is not None:
        if args.markdown is None:
            ap.error("--page-from needs --markdown")
        write_page(args.markdown, page(json.loads(args.page_from.read_text())))
        return 0
    if not args.before:
        ap.error("--before REV is needed")
    if args.pairs < 1:
        ap.error("--pairs must be at least 1")
    if args.frames < 1:
        ap.error("--frames must be at least 1")
    work = args.work.resolve()
    tree, commit = snapshot(args.before, work)
    load_start = os.getloadavg()
    payload: dict[str, Any] = {"machine": machine_info(), "load_start": [round(x, 2) for x in load_start]}
    if args.part == "replay":
        payload["params"] = {"before": commit, "pairs": args.pairs}
        payload["replay"] = replay_part(tree, work, args.pairs)
        print_table(["config", "keyframes", "CPU-s per robot s before", "now", "ratios"],
                    [[r["config"], f"{r['before'][0]['keyframes']} / {r['now'][0]['keyframes']}",
                      round(r["per_robot_s"]["before"], 3), round(r["per_robot_s"]["now"], 3),
                      ", ".join(f"{x:.3f}" for x in r["ratios"])] for r in payload["replay"]])
    elif args.part == "describe":
        payload["params"] = {"before": commit, "pairs": args.pairs}
        payload["describe"] = describe_part(tree, work, args.pairs, args.frames)
        print_table(["pair", "before ms", "now ms", "ratio"],
                    [[i + 1, round(b["median_ms"], 2), round(a["median_ms"], 2), round(r, 3)] for i, (b, a, r) in
                     enumerate(zip(payload["describe"]["before"], payload["describe"]["now"],
                                   payload["describe"]["ratios"]))])
    else:
        seeds = [0, 1, 2, 3, 4] if args.full else [int(s) for s in args.seeds.split(",")]
        payload["params"] = {"before": commit, "seeds": seeds, "route": "office"}
        payload["seeds"] = demo_part(tree, work, seeds, args.reuse)
    payload["load_end"] = [round(x, 2) for x in os.getloadavg()]
    path = write_json(args.out or DEFAULT_OUT[args.part], payload)
    print(f"\nwrote {path}")
    if args.markdown is not None:
        write_page(args.markdown, page(payload))
    return 0


if __name__ == "__main__":
    sys.exit(main())
