"""The live pose graph's memory and CPU per keyframe as it grows, every loop in it or thinned.

The pose graph (:class:`robotd.graph.incremental.IncrementalGraph`) is fed a map's links in
the order the daemon added them (the ``links`` table of a map written by ``robotd`` or by
``bench/bench_daemon.py --memory N --keep-map FILE``) or a synthetic map, as the graph
stage feeds it: each keyframe with its odometry edge, each loop after the chi-square
test's marginals (:meth:`~robotd.graph.incremental.IncrementalGraph.loop_chi2`), a full
solve every 200 keyframes (``[pose_graph] full_solve_every_keyframes``). Resident memory
after ``malloc_trim`` (GTSAM's C++ is invisible to tracemalloc) less the process's before
the first keyframe, CPU seconds of the updates and of the full solves, and the graph's own
size (loops in it and left out, iSAM2's factors, cliques and tree entries) every
``--every`` keyframes, for each setting in turn, each in a process of its own:

* ``every loop``: ``loop_spacing 0, loops_per_keyframe 0, fold 1`` (every accepted loop
  enters, every keyframe an iSAM2 variable);
* ``every keyframe in iSAM2``: ``fold 1``, the loops thinned as by default;
* ``thinned``: the loops thinned, and after each full solve the keyframes iSAM2 does
  not need folded into their odometry (``IncrementalParams.fold``), every place taking
  loops from every later pass (``loops_per_place`` 0);
* ``one loop per place``: the code's defaults, as ``thinned`` but with one loop in iSAM2
  per older place (``IncrementalParams.loops_per_place``).

``--synthetic laps|new N`` builds the map instead from the first 515 keyframes of
``--map`` (one lap of the office route at 15 cm): ``laps`` drives that lap again and
again (positions jittered by 2 cm) with loops to up to 8 keyframes of earlier passes
within 10 cm and 0.3 rad (a loop's noise and information drawn from the map's); ``new``
lays the lap's shape on new ground, each copy 20 m from the others (loops only within
a lap).

Run: ``python bench/bench_graph_memory.py --map MAP [--synthetic laps|new N] [--doc FILE]``;
writes ``NAME.json`` under ``--out`` (default bench/results); ``--page JSON... --doc FILE``
writes the page from several such files' runs. The default replays the map
given (a 1,500-keyframe map of three office laps: a few minutes); ``--full`` adds the two
synthetic maps of 10,000 keyframes.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import REPO_ROOT, machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import REPO_ROOT, machine_info, write_json

DEFAULT_MAP = Path.home() / ".cache" / "robotd-bench" / "office-3laps-map.sqlite"
SETTINGS = {"every loop": {"loop_spacing": 0, "loops_per_keyframe": 0, "fold": 1, "loops_per_place": 0},
            "every keyframe in iSAM2": {"fold": 1, "loops_per_place": 0}, "thinned": {"loops_per_place": 0},
            "one loop per place": {"loops_per_place": 1},
            "tied to the first pass": {"tie_to": "first"}}


def trimmed_rss_mb() -> float:
    """Resident memory after glibc's ``malloc_trim(0)``, MB."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def synthetic(source: Path, out: Path, n: int, kind: str, seed: int = 0, noisy: bool = False) -> None:
    """Write a synthetic map (``keyframes`` and ``links`` tables only) of ``n`` keyframes
    to ``out`` (see the module notes); ``noisy``: each odometry edge also drawn from its
    own information (otherwise exact), so that the solved map's error against the true
    poses (the ``keyframes`` table) measures what the loops correct."""
    from robotd.base.geometry import between

    rng = np.random.default_rng(seed)
    db = sqlite3.connect(f"file:{source}?mode=ro", uri=True)
    lap = np.array(list(db.execute("SELECT x_m, y_m, yaw_rad FROM keyframes ORDER BY id LIMIT 515")))
    infos = [np.frombuffer(b).reshape(3, 3) for (b,) in db.execute(
        "SELECT information FROM links WHERE kind = 'loop' LIMIT 200")]
    odo_infos = [np.frombuffer(b).reshape(3, 3) for (b,) in db.execute(
        "SELECT information FROM links WHERE kind = 'odometry' LIMIT 500")]
    db.close()
    reps = n // len(lap) + 1
    if kind == "laps":
        poses = np.concatenate([lap + rng.normal(0, [0.02, 0.02, 0.01], lap.shape) for _ in range(reps)])[:n]
    else:
        poses = np.concatenate([lap + [20.0 * (r % 5), 20.0 * (r // 5), 0.0] for r in range(reps)])[:n]
    o = sqlite3.connect(out)
    o.execute("CREATE TABLE keyframes (id INTEGER, x_m REAL, y_m REAL, yaw_rad REAL)")
    o.execute("CREATE TABLE links (id INTEGER PRIMARY KEY, kind TEXT, from_id INT, to_id INT, "
              "dx_m REAL, dy_m REAL, dyaw_rad REAL, information BLOB)")
    o.executemany("INSERT INTO keyframes VALUES (?, ?, ?, ?)", [(k + 1, *map(float, p)) for k, p in enumerate(poses)])
    rows = []
    for k in range(1, n):
        info = odo_infos[k % len(odo_infos)]
        d = between(poses[k - 1], poses[k])
        if noisy:
            d = d + np.random.default_rng([seed, k]).multivariate_normal(np.zeros(3), np.linalg.inv(info))
        rows.append(("odometry", k, k + 1, *map(float, d), info.tobytes()))
        if k <= 100:
            continue
        dist = np.hypot(*(poses[:k - 100, :2] - poses[k, :2]).T)
        dyaw = np.abs((poses[:k - 100, 2] - poses[k, 2] + np.pi) % (2 * np.pi) - np.pi)
        near = np.flatnonzero((dist < 0.10) & (dyaw < 0.3))
        for c in rng.permutation(near[np.argsort(dist[near])][:8]):
            info = infos[rng.integers(len(infos))]
            d = between(poses[c], poses[k]) + rng.multivariate_normal(np.zeros(3), np.linalg.inv(info))
            rows.append(("loop", int(c) + 1, k + 1, *map(float, d), info.tobytes()))
    o.executemany("INSERT INTO links (kind, from_id, to_id, dx_m, dy_m, dyaw_rad, information) "
                  "VALUES (?, ?, ?, ?, ?, ?, ?)", rows)
    o.commit()
    o.close()


def replay(map_path: Path, params: dict[str, Any], every: int, solve_every: int,
           gate: bool = True, truth: bool = False) -> dict[str, Any]:
    """One setting, in this process: the map's links through an IncrementalGraph
    (``truth``: the map's keyframe poses are the truth, and the last full solve's error
    against them is reported, ``ape_rms_m``)."""
    from robotd.graph.incremental import IncrementalGraph, IncrementalParams

    db = sqlite3.connect(f"file:{map_path}?mode=ro", uri=True)
    poses = {k: (x, y, t) for k, x, y, t in db.execute("SELECT id, x_m, y_m, yaw_rad FROM keyframes")}
    links = db.execute("SELECT kind, from_id, to_id, dx_m, dy_m, dyaw_rad, information FROM links ORDER BY id")
    graph = IncrementalGraph(IncrementalParams(**params))
    gc.collect()
    rss0 = trimmed_rss_mb()
    first = min(poses)
    graph.add_first(first, poses[first])
    n, since, update_s, solve_s, samples = 1, 0, 0.0, 0.0, []
    for kind, a, b, dx, dy, dyaw, blob in links:
        info = np.frombuffer(blob).reshape(3, 3)
        t0 = time.process_time()
        if kind == "odometry":
            if b in graph.graph:
                continue
            graph.add_keyframe(b, a, (dx, dy, dyaw), info)
            n += 1
            since += 1
        else:
            if gate:
                graph.loop_chi2(a, b, (dx, dy, dyaw), info)
            graph.add_loop(a, b, (dx, dy, dyaw), info)
        update_s += time.process_time() - t0
        if kind != "odometry":
            continue
        if solve_every and since >= solve_every:
            t0 = time.process_time()
            graph.resolve()
            solve_s += time.process_time() - t0
            since = 0
        if n % every == 0:
            gc.collect()
            samples.append({"keyframes": n, "graph_mb": trimmed_rss_mb() - rss0, "update_cpu_s": update_s,
                            "solve_cpu_s": solve_s, **graph.stats()})
            print(json.dumps(samples[-1]), file=sys.stderr, flush=True)
    db.close()
    out = {"params": params, "samples": samples, "keyframes": n, "update_cpu_s": update_s, "solve_cpu_s": solve_s}
    if truth:  # the final full solve against the true poses: APE RMS, anchored at the first keyframe
        result = graph.resolve()
        true = np.array([poses[int(k)] for k in result.ids])
        out["ape_rms_m"] = float(np.sqrt(np.mean(np.sum((result.poses[:, :2] - true[:, :2]) ** 2, axis=1))))
        out["loops_in_full_solve"] = int(graph.graph.loop_count)
    return out


def markdown(payload: dict[str, Any]) -> str:
    """The page: a table per map, a row per sample and setting."""
    m = payload["machine"]
    lines = ["# The live pose graph's memory and CPU (`bench/bench_graph_memory.py`)", "",
             "Generated from the JSON files beside it (`--page`); see the script's notes. Memory: resident after "
             "`malloc_trim`, less the process's before the first keyframe. CPU: process time of "
             "the iSAM2 updates (with the gate's marginals for each loop) and of the full solves.", "",
             f"Machine: {m['platform']}, {m['cpu_count']} CPUs, Python {m['python']}, numpy {m['numpy']}.", ""]
    for run in payload["runs"]:
        lines += [f"## {run['map']}", "",
                  "| setting | keyframes | graph MB | update CPU ms per keyframe (so far) | full solves CPU s "
                  "| loops in / left out | iSAM2 cliques | tree entries | keyframes folded |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for name, r in run["settings"].items():
            for s in r["samples"]:
                lines.append(f"| {name} | {s['keyframes']} | {s['graph_mb']:.1f} | "
                             f"{s['update_cpu_s'] / s['keyframes'] * 1e3:.2f} | {s['solve_cpu_s']:.1f} | "
                             f"{s['loops']} / {s['held_loops']} | {s['cliques']} | {s['tree_nnz']} | "
                             f"{s.get('folded', 0)} |")
        lines.append("")
        apes = [(name, r) for name, r in run["settings"].items() if "ape_rms_m" in r]
        if apes:
            lines += ["The last full solve against the true poses (APE RMS, anchored at the first keyframe): "
                      + "; ".join(f"{name} {r['ape_rms_m'] * 1e3:.1f} mm ({r['loops_in_full_solve']} loops in the "
                                  f"graph)" for name, r in apes) + ".", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--map", type=Path, default=DEFAULT_MAP,
                    help="a map file (its links table, in order; default: the cached three office laps, "
                         "made by bench/bench_daemon.py --memory 1500 --keep-map FILE)")
    ap.add_argument("--synthetic", nargs=2, metavar=("laps|new", "N"), default=None,
                    help="a synthetic map of N keyframes from the map's first lap instead")
    ap.add_argument("--every", type=int, default=500, help="sample every this many keyframes (default 500)")
    ap.add_argument("--solve-every", type=int, default=200, help="full solve every this many keyframes")
    ap.add_argument("--noisy", action="store_true",
                    help="with --synthetic: odometry edges drawn from their information too, and each setting's "
                         "last full solve against the true poses (APE RMS)")
    ap.add_argument("--truth", action="store_true", help=argparse.SUPPRESS)  # the child: the map's poses are true
    ap.add_argument("--no-gate", action="store_true",
                    help="leave out the gate's marginals (loop_chi2) before each loop: faster, memory alike")
    ap.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated, of: " + ", ".join(SETTINGS))
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)  # a setting, in a child process
    ap.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results")
    ap.add_argument("--name", default="graph_memory")
    ap.add_argument("--doc", type=Path, default=None, help="also write the markdown page here")
    ap.add_argument("--page", type=Path, nargs="+", default=None, metavar="JSON",
                    help="only write the page (--doc) from these JSON files' runs, in order")
    ap.add_argument("--full", action="store_true",
                    help="also the synthetic maps of 10,000 keyframes, laps and new ground (about an hour)")
    args = ap.parse_args(argv)
    if args.page is not None:
        payloads = [json.loads(f.read_text(encoding="utf-8")) for f in args.page]
        page = markdown({"machine": payloads[0]["machine"], "runs": [r for p in payloads for r in p["runs"]]})
        if args.doc is not None:
            args.doc.write_text(page, encoding="utf-8")
            print(f"wrote {args.doc}")
        else:
            print(page, end="")
        return 0
    if not args.map.is_file():
        ap.error(f"no map at {args.map}: make one with bench/bench_daemon.py --memory 1500 --keep-map {args.map}")
    if args.one is not None:
        print(json.dumps(replay(args.map, SETTINGS[args.one], args.every, args.solve_every, not args.no_gate,
                                args.truth)))
        return 0
    maps = [None] if args.synthetic is None else [(args.synthetic[0], int(args.synthetic[1]))]
    if args.full:
        maps += [("laps", 10000), ("new", 10000)]
    results = []
    for which in maps:
        with tempfile.TemporaryDirectory() as tmp:
            map_path, label = args.map, str(args.map)
            if which is not None:
                map_path = Path(tmp) / "synthetic.sqlite"
                synthetic(args.map, map_path, which[1], which[0], noisy=args.noisy)
                label = f"synthetic, {which[1]} keyframes, " + (
                    "the office lap driven again and again" if which[0] == "laps"
                    else "the office lap's shape over new ground") + (", odometry noisy" if args.noisy else "")
            runs: dict[str, Any] = {}
            for name in args.settings.split(","):
                out = subprocess.run([sys.executable, __file__, "--map", str(map_path), "--one", name,
                                      "--every", str(args.every), "--solve-every", str(args.solve_every)]
                                     + (["--no-gate"] if args.no_gate else [])
                                     + (["--truth"] if args.noisy and which is not None else []),
                                     check=True, stdout=subprocess.PIPE, text=True)
                runs[name] = json.loads(out.stdout.strip().splitlines()[-1])
            results.append({"map": label + ("" if not args.no_gate else ", without the gate's marginals"),
                            "settings": runs})
    payload = {"machine": machine_info(), "runs": results,
               "args": {k: str(v) for k, v in vars(args).items()}}
    path = write_json(args.out / f"{args.name}.json", payload)
    print(f"wrote {path}")
    if args.doc is not None:
        args.doc.write_text(markdown(payload), encoding="utf-8")
        print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
