"""``robotd calibrate loop-curve`` and ``robotd calibrate validate``: the command line of
the loop-threshold training in :mod:`calibration.train` (arguments, progress, the Table III
report, the calibration file update, JSON output)."""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from calibration.loop_curve import PrecisionRecall
from calibration.train import (
    MODES,
    ModeResult,
    ModeValidation,
    Progress,
    TrainParams,
    peak_rss_mb,
    load_run,
    drive_config,
    train,
    validate,
)
from robotd.base.camera import FloorCameraModel
from robotd.base.errors import CalibrationError

log = logging.getLogger(__name__)


def _progress_printer() -> Progress:
    from calibration.intrinsics import (
        ProgressBar,  # one progress bar for every calibration step
    )

    bars: dict[str, Any] = {}

    def show(label: str, done: int, total: int) -> None:
        bars.setdefault(label, ProgressBar(label))(done, total)

    return show


def _common_arguments(p: Any) -> None:
    p.add_argument("--config", type=Path, default=None,
                   help="robotd config (odometry, floor camera); default: the one the recording "
                        "was made with, else the defaults")
    p.add_argument("--modes", default="1,2,3,4,5,6", help="descriptor modes (default: all)")
    p.add_argument("--spacing", type=float, default=None, metavar="M",
                   help="keyframe spacing, metres (default: the config's [keyframes] distance_m)")
    p.add_argument("--rotation", type=float, default=None, metavar="DEG",
                   help="keyframe rotation, degrees (default: the config's [keyframes] rotation_deg)")
    p.add_argument("--r", type=float, default=TrainParams.r,
                   help=f"footprint overlap J that makes a loop (default {TrainParams.r})")
    p.add_argument("--far-pairs", type=float, default=TrainParams.far_pairs_per_keyframe, metavar="K",
                   help="distant pairs sampled per keyframe (default "
                        f"{TrainParams.far_pairs_per_keyframe:g})")
    p.add_argument("--workers", type=int, default=TrainParams.workers, help="worker processes")
    p.add_argument("--json", type=Path, default=None, metavar="FILE", help="also write the results as JSON")


def add_loop_curve_arguments(p: Any) -> None:
    p.add_argument("recording", type=Path, help="MCAP recording of a calibration drive")
    p.add_argument("--calibration", type=Path, required=True,
                   help="calibration file to write the thresholds into (created or updated)")
    p.add_argument("--odometry", choices=("fused", "wheel"), default="fused",
                   help="which odometry labels the pairs (default: fused wheel+gyro, as in the paper)")
    p.add_argument("--confidence", type=float, default=TrainParams.confidence,
                   help=f"P(loop | score) at the threshold (default {TrainParams.confidence})")
    p.add_argument("--drift", type=float, default=TrainParams.drift, metavar="F",
                   help="bound on the odometry's position error per metre of travel (default "
                        f"{TrainParams.drift:g}); pairs whose label that error could change are not used")
    p.add_argument("--label-tolerance", type=float, default=TrainParams.label_tolerance, metavar="F",
                   help="largest such error that still labels a pair, as a fraction of the footprint's "
                        f"shorter side (default {TrainParams.label_tolerance:g})")
    p.add_argument("--plot", type=Path, default=None, help="write the curves (paper Fig. 5) to this PNG")
    _common_arguments(p)


