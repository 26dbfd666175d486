"""Would compiled code make the floor describe fast enough? The default extraction's two
kinds of remaining work, each as one numba kernel, against the code as it is, same run.

The floor describe's remaining time is per-candidate arithmetic (the repeat check's pool
of raw descriptors) and per-pixel passes at the half resolution (the pooled orientation
maps), each a few large OpenCV and numpy calls (docs/performance.md). This measures what
a JIT compiler (numba, ``cache=True``) gives for them, and what it costs the daemon:

* **per candidate**: :func:`robotd.floor.keypoints.raw_descriptors` of the repeat check's
  pool (bilinear sampling of the two pooled maps at 16 cells, turning to the keypoint's
  orientation, normalising, clipping, renormalising) as one loop over the candidates;
* **per pixel**: the pooled maps' channels (gradient, angle level, the split table,
  product with the magnitude, 2 x 2 area halving) as one pass over the pixels, then the
  same two Gaussians as ``_pooled_orientation_maps``;
* the default extraction and OpenCV ORB (500) on the same frames, for scale;
* what the daemon would pay at every start: resident memory and time to import numba and
  load the two kernels from their cache, in a child process that first imports robotd's
  descriptor (the first child compiles and fills the cache; the second loads it).

The kernels are timing bounds, not replacements: their arithmetic is float and not
OpenCV's (fixed-point bilinear weights, its own angle), so their values agree to rounding
(the largest differences are reported), not bit for bit.

Needs numba, which robotd does not depend on: install it outside the project's
environment (``pip install --target DIR numba``) and put ``DIR`` on ``PYTHONPATH``. One
thread (OpenCV and numpy's BLAS, :func:`floor_common.one_thread`), CPU time of the calling
thread, the methods interleaved frame by frame.

Run from the repo root: ``.venv/bin/python bench/bench_describe_compiled.py [--recording
MCAP] [--out DIR] [--doc docs/benchmarks/describe_compiled.md]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

try:
    from bench.common import REPO_ROOT, print_table, write_json, write_page
    from bench.floor_common import add_common_args, header, load_average, log, one_thread, r
except ImportError:  # run as a script: bench/ is on sys.path
    from common import REPO_ROOT, print_table, write_json, write_page
    from floor_common import add_common_args, header, load_average, log, one_thread, r

from robotd.floor import keypoints as kp
from robotd.floor.descparams import ExtractParams

MODE = 4  # as the daemon describes keyframes


def kernels() -> tuple[Any, Any]:
    """The two numba kernels (compiled on first use, cached in ``NUMBA_CACHE_DIR``)."""
    from numba import njit

    @njit(cache=True, fastmath=True, boundscheck=False)  # type: ignore[misc]
    def raw_fused(xy: np.ndarray, ang: np.ndarray, p0: np.ndarray, p1: np.ndarray, cell: float,
                  out: np.ndarray) -> None:
        n = xy.shape[0]
        h, w = p0.shape[0], p0.shape[1]
        smp = np.empty(8, np.float32)
        for c in range(n):
            x0 = (xy[c, 0] - 0.5) * 0.5
            y0 = (xy[c, 1] - 0.5) * 0.5
            a = ang[c]
            cs, sn = math.cos(a), math.sin(a)
            ab = a * (8.0 / (2 * math.pi))
            a0 = int(ab) & 7
            f = ab - math.floor(ab)
            s2 = 0.0
            for gy in range(4):
                for gx in range(4):
                    u, v = gx - 1.5, gy - 1.5
                    mx = ((x0 + cell * (cs * u - sn * v)) - 0.5) * 0.5  # pixel centres of the halved maps
                    my = ((y0 + cell * (sn * u + cs * v)) - 0.5) * 0.5
                    ix, iy = int(math.floor(mx)), int(math.floor(my))
                    fx, fy = mx - ix, my - iy
                    smp[:] = 0.0
                    for dy in range(2):
                        yy = iy + dy
                        yy = -yy if yy < 0 else (2 * h - 2 - yy if yy >= h else yy)  # reflect 101
                        wy = fy if dy == 1 else 1.0 - fy
                        for dx in range(2):
                            xx = ix + dx
                            xx = -xx if xx < 0 else (2 * w - 2 - xx if xx >= w else xx)
                            wgt = wy * (fx if dx == 1 else 1.0 - fx)
                            for ch in range(4):
                                smp[ch] += wgt * p0[yy, xx, ch]
                                smp[ch + 4] += wgt * p1[yy, xx, ch]
                    base = (gy * 4 + gx) * 8
                    for j in range(8):
                        val = smp[(a0 + j) & 7] * (1 - f) + smp[(a0 + j + 1) & 7] * f
                        out[c, base + j] = val
                        s2 += val * val
            inv = 1.0 / max(math.sqrt(s2), 1e-12)
            s2 = 0.0
            for e in range(128):
                val = min(out[c, e] * inv, 0.2)
                out[c, e] = val
                s2 += val * val
            inv = 1.0 / max(math.sqrt(s2), 1e-12)
            for e in range(128):
                out[c, e] *= inv

    @njit(cache=True, fastmath=True, boundscheck=False)  # type: ignore[misc]
    def channels_fused(g: np.ndarray, table: np.ndarray, out: np.ndarray) -> None:
        h, w = g.shape
        out[:] = 0.0
        scale = np.float32(256.0 / (2 * math.pi))
        for y in range(h):
            ym = y - 1 if y > 0 else 1
            yp = y + 1 if y < h - 1 else h - 2
            oy = y >> 1
            for x in range(w):
                xm = x - 1 if x > 0 else 1
                xp = x + 1 if x < w - 1 else w - 2
                gx = g[y, xp] - g[y, xm]
                gy = g[yp, x] - g[ym, x]
                mag = math.sqrt(gx * gx + gy * gy)
                a = math.atan2(gy, gx)
                if a < 0:
                    a += np.float32(2 * math.pi)
                q = int(a * scale) & 255
                ox = x >> 1
                for d in range(8):
                    out[d >> 2, oy, ox, d & 3] += np.float32(0.25) * mag * table[(q - 32 * d) & 255]

    return raw_fused, channels_fused


def startup_child() -> None:
    """In a child process: resident memory and time to import numba and load the kernels."""
    def status() -> dict[str, int]:
        with open("/proc/self/status") as f:
            return {ln.split(":")[0]: int(ln.split()[1]) for ln in f if ln.startswith(("VmRSS", "RssAnon", "RssFile"))}

    import robotd.floor.descriptor  # noqa: F401  (what the daemon has loaded before)

    before = status()
    t0 = time.perf_counter()
    raw_fused, channels_fused = kernels()
    raw_fused(np.zeros((1, 2), np.float32) + 20, np.zeros(1, np.float32), np.zeros((40, 40, 4), np.float32),
              np.zeros((40, 40, 4), np.float32), 6.0, np.zeros((1, 128), np.float32))
    channels_fused(np.zeros((8, 8), np.float32), np.zeros(256, np.float32), np.zeros((2, 4, 4, 4), np.float32))
    seconds = time.perf_counter() - t0
    after = status()
    print(json.dumps({"seconds": seconds, "kb_before": before, "kb_after": after}))


def startup(cache: Path) -> list[dict[str, Any]]:
    """Two children: the first compiles into ``cache``, the second loads from it."""
    out = []
    for run in ("compile", "from cache"):
        env = {**os.environ, "NUMBA_CACHE_DIR": str(cache),
               "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), os.environ.get("PYTHONPATH", "")])}
        p = subprocess.run([sys.executable, __file__, "--startup-child"], env=env, check=True,
                           capture_output=True, text=True)
        res = json.loads(p.stdout.strip().splitlines()[-1])
        b, a = res["kb_before"], res["kb_after"]
        out.append({"run": run, "seconds": r(res["seconds"], 3),
                    "rss_mb_before": r(b["VmRSS"] / 1024, 1), "rss_mb_added": r((a["VmRSS"] - b["VmRSS"]) / 1024, 1),
                    "anon_mb_added": r((a["RssAnon"] - b["RssAnon"]) / 1024, 1),
                    "file_mb_added": r((a["RssFile"] - b["RssFile"]) / 1024, 1)})
    return out


def office_frames(recording: Path, count: int) -> list[np.ndarray]:
    """``count`` grey floor frames spread over the recorded drive."""
    from drivers.recording.reader import RecordingReader
    from robotd.base.messages import Frame

    with RecordingReader(recording) as rd:
        n_all = sum(1 for _t, msg in rd.messages() if isinstance(msg, Frame) and msg.camera == "floor")
    at = set(np.linspace(0, n_all - 1, count).astype(int).tolist())
    out = []
    with RecordingReader(recording) as rd:
        i = 0
        for _t, msg in rd.messages():
            if not (isinstance(msg, Frame) and msg.camera == "floor"):
                continue
            if i in at:
                img = msg.image
                out.append(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img)
            i += 1
    return out


def measure(frames: list[np.ndarray], repeats: int) -> dict[str, Any]:
    """Interleaved per-frame timings (median of ``repeats`` per frame) and value differences."""
    from robotd.floor.descriptor import extract, shipped_learned

    raw_fused, channels_fused = kernels()
    params, learned = ExtractParams(), shipped_learned()
    orb = cv2.ORB_create(nfeatures=500)
    table = kp._level_table()
    sigma = math.sqrt(max(params.pool_sigma_px**2 - 1.0, 0.25)) / 2
    ksize = 2 * int(math.ceil(2 * sigma)) + 1
    times: dict[str, list[float]] = {k: [] for k in ("extract", "orb", "raw_opencv", "raw_numba",
                                                     "maps_opencv", "maps_numba")}
    raw_diff, map_diff = 0.0, 0.0
    for j, img in enumerate(frames):
        work = kp.working(img, params)
        h2, w2 = work.shape[0] // 2, work.shape[1] // 2
        ws = kp.workspace(h2, w2)
        c = kp.candidates(work, params, learned, ws)
        k = min(params.repeat_pool, len(c.xy))
        xy, ang = np.ascontiguousarray(c.xy[:k]), np.ascontiguousarray(c.angle[:k])
        g1 = cv2.GaussianBlur(cv2.resize(work, (w2, h2), interpolation=cv2.INTER_AREA).astype(np.float32), (0, 0),
                              params.detect_sigma_px)
        raw_out = np.empty((k, 128), np.float32)
        ch = np.empty((2, h2 // 2, w2 // 2, 4), np.float32)

        def maps_numba() -> tuple[np.ndarray, np.ndarray]:
            channels_fused(g1, table, ch)
            return cv2.GaussianBlur(ch[0], (ksize, ksize), sigma), cv2.GaussianBlur(ch[1], (ksize, ksize), sigma)

        calls = {"extract": lambda: extract(img, MODE), "orb": lambda: orb.detectAndCompute(img, None),
                 "raw_opencv": lambda: kp.raw_descriptors(c, k, params, ws),
                 "raw_numba": lambda: raw_fused(xy, ang, c.pooled[0], c.pooled[1], params.cell_px, raw_out),
                 "maps_opencv": lambda: kp._pooled_orientation_maps(g1, sigma, ws, False, ws.half()),
                 "maps_numba": maps_numba}
        if j == 0:
            for fn in calls.values():
                fn()
        per: dict[str, list[float]] = {name: [] for name in calls}
        for _ in range(repeats):
            for name, fn in calls.items():  # interleaved: each sees the same load
                t0 = time.thread_time()
                fn()
                per[name].append(time.thread_time() - t0)
        for name in calls:
            times[name].append(float(np.median(per[name])))
        c = kp.candidates(work, params, learned, ws)  # the maps above overwrote the workspace's
        ref = kp.raw_descriptors(c, k, params, ws).copy()
        raw_fused(xy, ang, c.pooled[0], c.pooled[1], params.cell_px, raw_out)
        raw_diff = max(raw_diff, float(np.abs(ref - raw_out).max()))
        a = kp._pooled_orientation_maps(g1, sigma, ws, False, ws.half())
        b = maps_numba()
        map_diff = max(map_diff, max(float(np.abs(a[i] - b[i]).max() / max(np.abs(a[i]).max(), 1e-12))
                                     for i in range(2)))
    med = {name: 1e3 * float(np.median(v)) for name, v in times.items()}
    ratio = {"raw": float(np.median(np.array(times["raw_numba"]) / np.array(times["raw_opencv"]))),
             "maps": float(np.median(np.array(times["maps_numba"]) / np.array(times["maps_opencv"]))),
             "extract_over_orb": float(np.median(np.array(times["extract"]) / np.array(times["orb"])))}
    return {"frames": len(frames), "median_ms": {k: r(v, 3) for k, v in med.items()},
            "ratio_per_frame_median": {k: r(v, 3) for k, v in ratio.items()},
            "raw_max_abs_diff": raw_diff, "maps_max_rel_diff": map_diff}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_common_args(ap)
    ap.add_argument("--recording", type=Path, default=None,
                    help="office drive MCAP (default: the one ./dev bench daemon caches, recorded if missing)")
    ap.add_argument("--frames", type=int, default=40, help="office frames timed (default 40)")
    ap.add_argument("--repeats", type=int, default=3, help="timed calls per frame and method (default 3)")
    ap.add_argument("--doc", type=Path, default=None, help="also write the Markdown page of the run here")
    ap.add_argument("--startup-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.startup_child:
        startup_child()
        return 0
    try:
        import numba
    except ImportError:
        print("bench_describe_compiled: numba is not installed (robotd does not depend on it): "
              "pip install --target DIR numba, then PYTHONPATH=DIR", file=sys.stderr)
        return 2
    load_start = load_average()
    one_thread()
    try:
        from bench.bench_floor_descriptor import office_recording
    except ImportError:
        from bench_floor_descriptor import office_recording
    recording = office_recording(args)
    log(f"office drive: {recording}; load average {load_start}")
    frames = office_frames(recording, args.frames)
    with tempfile.TemporaryDirectory() as tmp:
        start = startup(Path(tmp) / "numba-cache")
        os.environ["NUMBA_CACHE_DIR"] = str(Path(tmp) / "numba-cache")
        res = measure(frames, args.repeats)
    payload = header("describe_compiled", load_start=load_start, settings={
        "mode": MODE, "frames": args.frames, "repeats": args.repeats, "threads": 1, "numba": numba.__version__,
        "timing": "CPU time of the thread; per frame the median of repeats, methods interleaved"})
    payload["timing"] = res
    payload["startup"] = start
    out = write_json(args.out / "describe_compiled.json", payload)
    print_table(["part", "numpy / OpenCV ms", "numba ms", "numba / numpy, per frame"],
                [["raw descriptors (1,000)", res["median_ms"]["raw_opencv"], res["median_ms"]["raw_numba"],
                  res["ratio_per_frame_median"]["raw"]],
                 ["pooled maps", res["median_ms"]["maps_opencv"], res["median_ms"]["maps_numba"],
                  res["ratio_per_frame_median"]["maps"]]])
    print(f"extract {res['median_ms']['extract']} ms, ORB {res['median_ms']['orb']} ms "
          f"(extract / ORB {res['ratio_per_frame_median']['extract_over_orb']})")
    print_table(["start-up", "s", "RSS before MB", "RSS added MB", "anon MB", "file MB"],
                [[s["run"], s["seconds"], s["rss_mb_before"], s["rss_mb_added"], s["anon_mb_added"],
                  s["file_mb_added"]] for s in start])
    print(f"wrote {out}")
    if args.doc is not None:
        write_page(args.doc, markdown(payload))
        print(f"wrote {args.doc}")
    return 0


def markdown(p: dict) -> list[str]:
    """The page of a run."""
    m, t = p["machine"], p["timing"]
    ms, ratio = t["median_ms"], t["ratio_per_frame_median"]
    lines = [
        "# The floor describe's remaining work as compiled code (numba)",
        "",
        f"Generated by `bench/bench_describe_compiled.py` (numba {p['settings']['numba']}) on "
        f"{m.get('platform')}, {m.get('cpu_count')} CPUs, load average {m.get('load_average_start')} at the start, "
        f"{m.get('load_average_end')} at the end; {t['frames']} frames of the recorded office drive, mode "
        f"{p['settings']['mode']}, one thread, CPU time, the methods interleaved frame by frame.",
        "",
        "| part | numpy / OpenCV, ms | numba kernel, ms | numba / numpy (median per frame) |",
        "|---|---:|---:|---:|",
        f"| raw descriptors of the repeat check's pool (per candidate) | {ms['raw_opencv']} | {ms['raw_numba']} "
        f"| {ratio['raw']} |",
        f"| pooled orientation maps (per pixel, with their two Gaussians) | {ms['maps_opencv']} | "
        f"{ms['maps_numba']} | {ratio['maps']} |",
        "",
        f"The whole default extraction on the same frames: {ms['extract']} ms; OpenCV ORB (500): {ms['orb']} ms "
        f"(extraction / ORB, median per frame: {ratio['extract_over_orb']}). The kernels' values against the "
        f"code's: raw descriptors within {t['raw_max_abs_diff']:.1e}, maps within {t['maps_max_rel_diff']:.1e} "
        "of their largest value (float arithmetic, not OpenCV's fixed-point sampling: a timing bound).",
        "",
        "What the daemon would pay at every start (a child process with robotd's descriptor imported, numba "
        "imported and both kernels called once):",
        "",
        "| run | seconds | RSS before, MB | RSS added, MB | of it anonymous | of it file-backed |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    lines += [f"| {s['run']} | {s['seconds']} | {s['rss_mb_before']} | {s['rss_mb_added']} | {s['anon_mb_added']} "
              f"| {s['file_mb_added']} |" for s in p["startup"]]
    return lines + [""]


if __name__ == "__main__":
    sys.exit(main())
