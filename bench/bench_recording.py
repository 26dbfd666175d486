"""Recording size and decoding cost: lossless PNG frames against JPEG at several qualities,
on the same drive.

One drive of the virtual robot is recorded once with PNG frames (lossless: the pixels the
daemon saw), then transcoded to JPEG at each quality (:func:`drivers.recording.transcode.transcode`,
which gives the very bytes a JPEG recording of that run holds). Reported per format: file
size, MB per minute of drive, how many times smaller than PNG, the mean absolute pixel
error against the PNG frames, the time to read and decode every frame (our reader, as a
replay does) and to encode one (as the recorder does), as ratios to PNG in the same run.
``--train`` also trains the loop thresholds (``robotd calibrate loop-curve``) on every form
of the drive and prints them side by side (CPU heavy: minutes per form).

Usage: ``python bench/bench_recording.py [--route figure8 --seed 11] [--recording PNG.mcap]
[--qualities 15,20,50] [--train]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

try:
    from bench.common import machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json  # type: ignore[no-redef]

REPO_ROOT = Path(__file__).resolve().parents[1]


def record_png(path: Path, route: str, seed: int, duration_s: float | None) -> None:
    """Record the virtual robot's drive with lossless PNG frames."""
    from robotd.app.demo import run_demo
    from robotd.base.config import Config, replace

    cfg = replace(Config(), "recording", image_format="png")
    run_demo(cfg, out=path.with_name(path.stem + "-demo"), route=route, seed=seed, duration_s=duration_s,
             plot=False, record=path)


def frames_of(path: Path) -> tuple[list[np.ndarray], float, float]:
    """Every floor frame of a recording, the robot time it spans (s), and the wall time
    to read and decode them all with our reader (s)."""
    from drivers.recording.reader import RecordingReader
    from robotd.base.messages import Frame

    t0 = time.perf_counter()
    frames = []
    with RecordingReader(path) as r:
        for _, m in r.messages():
            if isinstance(m, Frame) and m.camera == "floor":
                frames.append(m.image)
        span = r.time_range_ns
    wall = time.perf_counter() - t0
    return frames, (span[1] - span[0]) / 1e9 if span else 0.0, wall


def encode_ms(frames: list[np.ndarray], image_format: str, quality: int) -> float:
    """Median time to encode one frame as the recorder does, ms (every 10th frame)."""
    from drivers.recording.writer import image_encoding

    ext, params = image_encoding(image_format, quality, 1)
    times = []
    for f in frames[::10]:
        t0 = time.perf_counter()
        cv2.imencode(ext, f, params)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def train(path: Path, out: Path) -> dict[str, object]:
    """``robotd calibrate loop-curve`` on ``path``; its JSON (thresholds per mode)."""
    js = out / f"train-{path.stem}.json"
    if not js.exists():
        subprocess.run([sys.executable, "-m", "robotd.app.cli", "calibrate", "loop-curve", str(path),
                        "--calibration", str(out / f"cal-{path.stem}.yml"), "--workers", "1",
                        "--json", str(js)], check=True, cwd=REPO_ROOT)
    return json.loads(js.read_text())


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    from drivers.recording.transcode import transcode

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--recording", type=Path, default=None, help="an existing PNG recording (else one is made)")
    p.add_argument("--route", default="figure8")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--duration", type=float, default=None)
    p.add_argument("--qualities", default="15,20,50,75")
    p.add_argument("--work", type=Path, default=None, help="folder for the recordings (default: temporary)")
    p.add_argument("--train", action="store_true", help="also train the loop thresholds on every form")
    p.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "recording.json")
    args = p.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-recording-"))
    work.mkdir(parents=True, exist_ok=True)
    png = args.recording or work / "drive-png.mcap"
    if not png.exists():
        record_png(png, args.route, args.seed, args.duration)
    forms: list[tuple[str, Path, str, int]] = [("png", png, "png", 1)]
    for q in (int(x) for x in args.qualities.split(",")):
        dst = work / f"drive-jpeg{q}.mcap"
        if not dst.exists():
            transcode(png, dst, image_format="jpeg", jpeg_quality=q)
        forms.append((f"jpeg {q}", dst, "jpeg", q))
    ref, span_s, _ = frames_of(png)
    rows, results = [], []
    base: dict[str, float] = {}
    for name, path, fmt, q in forms:
        frames, _, read_s = frames_of(path)
        err = float(np.mean([np.abs(a.astype(np.int16) - b).mean() for a, b in zip(frames, ref, strict=True)]))
        enc = encode_ms(ref, fmt, q)
        size = path.stat().st_size
        res = {"form": name, "bytes": size, "mb_per_min": size / 1e6 / (span_s / 60.0),
               "read_decode_ms_per_frame": 1e3 * read_s / len(frames), "encode_ms_per_frame": enc,
               "mean_abs_error": err, "frames": len(frames)}
        base = base or res
        res["x_smaller"] = base["bytes"] / size
        res["read_decode_vs_png"] = res["read_decode_ms_per_frame"] / base["read_decode_ms_per_frame"]
        res["encode_vs_png"] = enc / base["encode_ms_per_frame"]
        if args.train:
            res["training"] = train(path, work)
        results.append(res)
        rows.append([name, f"{size / 1e6:.1f}", f"{res['mb_per_min']:.1f}", f"{res['x_smaller']:.1f}",
                     f"{err:.2f}", f"{res['read_decode_ms_per_frame']:.2f} ({res['read_decode_vs_png']:.2f})",
                     f"{enc:.2f} ({res['encode_vs_png']:.2f})"])
    print(f"{png}: {len(ref)} floor frames, {span_s:.1f} s of drive")
    print_table(["frames", "MB", "MB/min", "x smaller", "mean |error|", "read+decode ms/frame (vs PNG)",
                 "encode ms/frame (vs PNG)"], rows)
    write_json(args.out, {"machine": machine_info(), "recording": str(png), "span_s": span_s,
                          "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
