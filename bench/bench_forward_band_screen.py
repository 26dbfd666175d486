"""The band fallback's screen: what it saves of the verification's time and what it costs in
accepted fallbacks, on the detector's own verifications.

The planar verification's bounded fallback (``VerifyParams.fallback_band_px``: five-point
RANSAC, at most 200 samples among the matches within 10 px of the level motion) is the tail
of the time per forward image, and it mostly fails (``docs/forward.md``, "The p99 in the
daemon now"). ``VerifyParams.fallback_screen = "usac"`` runs OpenCV's USAC (the same test and
iteration bound, a cheaper sample) in the band first and refuses the candidate when its best
essential matrix has fewer than ``min_inliers`` inliers over all the matches in front of both
cameras; otherwise RANSAC runs as without the screen and decides. So the screen can only
refuse: every acceptance is RANSAC's.

The detector runs once per sequence with the screen off and every
:func:`robotd.forward.verify.verify_pair` call it makes is recorded (the past image as
stored, the new image, the parameters, the camera matrix): the real corridor of
``rtabmap_samples`` with the default detector (no pose), and the virtual office route
(``--dir``, as ``bench/bench_forward_ablation.py`` writes it) with the fused pose, the
detector as the daemon runs it (:func:`robotd.forward.detector.daemon_params`). Each
recorded call is then verified with the screen off and on, alternating which goes first,
``--rounds`` times; the thread's CPU time of each call (``time.thread_time``), of the band's
general search and of the screen (timed around their calls), the minimum over the rounds.

Reported per sequence: calls, band searches (the general search in the band ran without
the screen), of them accepted without the screen, screened out, and accepted without the
screen but refused with it (recall lost: the screen missed a consensus RANSAC found);
every outcome the same otherwise (digest of each verification, with the screen's own flag
left out). Time: the band's part per band search (without: RANSAC; with: the screen plus
RANSAC where it passed), per call and per verifying image (the sum of its calls; median,
p99, max), each as a ratio with / without over the same calls in the same run.

Run: ``PYTHONPATH=. .venv/bin/python bench/bench_forward_band_screen.py --dir /tmp/office``
(about 10 minutes on a loaded 2-core machine); ``--page FILE.json`` rewrites
``docs/benchmarks/forward_band_screen.md`` from a result.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.bench_forward_ablation import DATA, extract_timed, office_fused_odometry, office_sequence
    from bench.common import git_commit, machine_info, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from bench_forward_ablation import DATA, extract_timed, office_fused_odometry, office_sequence  # type: ignore[no-redef]
    from common import git_commit, machine_info, write_json, write_page

import robotd.forward.detector as detector_module
import robotd.forward.verify as verify_module
from robotd.forward import ForwardDetector, method_params
from robotd.forward.detector import daemon_params
from robotd.forward.verify import camera_matrix_guess
from robotd.io.sequence import list_images, read_image

PAGE = Path(__file__).resolve().parent.parent / "docs" / "benchmarks" / "forward_band_screen.md"
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_band_screen.json"
SCREEN = "usac"


def record(name: str, folder: Path, truth_path: Path, odometry: tuple[np.ndarray, np.ndarray] | None,
           daemon: bool) -> list[tuple[int, Any, Any, Any, Any]]:
    """Every ``verify_pair`` call of one run of the detector, screen off: ``(image, old, new,
    params, camera_matrix)``."""
    files = list_images(folder, exclude=(truth_path,))
    images = [read_image(p) for p in files]
    h, w = images[0].shape[:2]
    k = camera_matrix_guess(w, h, 525.0 if name == "office" else None)
    params = method_params("default")
    params = replace(params, verify=replace(params.verify, fallback_screen=None))
    if daemon:
        params = daemon_params(params)
    det = ForwardDetector(params, camera_matrix=k)
    calls: list[tuple[int, Any, Any, Any, Any]] = []
    inner = detector_module.verify_pair
    image = [0]

    def hook(old: Any, new: Any, vp: Any, km: Any) -> Any:
        calls.append((image[0], old, new, vp, km))
        return inner(old, new, vp, km)

    detector_module.verify_pair = hook  # type: ignore[assignment]
    try:
        for t, (fe, fs) in enumerate(extract_timed(params.features, images)):
            image[0] = t
            if odometry is None:
                det.process_features(fe, fs)
            else:
                det.process_features(fe, fs, odometry[0][t], odometry[1][t])
    finally:
        detector_module.verify_pair = inner
    return calls


def _digest(v: Any) -> str:
    """Everything a verification holds but the screen's own flag."""
    h = hashlib.sha256()
    for name in ("accepted", "reason", "n_matches", "n_inliers", "n_plane_inliers", "planar", "support_area",
                 "range_m", "n_floor_points", "sigma_bearing_rad", "sigma_yaw_rad", "noise_px", "planarity_chi2",
                 "level_yaw_rad"):
        h.update(repr(getattr(v, name)).encode())
    for name in ("rotation", "translation_dir"):
        x = getattr(v, name)
        h.update(b"-" if x is None else np.asarray(x, np.float64).tobytes())
    return h.hexdigest()


