"""The forward loop detector on the virtual robot's forward camera.

Writes the forward-camera keyframes of a route in its textured world with their
same-place ground truth (:func:`sim.forward_sequence.write_forward_sequence`: images,
``gt.npy``, poses, a top view), then runs ``robotd eval forward`` on that folder in the
same process: the detector (incremental vocabulary, Bayes filter, epipolar verification)
beside its two baselines (best score without the filter, and brute-force SIFT + RANSAC
against every past image, skipped with ``--no-brute-force``: its time grows with the
square of the sequence). The eval prints precision, recall and recall at 100 % precision;
this script adds the sequence's own figures and writes one JSON.

Run: ``.venv/bin/python bench/bench_forward_sequence.py --dir /tmp/fwd [--step-m 0.1]
[--turn-deg 10] [--no-brute-force]``. The default keyframing (0.1 m or 10 deg) gives
1031 images on the office route.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

try:
    from bench.common import machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, write_json

from sim.forward_sequence import SequenceSettings, write_forward_sequence

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_sequence.json"


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, required=True, help="folder for the images, gt.npy and the eval output")
    ap.add_argument("--route", default="office")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--step-m", type=float, default=0.1, help="keyframe every STEP metres (default 0.1)")
    ap.add_argument("--turn-deg", type=float, default=10.0, help="or every TURN degrees (default 10)")
    ap.add_argument("--threshold", type=float, default=0.2, help="view overlap for 'same place' (default 0.2)")
    ap.add_argument("--repeats", type=int, default=1, help="drive the route this many times")
    ap.add_argument("--no-brute-force", action="store_true")
    ap.add_argument("--skip-write", action="store_true", help="reuse the images already in --dir")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)

    settings = SequenceSettings(route=args.route, seed=args.seed, step_m=args.step_m,
                                turn_rad=math.radians(args.turn_deg), threshold=args.threshold,
                                repeats=args.repeats)
    if args.skip_write:
        summary = json.loads((args.dir / "sequence.json").read_text())
    else:
        summary = write_forward_sequence(args.dir, settings)
    print(f"{args.dir}: {summary['images']} images of route {args.route!r} "
          f"({summary['route_length_m']:.0f} m), rendered in {summary['render_s']:.1f} s; "
          f"ground truth in {summary['ground_truth_s']:.1f} s, {summary['same_place_pairs']} same-place pairs")

    from robotd.app.cli import main as robotd_main

    eval_dir = args.dir / "eval"
    cmd = ["eval", "forward", "--images", str(args.dir), "--ground-truth", str(args.dir / "gt.npy"),
           "--focal-px", str(summary["camera"]["fx_px"]), "--out", str(eval_dir)]
    if args.no_brute_force:
        cmd.append("--no-brute-force")
    t0 = time.perf_counter()
    rc = robotd_main(cmd)
    t_eval = time.perf_counter() - t0
    if rc != 0:
        return rc
    report = json.loads((eval_dir / "forward_eval.json").read_text())
    payload = {
        "benchmark": "forward_sequence", "machine": machine_info(), "sequence": summary,
        "eval_command": "robotd " + " ".join(cmd), "eval_s": t_eval,
        "methods": report["methods"], "memory": report["memory"], "versions": report["versions"],
    }
    print(f"\nwrote {write_json(args.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