def _setup(args: Any) -> tuple[Any, FloorCameraModel, TrainParams]:
    from robotd.io.calibfile import camera_model, read_calibration

    cfg = drive_config(args.config, args.recording)
    calib = read_calibration(args.calibration) if args.calibration.exists() else None
    try:
        modes = tuple(sorted({int(m) for m in args.modes.split(",")}))
    except ValueError:
        raise CalibrationError(f"--modes must be a comma-separated list of 1..6, got {args.modes!r}") from None
    if not modes or not set(modes) <= set(MODES):
        raise CalibrationError(f"--modes must be a comma-separated list of 1..6, got {args.modes!r}")
    confidence = getattr(args, "confidence", TrainParams.confidence)
    spacing = cfg.keyframes.distance_m if args.spacing is None else args.spacing
    rotation = cfg.keyframes.rotation_deg if args.rotation is None else args.rotation
    drift = getattr(args, "drift", TrainParams.drift)
    tolerance = getattr(args, "label_tolerance", TrainParams.label_tolerance)
    if not (spacing > 0 and rotation > 0 and 0 < args.r <= 1 and 0 < confidence < 1
            and args.far_pairs >= 0 and args.workers >= 1 and drift >= 0 and tolerance > 0):
        raise CalibrationError("need --spacing > 0, --rotation > 0, 0 < --r <= 1, 0 < --confidence < 1, "
                               "--far-pairs >= 0, --workers >= 1, --drift >= 0, --label-tolerance > 0")
    params = TrainParams(modes=modes, spacing_m=spacing, rotation_deg=rotation,
                         odometry=getattr(args, "odometry", "fused"), far_pairs_per_keyframe=args.far_pairs,
                         r=args.r, confidence=confidence, workers=args.workers, drift=drift,
                         label_tolerance=tolerance)
    return cfg, camera_model(calib, cfg.floor_camera), params


def _row(name: str, values: list[str]) -> str:
    return f"{name:<22}" + "".join(f"{v:>9}" for v in values)


def format_table_iii(res: dict[int, ModeResult], params: TrainParams) -> str:
    """The trained thresholds in the layout of paper 003's Table III (one column per mode),
    with what stands behind each: P(loop) at the threshold and the training loops above it."""
    modes = list(res)
    lines = [_row("local score", [f"mode {m}" for m in modes])]
    lines.append(_row("threshold", [_fmt(r.threshold) for r in res.values()]))
    p_at, above, loops = [], [], []
    for r in res.values():
        is_loop = r.overlap >= params.r
        loops.append(str(int(is_loop.sum())))
        if r.threshold is None:
            p_at.append("-")
            above.append("-")
            continue
        p_at.append(f"{float(r.curve.at(r.threshold)):.4f}")
        above.append(str(int(np.sum((r.scores >= r.threshold) & is_loop))))
    lines.append(_row("P(loop) at threshold", p_at))
    lines.append(_row("loops (J >= r)", loops))
    lines.append(_row("loops above threshold", above))
    return "\n".join(lines)


