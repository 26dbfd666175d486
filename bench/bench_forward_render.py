"""Forward-camera rendering speed per core: the column raycaster against two baselines.

The virtual robot's forward camera renders 640x480 grey frames of the office world
(:mod:`sim.world.rooms`) with one ray per image column (:mod:`sim.cameras.forward`). The
demo must stay faster than real time on 2 cores with everything else running, so this
benchmark (OpenCV limited to one thread) measures, along the office route's keyframes:

* the column raycaster, default parameters (mip levels, read noise), per frame, and its
  stages: casting the 640 column rays, building the per-pixel atlas maps, the remap;
* baseline 1, same run: a naive per-pixel raycaster written here (each of the 307,200
  pixel rays intersected with every wall plane, the floor and the ceiling, nearest hit,
  one remap of the same atlas at full resolution); its frames are compared with the
  column raycaster's (same atlas level, no noise) to show both draw the same picture;
* baseline 2, same run: the floor camera (:class:`sim.cameras.floor.FloorRenderer`,
  default camera and render parameters, 0.3 m/s motion blur) at the same poses, after a
  warm pass that fills its tile cache;
* the cost of one simulated second with the floor camera at 30 Hz and the forward camera
  at 10 Hz, in core-seconds.

Run: ``.venv/bin/python bench/bench_forward_render.py [--frames 200] [--out FILE]``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import skimage

try:
    from bench.common import machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json

from robotd.base.camera import FloorCameraModel
from sim.cameras.floor import FloorRenderer, RenderParams
from sim.cameras.forward import ForwardCameraModel, ForwardRenderer, ForwardRenderParams
from sim.forward_sequence import keyframe_times
from sim.route import build_route, plan_motion
from sim.world.floor import Floor
from sim.world.rooms import WallWorld, office_world

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_render.json"


def naive_render(world: WallWorld, camera: ForwardCameraModel, pose: np.ndarray, rows_per_block: int = 48) -> np.ndarray:
    """Baseline: one 3-D ray per pixel against every wall, the floor and the ceiling.

    Same optics and atlas (full-resolution level, no noise) as the column raycaster, but
    nothing is shared between the pixels of a column: each pixel's ray meets each wall's
    vertical plane, keeps hits inside the wall's extent and height, and takes the nearest
    of those, the floor and the ceiling.
    """
    k = camera.intrinsics
    wp = world.params
    x, y, h = camera.camera_pose(pose)
    f = np.array([math.cos(h), math.sin(h)])
    r = np.array([math.sin(h), -math.cos(h)])
    xn = (np.arange(k.width_px) - k.cx_px) / k.fx_px
    a, e = world.a_m, world.b_m - world.a_m
    length = np.linalg.norm(e, axis=1)
    wvec = a - np.array([x, y])
    map_x = np.empty((k.height_px, k.width_px), np.float32)
    map_y = np.empty_like(map_x)
    for v0 in range(0, k.height_px, rows_per_block):
        vv = (np.arange(v0, min(v0 + rows_per_block, k.height_px)) - k.cy_px) / k.fy_px  # (R,)
        # Per-pixel 3-D direction (forward component 1): (d2 = f + xn r, dz = -vv).
        d2 = f[None, None, :] + xn[None, :, None] * r[None, None, :]  # (1, W, 2)
        d2 = np.broadcast_to(d2, (len(vv), k.width_px, 2))
        dz = np.broadcast_to(-vv[:, None], (len(vv), k.width_px))
        denom = d2[..., 0, None] * e[None, None, :, 1] - d2[..., 1, None] * e[None, None, :, 0]  # (R, W, K)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wvec[:, 0] * e[:, 1] - wvec[:, 1] * e[:, 0]) / denom
            sig = (wvec[:, 0] * d2[..., 1, None] - wvec[:, 1] * d2[..., 0, None]) / denom
            hgt = camera.height_m + t * dz[..., None]
            ok = (t > 1e-9) & (sig >= 0) & (sig <= 1) & (hgt >= 0) & (hgt <= wp.wall_height_m)
        t = np.where(ok, t, np.inf)
        kk = np.argmin(t, axis=2)
        tw = np.take_along_axis(t, kk[..., None], 2)[..., 0]
        sw = np.take_along_axis(sig, kk[..., None], 2)[..., 0]
        hw = np.take_along_axis(hgt, kk[..., None], 2)[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(dz < 0, camera.height_m / -dz, np.inf)
            t_ceil = np.where(dz > 0, (wp.wall_height_m - camera.height_m) / dz, np.inf)
        wall = tw < np.minimum(t_floor, t_ceil)
        tex_m = (1.0 - sw) * length[kk]
        wx = world.tex_x0[kk] + tex_m * wp.px_per_m - 0.5
        wy = world.tex_y0[kk] + (wp.wall_height_m - hw) * wp.px_per_m - 0.5
        floor = t_floor < t_ceil
        tp = np.where(floor, t_floor, t_ceil)
        tp = np.where(np.isfinite(tp), tp, 0.0)
        ppm = np.where(floor, wp.floor_px_per_m, wp.ceiling_px_per_m)
        period = np.where(floor[..., None], np.array(world.floor_period_px, float), np.array(world.ceiling_period_px, float))
        origin = np.where(floor[..., None], world.floor_origin, world.ceiling_origin)
        px = np.mod((x + tp * d2[..., 0]) * ppm, period[..., 0])
        py = np.mod(-(y + tp * d2[..., 1]) * ppm, period[..., 1])
        rows = slice(v0, v0 + len(vv))
        map_x[rows] = np.where(wall, wx, origin[..., 0] + px - 0.5)
        map_y[rows] = np.where(wall, wy, origin[..., 1] + py - 0.5)
    return cv2.remap(world.atlas, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _stats(runs_s: list[float]) -> dict[str, float]:
    ms = sorted(1e3 * r for r in runs_s)
    q1, med, q3 = statistics.quantiles(ms, n=4, method="inclusive") if len(ms) > 1 else (ms[0],) * 3
    return {"median_ms": med, "iqr_ms": q3 - q1, "p90_ms": ms[int(0.9 * (len(ms) - 1))],
            "max_ms": ms[-1], "frames": len(ms), "fps_median": 1e3 / med}


_CPU: dict[int, list[float]] = {}


def _time_each(fn, items) -> list[float]:
    """Wall-clock seconds per call; the process CPU seconds per call go to ``_CPU[id(list)]``
    (on a shared machine the CPU time shows the cost without the waiting)."""
    out, cpu = [], []
    for it in items:
        c0, t0 = time.process_time(), time.perf_counter()
        fn(it)
        out.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    _CPU[id(out)] = cpu
    return out


def _cpu_ms(runs: list[float]) -> float:
    return 1e3 * statistics.median(_CPU[id(runs)])


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=200, help="keyframes of the office route rendered (default 200)")
    ap.add_argument("--naive-frames", type=int, default=10, help="frames of the per-pixel baseline (default 10)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)

    t0 = time.perf_counter()
    world = office_world(args.seed)
    t_world = time.perf_counter() - t0
    motion = plan_motion(build_route("office"))
    times = keyframe_times(motion, 0.1, math.radians(10.0))
    idx = np.linspace(0, len(times) - 1, args.frames).round().astype(int)
    poses = motion.poses_at(times[idx])
    cam = ForwardCameraModel()
    fwd = ForwardRenderer(world, cam, ForwardRenderParams(), np.random.default_rng(args.seed))
    for p in poses[:5]:
        fwd.render(p)  # warm-up
    column = _time_each(fwd.render, poses)
    cast = _time_each(fwd.cast, poses)
    maps = _time_each(fwd.maps, poses)
    mx, my, _ = fwd.maps(poses[0])
    remap = _time_each(lambda _: cv2.remap(world.atlas, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), poses)

    # Baseline 1: the per-pixel raycaster, checked against the column raycaster at level 0.
    flat = ForwardRenderer(world, cam, ForwardRenderParams(noise_sigma=0.0, mipmap=False))
    sel = poses[np.linspace(0, len(poses) - 1, args.naive_frames).round().astype(int)]
    naive = _time_each(lambda p: naive_render(world, cam, p), sel)
    diffs = [np.abs(naive_render(world, cam, p).astype(int) - flat.render_clean(p).astype(int)) for p in sel]
    agree = float(np.mean([np.mean(d <= 2) for d in diffs]))

    # Baseline 2: the floor camera at the same poses (default camera, blur and noise).
    floor_r = FloorRenderer(Floor.default(seed=args.seed), FloorCameraModel.default(), RenderParams(),
                            np.random.default_rng(args.seed))
    for p in poses:  # warm pass: every floor tile these poses need is generated and cached
        floor_r.render(p, 0.3, 0.0, 0.0)
    floor_t = _time_each(lambda p: floor_r.render(p, 0.3, 0.0, 0.0), poses)

    col, nav, flo = _stats(column), _stats(naive), _stats(floor_t)
    per_sim_s = 30 * flo["median_ms"] / 1e3 + 10 * col["median_ms"] / 1e3
    per_sim_cpu_s = 30 * _cpu_ms(floor_t) / 1e3 + 10 * _cpu_ms(column) / 1e3
    print(f"640x480 forward frames, one core (cv2.setNumThreads(1)), {args.frames} office-route keyframes; "
          f"world built in {t_world:.1f} s ({world.n_walls} walls, atlas {world.atlas.shape[1]}x{world.atlas.shape[0]})")
    print_table(
        ["renderer", "frames", "ms med", "ms IQR", "ms p90", "fps med", "x column", "CPU ms med"],
        [["column raycaster (default)", col["frames"], round(col["median_ms"], 2), round(col["iqr_ms"], 2),
          round(col["p90_ms"], 2), round(col["fps_median"]), 1.0, round(_cpu_ms(column), 2)],
         ["  stage: cast 640 rays", len(cast), round(_stats(cast)["median_ms"], 2), round(_stats(cast)["iqr_ms"], 2),
          round(_stats(cast)["p90_ms"], 2), "", "", round(_cpu_ms(cast), 2)],
         ["  stage: atlas maps", len(maps), round(_stats(maps)["median_ms"], 2), round(_stats(maps)["iqr_ms"], 2),
          round(_stats(maps)["p90_ms"], 2), "", "", round(_cpu_ms(maps), 2)],
         ["  stage: remap", len(remap), round(_stats(remap)["median_ms"], 2), round(_stats(remap)["iqr_ms"], 2),
          round(_stats(remap)["p90_ms"], 2), "", "", round(_cpu_ms(remap), 2)],
         ["baseline: per-pixel raycaster", nav["frames"], round(nav["median_ms"], 1), round(nav["iqr_ms"], 1),
          round(nav["p90_ms"], 1), round(nav["fps_median"], 1), round(nav["median_ms"] / col["median_ms"], 1),
          round(_cpu_ms(naive), 1)],
         ["baseline: floor camera (default)", flo["frames"], round(flo["median_ms"], 2), round(flo["iqr_ms"], 2),
          round(flo["p90_ms"], 2), round(flo["fps_median"]), round(flo["median_ms"] / col["median_ms"], 2),
          round(_cpu_ms(floor_t), 2)]],
    )
    print(f"\nper-pixel vs column raycaster (full-res level, no noise): {100 * agree:.2f} % of pixels within 2 grey levels")
    print(f"one simulated second, floor camera 30 Hz + forward camera 10 Hz: {per_sim_s:.2f} core-s "
          f"({1 / per_sim_s:.1f}x real time on one core); by CPU time {per_sim_cpu_s:.2f} core-s")
    payload = {
        "benchmark": "forward_render", "machine": machine_info(),
        "versions": {"opencv": cv2.__version__, "scikit-image": skimage.__version__, "numpy": np.__version__},
        "settings": {"threads": 1, "frames": args.frames, "naive_frames": args.naive_frames, "seed": args.seed,
                     "image": [640, 480], "camera_height_m": cam.height_m, "fx_px": cam.intrinsics.fx_px},
        "world": {"build_s": t_world, "walls": world.n_walls, "atlas": list(world.atlas.shape)},
        "column": col, "stages": {"cast": _stats(cast), "maps": _stats(maps), "remap": _stats(remap)},
        "cpu_median_ms": {"column": _cpu_ms(column), "cast": _cpu_ms(cast), "maps": _cpu_ms(maps),
                          "remap": _cpu_ms(remap), "naive": _cpu_ms(naive), "floor": _cpu_ms(floor_t)},
        "naive_per_pixel": nav, "naive_agreement_within_2": agree, "floor_camera": flo,
        "core_s_per_sim_s_floor30_forward10": per_sim_s, "cpu_s_per_sim_s_floor30_forward10": per_sim_cpu_s,
    }
    print(f"\nwrote {write_json(args.out, payload)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
