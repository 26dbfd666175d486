"""Floor-camera rendering speed per core, with tile generation reported separately.

The virtual robot renders 640x480 floor frames at 30 Hz; the demo must run faster than
real time on 2 cores together with the rest of the pipeline, so rendering alone should
be well above 60 frames/s on one core. This benchmark (OpenCV limited to one thread):

* drives a straight 10 m line and a 10 m curve (radius 3 m) at 0.3 m/s, one frame every
  1/30 s, over the default floor (brick, grass, gravel quilted; default camera and
  render parameters: 3-sample motion blur at 0.3 m/s, read + shot noise, gain drift);
* cold pass: empty tile cache, so frames that need new floor wait for tile generation;
  then the tiles of that pass are regenerated one by one to time a tile (ms/tile);
* warm passes: the same path with every tile cached; per-frame median and spread
  (interquartile range) after the cold pass as warm-up, and whole-path throughput;
* the same with blur and noise off, to show what they cost;
* baseline, same run: one plain ``cv2.remap`` of a 640x480 uint8 image with precomputed
  float maps, the floor of what a frame can cost; render cost is printed as a ratio to it;
* the 10 x 10 m floor overview at 100 px/m that trajectory plots draw.

Run: ``.venv/bin/python bench/bench_render.py [--out FILE] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import skimage

try:
    from bench.common import machine_info, print_table, time_repeats, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, time_repeats, write_json

from robotd.base.camera import FloorCameraModel
from sim.world.floor import Floor
from sim.cameras.floor import FloorRenderer, RenderParams

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "render.json"
FPS = 30.0
SPEED_MPS = 0.3
DISTANCE_M = 10.0
CURVE_RADIUS_M = 3.0


def path_poses(kind: str) -> tuple[np.ndarray, float, float]:
    """Poses ``(N, 3)`` at 30 Hz along the path, and the constant ``v``, ``w`` on it."""
    n = int(round(DISTANCE_M / SPEED_MPS * FPS)) + 1
    s = np.arange(n) * SPEED_MPS / FPS  # arc length, metres
    if kind == "straight":
        return np.column_stack([s, np.zeros(n), np.zeros(n)]), SPEED_MPS, 0.0
    w = SPEED_MPS / CURVE_RADIUS_M
    th = s / CURVE_RADIUS_M
    poses = np.column_stack([CURVE_RADIUS_M * np.sin(th), CURVE_RADIUS_M * (1.0 - np.cos(th)), th])
    return poses, SPEED_MPS, w


def _stats_ms(runs_s: list[float]) -> dict[str, float]:
    ms = sorted(1e3 * r for r in runs_s)
    q1, med, q3 = statistics.quantiles(ms, n=4, method="inclusive")
    return {"median_ms": med, "iqr_ms": q3 - q1, "p90_ms": ms[int(0.9 * (len(ms) - 1))], "max_ms": ms[-1]}


def drive(renderer: FloorRenderer, poses: np.ndarray, v: float, w: float) -> tuple[list[float], float]:
    """Render every pose once; per-frame seconds and the whole pass in seconds."""
    per_frame = []
    t_start = time.perf_counter()
    for k, pose in enumerate(poses):
        t0 = time.perf_counter()
        renderer.render(pose, v, w, k / FPS)
        per_frame.append(time.perf_counter() - t0)
    return per_frame, time.perf_counter() - t_start


def bench_path(kind: str, params: RenderParams, label: str, repeats: int, seed: int) -> dict[str, object]:
    floor = Floor.default(seed=seed)
    cam = FloorCameraModel.default()
    cam.pixel_floor_grid_robot()  # per-model precomputation, once, outside the timings
    renderer = FloorRenderer(floor, cam, params, np.random.default_rng(seed))
    poses, v, w = path_poses(kind)

    cold_frames, cold_total = drive(renderer, poses, v, w)
    tiles = floor.cached_tiles()  # the tiles this path needed
    n_tiles = floor.tiles_generated
    # Time tile generation alone: regenerate each tile of the path from an empty cache.
    floor.clear_cache()
    tile_runs = []
    for key in tiles:
        t0 = time.perf_counter()
        floor.tile(*key)
        tile_runs.append(time.perf_counter() - t0)

    warm_frames: list[float] = []
    warm_totals = []
    for _ in range(repeats):
        frames, total = drive(renderer, poses, v, w)
        warm_frames += frames
        warm_totals.append(total)
    warm = _stats_ms(warm_frames)
    return {
        "path": kind,
        "config": label,
        "frames": len(poses),
        "blur_samples": renderer.blur_samples(v, w),
        "cold": {"total_s": cold_total, "fps_throughput": len(poses) / cold_total, **_stats_ms(cold_frames)},
        "tiles": {"count": n_tiles, "per_m": n_tiles / DISTANCE_M, "tile_px": floor.params.tile_px,
                  **_stats_ms(tile_runs), "total_s": sum(tile_runs)},
        "warm": {**warm, "fps_median": 1e3 / warm["median_ms"],
                 "fps_throughput": len(poses) / statistics.median(warm_totals)},
        "patches_fetched_per_pass": renderer.patches_fetched / (repeats + 1),
    }


def bench_remap_baseline(repeats: int, seed: int) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    src = rng.integers(0, 256, (1600, 1600), dtype=np.uint8)
    cam = FloorCameraModel.default()
    grid = cam.pixel_floor_grid_robot()
    maps = (grid / 0.001 + 800.0).astype(np.float32)  # the same kind of map a frame uses
    inner = 200

    def run() -> None:
        for _ in range(inner):
            cv2.remap(src, maps, None, cv2.INTER_LINEAR)

    t = time_repeats(run, repeats=max(repeats, 5), warmup=1)
    return {"median_ms": 1e3 * t["median_s"] / inner, "iqr_ms": 1e3 * t["iqr_s"] / inner}


def bench_overview(repeats: int, seed: int) -> dict[str, float]:
    floor = Floor.default(seed=seed)
    t = time_repeats(lambda: floor.render_overview(-5.0, -5.0, 5.0, 5.0, 100.0), repeats=max(repeats, 3), warmup=1)
    return {"median_ms": 1e3 * t["median_s"], "iqr_ms": 1e3 * t["iqr_s"], "size_px": [1000, 1000]}


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output (default bench/results/render.json)")
    ap.add_argument("--repeats", type=int, default=3, help="warm passes over each path (default 3)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)

    baseline = bench_remap_baseline(args.repeats, args.seed)
    default = RenderParams()
    bare = RenderParams(motion_blur=False, noise_sigma=0.0, shot_noise=False, drift_amplitude=0.0)
    runs = [
        bench_path("straight", default, "default", args.repeats, args.seed),
        bench_path("curve", default, "default", args.repeats, args.seed),
        bench_path("straight", bare, "no blur, no noise", args.repeats, args.seed),
    ]
    overview = bench_overview(args.repeats, args.seed)

    rows = []
    for r in runs:
        warm, cold, tiles = r["warm"], r["cold"], r["tiles"]
        rows.append([
            r["path"], r["config"], r["blur_samples"],
            round(warm["median_ms"], 2), round(warm["iqr_ms"], 2), round(warm["p90_ms"], 2),
            round(warm["fps_median"]), round(warm["fps_throughput"]), round(cold["fps_throughput"]),
            round(warm["median_ms"] / baseline["median_ms"], 1),
            round(tiles["median_ms"], 1), round(tiles["iqr_ms"], 1), round(tiles["per_m"], 1),
        ])
    print(f"640x480 floor frames, one core (cv2.setNumThreads(1)), {DISTANCE_M:g} m at {SPEED_MPS} m/s, {FPS:g} Hz")
    print_table(
        ["path", "config", "blur n", "ms med", "ms IQR", "ms p90", "fps med", "fps warm", "fps cold",
         "x remap", "tile ms", "tile IQR", "tiles/m"],
        rows,
    )
    print()
    print_table(
        ["baseline / floor API", "median ms", "IQR ms"],
        [["cv2.remap 640x480 uint8, float maps", round(baseline["median_ms"], 3), round(baseline["iqr_ms"], 3)],
         ["render_overview 10x10 m at 100 px/m", round(overview["median_ms"], 1), round(overview["iqr_ms"], 1)]],
    )
    payload = {
        "benchmark": "render",
        "machine": machine_info(),
        "versions": {"opencv": cv2.__version__, "scikit-image": skimage.__version__, "numpy": np.__version__},
        "settings": {"threads": 1, "fps": FPS, "speed_mps": SPEED_MPS, "distance_m": DISTANCE_M,
                     "curve_radius_m": CURVE_RADIUS_M, "repeats": args.repeats, "seed": args.seed,
                     "image": [640, 480]},
        "baseline_remap": baseline,
        "runs": runs,
        "overview_10x10m_100ppm": overview,
    }
    out = write_json(args.out, payload)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