def run_loop_curve(args: Any) -> int:

    from robotd.io.calibfile import (
        CalibrationFile,
        LoopThresholds,
        read_calibration,
        update_calibration,
    )

    t0 = time.monotonic()
    cfg, camera, params = _setup(args)
    progress = _progress_printer()
    run = load_run(args.recording, cfg, params, progress)
    t_load = time.monotonic() - t0
    res = train(run, camera, params, progress)
    seconds = time.monotonic() - t0
    own_mb = peak_rss_mb()
    worker_mb = max([run.worker_peak_rss_mb] + [r.worker_peak_rss_mb for r in res.values()])
    thresholds = {m: r.threshold for m, r in res.items()}
    old = read_calibration(args.calibration).loop if args.calibration.exists() else None
    by_mode, kept, dropped = merge_thresholds(old, thresholds, params)
    first = next(iter(res.values()))
    n_near = int(np.sum(first.weights == 1.0))
    out = sys.stdout
    print(f"\n{len(run.stamps_ns)} keyframes (every {params.spacing_m:g} m or {params.rotation_deg:g} deg); "
          f"{len(first.scores)} scored pairs per mode ({n_near} that could overlap, "
          f"{len(first.scores) - n_near} sampled distant ones); labels from {params.odometry} odometry, "
          f"loop = J >= {params.r}; {first.untrusted} candidate pairs left unlabelled (a drift of "
          f"{params.drift:g} per metre of travel could change their label)", file=out)
    if first.mislabelled is not None:
        print(f"ground truth (virtual robot) contradicts {first.mislabelled} of the {len(first.scores)} "
              "labels", file=out)
    print(f"Thresholds (paper 003 Table III): smallest local score with P(loop | score) >= "
          f"{params.confidence}", file=out)
    print(format_table_iii(res, params), file=out)
    print(f"training time {seconds:.1f} s (reading and describing {t_load:.1f} s, scoring "
          f"{sum(r.seconds for r in res.values()):.1f} s) on {params.workers} worker process(es); peak resident "
          f"memory {own_mb:.0f} MB (main process), {worker_mb:.0f} MB (largest worker)", file=out)
    untrained = [m for m, t in thresholds.items() if t is None]
    if untrained:
        print(f"modes {', '.join(map(str, untrained))}: no score reaches P(loop) >= {params.confidence} "
              "with enough evidence; no new threshold", file=out)
    if len(untrained) == len(thresholds):
        had = [m for m in range(1, 7) if old is not None and old.for_mode(m) is not None]
        raise CalibrationError(
            f"{args.recording}: no mode could be trained ({len(run.stamps_ns)} keyframes: too short "
            f"a drive, or too few revisits); {args.calibration} is left as it was"
            + (f", with its thresholds for modes {', '.join(map(str, had))}" if had else ""))
    update_calibration(args.calibration, CalibrationFile(loop=LoopThresholds.from_mapping(
        by_mode, overlap_r=params.r, confidence=params.confidence)))
    if kept:
        print(f"modes {', '.join(map(str, kept))}: the thresholds already in {args.calibration} are "
              "kept", file=out)
    if dropped and old is not None:  # only a file that had thresholds can lose some
        print(f"modes {', '.join(map(str, dropped))}: the thresholds in {args.calibration} were trained "
              f"for r = {old.overlap_r:g}, confidence {old.confidence:g} (not r = {params.r:g}, "
              f"confidence {params.confidence:g}) and are removed", file=out)
    print(f"thresholds written to {args.calibration}", file=out)
    if args.plot is not None:
        from robotd.io.plots import plot_loop_curves

        plot_loop_curves(args.plot, {m: r.curve for m, r in res.items()}, thresholds, params.confidence,
                         title=f"P(J >= {params.r} | local score), {len(run.stamps_ns)} keyframes, "
                               f"labels from {params.odometry} odometry")
        print(f"curves: {args.plot}", file=out)
    if args.json is not None:
        args.json.write_text(json.dumps({
            "recording": str(args.recording), "odometry": params.odometry, "keyframes": len(run.stamps_ns),
            "spacing_m": params.spacing_m, "r": params.r, "confidence": params.confidence,
            "pairs": len(first.scores), "near_pairs": n_near, "workers": params.workers,
            "unlabelled_pairs": first.untrusted, "mislabelled_pairs": first.mislabelled, "drift": params.drift,
            "label_tolerance": params.label_tolerance,
            "seconds": seconds, "seconds_load": t_load, "peak_rss_mb_main": own_mb,
            "peak_rss_mb_largest_worker": worker_mb,
            "modes": {str(m): {"threshold": r.threshold, "loops": int(np.sum(r.overlap >= params.r)),
                               "seconds": r.seconds,
                               "curve": {"score_lo": r.curve.score_lo.tolist(),
                                         "score_hi": r.curve.score_hi.tolist(),
                                         "probability": r.curve.probability.tolist(),
                                         "lower": r.curve.lower.tolist()}}
                      for m, r in res.items()},
        }, indent=2) + "\n")
    return 0


def merge_thresholds(old: Any, trained: dict[int, float | None], params: TrainParams,
                     ) -> tuple[dict[int, float], list[int], list[int]]:
    """The thresholds to write: each newly trained one, and the calibration file's own
    (``old``, a :class:`~robotd.io.calibfile.LoopThresholds` or None) for every mode not
    trained now, when they were trained for the same ``r`` and confidence. Returns
    ``(threshold by mode, modes whose old threshold is kept, modes whose old threshold
    cannot stand beside the new ones: another r or confidence)``."""
    by_mode = {m: t for m, t in trained.items() if t is not None}
    kept: list[int] = []
    dropped: list[int] = []
    if old is not None:
        same = (old.overlap_r, old.confidence) == (params.r, params.confidence)
        for m in range(1, len(old.thresholds) + 1):
            if m not in by_mode and old.for_mode(m) is not None:
                if same:
                    by_mode[m] = old.for_mode(m)
                    kept.append(m)
                else:
                    dropped.append(m)
    return by_mode, kept, dropped