class _Timers:
    """Thread CPU time around the band's general search and the screen (patched into
    :mod:`robotd.forward.verify` while the calls are replayed)."""

    def __init__(self) -> None:
        self.band_s = 0.0
        self.band_ran = False
        self.screen_s = 0.0
        self.screen_ran = False
        self._general = verify_module._general_motion
        self._screen = verify_module._screen_passes

    def reset(self) -> None:
        self.band_s = self.screen_s = 0.0
        self.band_ran = self.screen_ran = False

    def __enter__(self) -> _Timers:
        def general(*args: Any, **kwargs: Any) -> Any:
            band = kwargs.get("half_inliers", True) is False
            t0 = time.thread_time()
            out = self._general(*args, **kwargs)
            if band:
                self.band_s += time.thread_time() - t0
                self.band_ran = True
            return out

        def screen(*args: Any, **kwargs: Any) -> Any:
            t0 = time.thread_time()
            out = self._screen(*args, **kwargs)
            self.screen_s += time.thread_time() - t0
            self.screen_ran = True
            return out

        verify_module._general_motion = general  # type: ignore[assignment]
        verify_module._screen_passes = screen  # type: ignore[assignment]
        return self

    def __exit__(self, *exc: object) -> None:
        verify_module._general_motion = self._general  # type: ignore[assignment]
        verify_module._screen_passes = self._screen  # type: ignore[assignment]


def replay(calls: list[tuple[int, Any, Any, Any, Any]], rounds: int, screen: str = SCREEN) -> dict[str, Any]:
    """Each call verified without and with the screen, alternating, ``rounds`` times."""
    n = len(calls)
    t_call = {False: np.full((rounds, n), np.inf), True: np.full((rounds, n), np.inf)}
    t_band = {False: np.zeros((rounds, n)), True: np.zeros((rounds, n))}
    outcome: dict[bool, list[Any]] = {False: [None] * n, True: [None] * n}
    band_ran = np.zeros(n, bool)
    screened = np.zeros(n, bool)
    with _Timers() as timers:
        for r in range(rounds):
            for i, (_, old, new, vp, km) in enumerate(calls):
                order = (False, True) if (i + r) % 2 == 0 else (True, False)
                for on in order:
                    p = replace(vp, fallback_screen=screen if on else None)
                    timers.reset()
                    t0 = time.thread_time()
                    v = verify_module.verify_pair(old, new, p, km)
                    t_call[on][r, i] = time.thread_time() - t0
                    t_band[on][r, i] = timers.band_s + timers.screen_s
                    if r == 0:
                        outcome[on][i] = v
                        if not on:
                            band_ran[i] = timers.band_ran
                        else:
                            screened[i] = v.screened
    images = np.array([c[0] for c in calls])
    off_ok = np.array([v.accepted for v in outcome[False]])
    on_ok = np.array([v.accepted for v in outcome[True]])
    same = np.array([_digest(a) == _digest(b) for a, b in zip(outcome[False], outcome[True], strict=True)])
    # Where the screen refused, the outcome is the guided search's refusal; elsewhere the same.
    differ_not_screened = int(np.sum(~same & ~screened))
    call_ms = {on: 1e3 * t_call[on].min(axis=0) for on in (False, True)}
    band_ms = {on: 1e3 * t_band[on].min(axis=0) for on in (False, True)}
    per_image = {}
    for on in (False, True):
        sums: dict[int, float] = {}
        for img, t in zip(images, call_ms[on], strict=True):
            sums[int(img)] = sums.get(int(img), 0.0) + float(t)
        per_image[on] = np.array([sums[i] for i in sorted(sums)])
    b = band_ran

    def stats(x: np.ndarray) -> dict[str, float]:
        if not len(x):
            return {"median": float("nan"), "p99": float("nan"), "max": float("nan"), "total": 0.0}
        return {"median": float(np.median(x)), "p99": float(np.percentile(x, 99)), "max": float(np.max(x)),
                "total": float(np.sum(x))}

    res: dict[str, Any] = {
        "calls": n, "images_verified": len(per_image[False]),
        "band_searches": int(b.sum()), "band_accepted": int(np.sum(b & off_ok)),
        "screened_out": int(screened.sum()), "accepted_lost": int(np.sum(off_ok & ~on_ok)),
        "accepted_new": int(np.sum(on_ok & ~off_ok)), "differ_where_not_screened": differ_not_screened,
        "band_ms": {"without": stats(band_ms[False][b]), "with": stats(band_ms[True][b])},
        "call_ms": {"without": stats(call_ms[False]), "with": stats(call_ms[True])},
        "image_ms": {"without": stats(per_image[False]), "with": stats(per_image[True])},
        "band_searches_accepted_ms": {"without": stats(band_ms[False][b & off_ok]),
                                      "with": stats(band_ms[True][b & off_ok])},
    }
    res["ratios"] = {f"{part}_{k}": (res[part]["with"][k] / res[part]["without"][k]
                                     if res[part]["without"][k] else float("nan"))
                     for part in ("band_ms", "call_ms", "image_ms") for k in ("median", "p99", "max", "total")}
    return res


