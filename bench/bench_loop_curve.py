"""Loop thresholds trained from odometry and checked against ground truth (paper 003 Sec. IV-C).

For each floor (the printed plank floor whose four prints repeat, the paper's worst case;
the default mixed floor of real photos; the herringbone brick photo in
``../shared/data/floor``; any ``--floor FILE``) the virtual robot drives two routes over
the same floor and both drives are recorded to MCAP with ``robotd record --virtual``:

* ``--train-route`` (default ``figure8``): the calibration drive;
* ``--val-route`` (default ``square``): another route, the validation drive.

Then, exactly as a user would, with the ``robotd`` command's own code:

* ``robotd calibrate loop-curve TRAIN.mcap --odometry fused`` and ``--odometry wheel``:
  thresholds per mode (paper Table III) from pairs labelled by the fused wheel+gyro
  odometry, and once by wheel-only odometry to show what the gyro changes; both once more
  with ``--drift 0``, which trusts the odometry over any travel and labels every candidate
  pair, revisits included (what the default drift bound protects against);
* ``robotd calibrate validate VAL.mcap``: precision and recall of each set of thresholds
  against the validation drive's *ground-truth* overlap (all scored pairs, and revisits:
  pairs more than 2 m of travel apart).

``--big`` adds the training time and peak memory of a 7154-frame recording (the paper's
office run: the ``office`` route, about 110 m, its frame rate set so that the recording
holds 7154 floor frames), with keyframes chosen by the daemon's rule. The baseline is the
same training with *every* pair of keyframes scored (the paper's N^2 labelling),
estimated from the measured per-pair time of the run, reported as a ratio.

Every step writes its own files into ``--out`` and is skipped when its output is already
there, so an interrupted run resumes (delete the folder to start afresh). ``--only NAME``
runs only some floors, ``--labels TAG`` only some training variants (``fused``, ``wheel``,
``fused-every-pair``, ``wheel-every-pair``). Writes
``DIR/loop_curve.json`` and prints the tables. Takes ~15 min per floor on 2 cores, plus
~25 min with ``--big``.

Run from the repo root: ``.venv/bin/python bench/bench_loop_curve.py [--out DIR] [--big]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

try:
    from bench.common import machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json

from robotd.app.cli import main as robotd
from robotd.base.config import Config, replace
from robotd.base.configfile import to_toml

HERRINGBONE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "floor" / "brick_floor_herringbone_1k.png"
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "loop_curve"
PAPER_FRAMES = 7154
MODES = (1, 2, 3, 4, 5, 6)
#: Training variants: name -> (file tag, odometry, extra ``calibrate loop-curve`` options).
LABELS = {"fused": ("fused", "fused", []), "wheel": ("wheel", "wheel", []),
          "fused, every pair": ("fused-every-pair", "fused", ["--drift", "0"]),
          "wheel, every pair": ("wheel-every-pair", "wheel", ["--drift", "0"])}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def step(out: Path, argv: list[str]) -> float:
    """Run ``robotd ARGV`` unless ``out`` exists; returns the wall time (0 when skipped)."""
    if out.exists():
        log(f"  (have {out.name})")
        return 0.0
    log("  robotd " + " ".join(argv))
    t0 = time.monotonic()
    rc = robotd(argv)
    if rc != 0:
        raise SystemExit(f"robotd {' '.join(argv)} failed with exit code {rc}")
    return time.monotonic() - t0


def floors(extra: list[str]) -> dict[str, list[str]]:
    """Floor name -> the ``robotd record`` options that make it."""
    out = {"planks": ["--floor-pattern", "planks"], "mixed": []}
    if HERRINGBONE.exists():
        out["herringbone"] = ["--floor", str(HERRINGBONE)]
    else:
        log(f"{HERRINGBONE} is missing: the herringbone floor is left out")
    for f in extra:
        out[Path(f).stem] = ["--floor", f]
    return out


def run_floor(name: str, floor_args: list[str], args: argparse.Namespace, cfg_path: Path) -> dict[str, Any]:
    d = args.out / name
    d.mkdir(parents=True, exist_ok=True)
    train, val = d / f"train-{args.train_route}.mcap", d / f"val-{args.val_route}.mcap"
    seed = str(args.seed)
    step(train, ["record", str(train), "--virtual", "--config", str(cfg_path), "--route", args.train_route,
                 "--seed", seed, *floor_args])
    step(val, ["record", str(val), "--virtual", "--config", str(cfg_path), "--route", args.val_route,
               "--seed", seed, *floor_args])
    res: dict[str, Any] = {"floor": name, "floor_args": floor_args}
    for label, (tag, odo, extra) in LABELS.items():
        if args.labels and tag not in args.labels:
            continue
        calib = d / f"calibration-{tag}.yml"
        tj, vj = d / f"train-{tag}.json", d / f"validate-{tag}.json"
        if not tj.exists() and calib.exists():
            calib.unlink()  # a half-finished earlier run
        step(tj, ["calibrate", "loop-curve", str(train), "--calibration", str(calib), "--odometry", odo, *extra,
                  "--plot", str(d / f"curves-{tag}.png"), "--json", str(tj)])
        step(vj, ["calibrate", "validate", str(val), "--calibration", str(calib), "--json", str(vj)])
        res[label] = {"train": json.loads(tj.read_text()), "validate": json.loads(vj.read_text())}
    return res


def run_big(args: argparse.Namespace, cfg: Config) -> dict[str, Any]:
    """The 7154-frame office recording and its training (fused odometry)."""
    from sim.route import build_route, plan_motion

    d = args.out / "big"
    d.mkdir(parents=True, exist_ok=True)
    duration = plan_motion(build_route("office")).duration_s
    # Frames are rendered at k / fps for k = 0, 1, ... while t < duration.
    fps = (PAPER_FRAMES - 0.5) / duration
    cfg_path = d / "robotd.toml"
    cfg_path.write_text(to_toml(replace(cfg, "floor_camera", fps=fps)))
    rec = d / "office.mcap"
    step(rec, ["record", str(rec), "--virtual", "--config", str(cfg_path), "--route", "office",
               "--seed", str(args.seed), *floors([])["planks"]])
    tj = d / "train-fused.json"
    calib = d / "calibration.yml"
    if not tj.exists() and calib.exists():
        calib.unlink()
    step(tj, ["calibrate", "loop-curve", str(rec), "--calibration", str(calib), "--plot", str(d / "curves.png"),
              "--json", str(tj)])
    out = {"fps": fps, "frames": _count_frames(rec), "train": json.loads(tj.read_text())}
    vj = d / "validate-planks-square.json"
    val = args.out / "planks" / f"val-{args.val_route}.mcap"
    if val.exists():
        step(vj, ["calibrate", "validate", str(val), "--calibration", str(calib), "--json", str(vj)])
        out["validate"] = json.loads(vj.read_text())
    return out


def _count_frames(path: Path) -> int:
    """Floor frames in a recording (counted without decoding the images)."""
    from drivers.recording.reader import RecordingReader

    with RecordingReader(path) as r:
        return sum(1 for ch, _ in r.raw_messages() if ch.topic == "/floor_camera/image/compressed")


def _pct(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.2f}"


def _thr(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def report(results: list[dict[str, Any]], big: dict[str, Any] | None) -> None:
    print("\nThresholds per mode (paper Table III: smallest local score with P(loop | score) >= 0.99)")
    rows = []
    for r in results:
        for odo in LABELS:
            if odo not in r:
                continue
            t = r[odo]["train"]
            rows.append([r["floor"], odo, t["keyframes"], t["pairs"], t.get("mislabelled_pairs", "?"),
                         *(_thr(t["modes"][str(m)]["threshold"]) for m in MODES)])
    print_table(["floor", "labels", "keyframes", "pairs", "wrong labels", *(f"m{m}" for m in MODES)], rows)

    for subset, title in (("all", "Validation on another route, against ground truth: precision / recall, % "
                                  "(all scored pairs)"),
                          ("revisits", "Revisits only (pairs > 2 m of travel apart): precision / recall, %")):
        print("\n" + title)
        rows = []
        for r in results:
            for odo in LABELS:
                if odo not in r:
                    continue
                v = r[odo]["validate"]["modes"]
                rows.append([r["floor"], odo, *(f"{_pct(v[str(m)][subset]['precision'])} / "
                                                f"{_pct(v[str(m)][subset]['recall'])}" for m in MODES)])
        print_table(["floor", "labels", *(f"m{m}" for m in MODES)], rows)

    print("\nTraining cost")
    rows = []
    for r in results:
        t = r["fused"]["train"]
        rows.append([r["floor"], t["keyframes"], t["pairs"], round(t["seconds"], 1),
                     round(t["peak_rss_mb_main"]), round(t["peak_rss_mb_largest_worker"])])
    if big is not None:
        t = big["train"]
        rows.append([f"office, {big['frames']} frames", t["keyframes"], t["pairs"], round(t["seconds"], 1),
                     round(t["peak_rss_mb_main"]), round(t["peak_rss_mb_largest_worker"])])
    print_table(["run", "keyframes", "pairs/mode", "train s", "main MB", "worker MB"], rows)
    if big is not None:
        t = big["train"]
        n = t["keyframes"]
        scoring_s = sum(m["seconds"] for m in t["modes"].values())
        all_pairs = n * (n - 1) // 2
        est = scoring_s * all_pairs / t["pairs"] + t["seconds_load"]
        big["all_pairs_estimate_s"] = est
        big["ratio_all_pairs_over_ours"] = est / t["seconds"]
        print(f"\n7154-frame recording: {n} keyframes, {t['pairs']} pairs per mode scored in "
              f"{t['seconds']:.0f} s ({t['seconds'] / 60:.1f} min) on {t['workers']} workers; scoring all "
              f"{all_pairs} pairs (baseline, estimated from this run's per-pair time) would take "
              f"{est:.0f} s: x{est / t['seconds']:.1f}")


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--floor", action="append", default=[], metavar="FILE", help="another floor photo")
    ap.add_argument("--only", action="append", default=[], metavar="NAME", help="only these floors")
    ap.add_argument("--labels", action="append", default=[], choices=[v[0] for v in LABELS.values()],
                    metavar="TAG", help="only these training variants (fused, wheel, fused-every-pair, "
                                        "wheel-every-pair; default all)")
    ap.add_argument("--train-route", default="figure8")
    ap.add_argument("--val-route", default="square")
    ap.add_argument("--seed", type=int, default=1, help="seed of the floors and the robots")
    ap.add_argument("--big", action="store_true", help="also the 7154-frame office recording")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    # The recordings need no floor detector; everything else is the default config.
    cfg = replace(Config(), "floor_detector", enabled=False)
    cfg = replace(cfg, "recording", image_format="png")  # train on the camera's own pixels
    cfg_path = args.out / "robotd.toml"
    cfg_path.write_text(to_toml(cfg))
    results = []
    for name, fargs in floors(args.floor).items():
        if args.only and name not in args.only:
            continue
        log(f"floor {name}")
        results.append(run_floor(name, fargs, args, cfg_path))
    big = run_big(args, cfg) if args.big else None
    report(results, big)
    payload = {"benchmark": "loop_curve", "machine": machine_info(),
               "settings": {"train_route": args.train_route, "val_route": args.val_route, "seed": args.seed},
               "floors": results, "big": big}
    path = write_json(args.out / "loop_curve.json", payload)
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