def _fmt(t: float | None) -> str:
    return "-" if t is None else f"{t:.1f}"


def add_validate_arguments(p: Any) -> None:
    p.add_argument("recording", type=Path, help="MCAP recording of another drive (with ground truth)")
    p.add_argument("--calibration", type=Path, required=True, help="calibration file with thresholds")
    p.add_argument("--revisit", type=float, default=2.0, metavar="M",
                   help="pairs more than this much travel apart count as revisits (default 2 m)")
    _common_arguments(p)


def _pr_json(pr: PrecisionRecall) -> dict[str, Any]:
    """Counts, precision and recall as JSON values (null where undefined)."""
    def num(x: float) -> float | None:
        return x if math.isfinite(x) else None

    return {"true_positives": pr.true_positives, "false_positives": pr.false_positives,
            "false_negatives": pr.false_negatives, "precision": num(pr.precision), "recall": num(pr.recall)}


def _pct(x: float) -> str:
    return "-" if x != x else f"{100.0 * x:.2f}%"


def run_validate(args: Any) -> int:

    from robotd.io.calibfile import read_calibration

    cfg, camera, params = _setup(args)
    calib = read_calibration(args.calibration)
    if calib.loop is None:
        raise CalibrationError(f"{args.calibration}: no loop thresholds (run `robotd calibrate loop-curve`)")
    if args.r != calib.loop.overlap_r:
        log.warning("validating with r = %s but the thresholds were trained for r = %s",
                    args.r, calib.loop.overlap_r)
    progress = _progress_printer()
    run = load_run(args.recording, cfg, params, progress)
    res = validate(run, camera, {m: calib.loop.for_mode(m) for m in params.modes}, params,
                   revisit_m=args.revisit, progress=progress)
    out = sys.stdout
    print(f"\n{len(run.stamps_ns)} keyframes (every {params.spacing_m:g} m or {params.rotation_deg:g} deg); "
          f"a loop is a ground-truth overlap J >= {params.r}; distant pairs sampled and weighted", file=out)
    modes = list(res)
    rows: list[tuple[str, Callable[[ModeValidation], str]]] = [
        ("threshold", lambda v: _fmt(v.all_pairs.threshold if math.isfinite(v.all_pairs.threshold) else None)),
        ("declared loops", lambda v: str(v.all_pairs.true_positives + v.all_pairs.false_positives)),
        ("false loops", lambda v: str(v.all_pairs.false_positives)),
        ("missed loops", lambda v: str(v.all_pairs.false_negatives)),
        ("precision", lambda v: _pct(v.all_pairs.precision)),
        ("recall", lambda v: _pct(v.all_pairs.recall)),
        (f"revisits (> {args.revisit:g} m): loops", lambda v: str(v.revisits.true_positives
                                                                  + v.revisits.false_negatives)),
        ("  precision", lambda v: _pct(v.revisits.precision)),
        ("  recall", lambda v: _pct(v.revisits.recall)),
    ]
    print(f"{'local score':<26}" + "".join(f"{'mode ' + str(m):>9}" for m in modes), file=out)
    for name, cell in rows:
        print(f"{name:<26}" + "".join(f"{cell(v):>9}" for v in res.values()), file=out)
    if args.json is not None:
        args.json.write_text(json.dumps({
            "recording": str(args.recording), "keyframes": len(run.stamps_ns), "r": params.r,
            "revisit_m": args.revisit,
            "modes": {str(m): {
                "threshold": v.all_pairs.threshold if math.isfinite(v.all_pairs.threshold) else None,
                "all": _pr_json(v.all_pairs), "revisits": _pr_json(v.revisits)} for m, v in res.items()},
        }, indent=2) + "\n")
    return 0