def page(res: dict[str, Any]) -> list[str]:
    m = res["machine"]
    lines = [
        "# The band fallback's screen: time and accepted fallbacks on the detector's own verifications",
        "",
        "Generated by `bench/bench_forward_band_screen.py` from its JSON (do not edit by hand; what is measured: "
        "the bench's docstring and [docs/forward.md](../forward.md), \"The p99 in the daemon now\"). Every "
        "`verify_pair` call of one run of the detector (screen off), verified again without and with "
        "`VerifyParams.fallback_screen = \"usac\"`, alternating, the minimum thread CPU time over "
        f"{res['rounds']} rounds; ratios are with / without over the same calls in the same run.",
        "",
        f"Machine: {m.get('cpu_model', '?')}, {m.get('cpu_count', '?')} CPUs, OpenCV {m.get('opencv', '?')}; "
        f"load average {', '.join(f'{x:.1f}' for x in res['load_avg'])} at the end. Commit {res.get('commit')}.",
        "",
        "| sequence | calls (images) | band searches | of them accepted | screened out | accepted lost | "
        "other outcomes changed |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, s in res["sequences"].items():
        lines.append(f"| {name} | {s['calls']} ({s['images_verified']}) | {s['band_searches']} | "
                     f"{s['band_accepted']} | {s['screened_out']} | {s['accepted_lost']} | "
                     f"{s['differ_where_not_screened'] + s['accepted_new']} |")
    lines += ["", "CPU ms, without -> with the screen (ratio):", "",
              "| sequence | part | median | p99 | max | total |", "|---|---|---:|---:|---:|---:|"]
    for name, s in res["sequences"].items():
        for part, label in (("band_ms", "band fallback, per band search"), ("call_ms", "verification, per call"),
                            ("image_ms", "verification, per verifying image")):
            cells = []
            for k in ("median", "p99", "max", "total"):
                a, b = s[part]["without"][k], s[part]["with"][k]
                cells.append(f"{a:.1f} -> {b:.1f} ({s['ratios'][f'{part}_{k}']:.2f})")
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
    return lines


def _recorded(folder: Path | None, name: str, make: Any) -> list[tuple[int, Any, Any, Any, Any]]:
    """``make()``'s calls, pickled in ``folder`` (read from there when present)."""
    if folder is None:
        return make()
    path = folder / f"{name}.pkl"
    if path.exists():
        with path.open("rb") as f:
            return pickle.load(f)
    calls = make()
    folder.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        pickle.dump(calls, f)
    return calls


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, required=False, default=None, help="folder of the virtual office sequence")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--only", choices=("rtabmap_samples", "office"), default=None)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--calls", type=Path, default=None, metavar="DIR",
                    help="keep each sequence's recorded calls here (pickled) and reuse them when there")
    ap.add_argument("--page", type=Path, default=None, metavar="JSON",
                    help="rewrite docs/benchmarks/forward_band_screen.md from a result and exit")
    args = ap.parse_args(argv)
    if args.page is not None:
        write_page(PAGE, page(json.loads(args.page.read_text(encoding="utf-8"))))
        return 0
    if args.only != "rtabmap_samples" and args.dir is None:
        ap.error("--dir is needed for the office route")
    one_blas_thread()  # as robotd's command line runs the daemon
    import cv2

    result: dict[str, Any] = {"machine": {**machine_info(), "opencv": cv2.__version__}, "commit": git_commit(),
                              "rounds": args.rounds, "sequences": {}}
    if args.only in (None, "rtabmap_samples"):
        folder = args.data / "forward" / "rtabmap_samples"
        calls = _recorded(args.calls, "rtabmap_samples",
                          lambda: record("rtabmap_samples", folder, folder / "ground_truth.bmp", None, daemon=False))
        result["sequences"]["rtabmap_samples (default)"] = replay(calls, args.rounds)
        print(json.dumps(result["sequences"]["rtabmap_samples (default)"], indent=1), flush=True)
    if args.only in (None, "office"):
        folder = office_sequence(args.dir)
        calls = _recorded(args.calls, "office", lambda: record("office", folder, folder / "gt.npy",
                                                              office_fused_odometry(folder), daemon=True))
        result["sequences"]["office, fused pose (as the daemon runs it)"] = replay(calls, args.rounds)
        print(json.dumps(result["sequences"]["office, fused pose (as the daemon runs it)"], indent=1), flush=True)
    result["load_avg"] = list(os.getloadavg())
    print(f"wrote {write_json(args.out, result)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
