"""The forward verification's CPU time on the office route's own verifications: the current
code against a baseline revision, the same outcomes required.

The default detector runs once over the virtual office route without a pose (1139 images
at 640x480, its features extracted once) and every :func:`robotd.forward.verify.verify_pair`
call it makes is recorded: the past image as the detector stores it, the new image, the
parameters and the camera matrix (about 1,100 calls, about 800 of which refine a motion).
Then the current tree and ``--baseline-rev``'s tree (exported with ``git archive``) each
verify every recorded pair in a fresh process of their own, alternating, ``--rounds``
times: the thread's CPU time per call (``time.thread_time``) and per motion refinement
(:func:`robotd.forward.planar.fit_motion`, timed around the verification's call of it), and
a digest of every outcome (accepted, reason, counts, the motion, its sigmas, noise and
planarity, range, support, the matches' indices) that must be the same for both codes.

Reported per code: the mean CPU per verification and per motion refinement, the median of
the verification's CPU per image over the images that verified a candidate, each the
median over the rounds; and the ratios current / baseline (per round, then their median).
Speed on a shared machine moves with its load: compare the ratio, not the milliseconds.

Run: ``PYTHONPATH=. .venv/bin/python bench/bench_forward_verify_calls.py --dir /tmp/office
--baseline-rev REV [--rounds 3] [--out FILE.json]`` (a few minutes); ``--page FILE.json``
rewrites ``docs/benchmarks/forward_verify_calls.md`` from a result.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

if "--child" not in sys.argv:  # a child verifies with the robotd of its PYTHONPATH (a baseline's tree)
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
else:
    sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

PAGE = Path(__file__).resolve().parent.parent / "docs" / "benchmarks" / "forward_verify_calls.md"


def record(folder: Path, out: Path) -> int:
    """Run the default detector over the office sequence in ``folder`` and pickle every
    verification call it makes to ``out`` as ``(image, old, new, params, camera_matrix)``."""
    try:
        from bench.bench_forward_ablation import office_sequence
    except ImportError:
        from bench_forward_ablation import office_sequence  # type: ignore[no-redef]
    import robotd.forward.detector as detector_module
    from robotd.forward import FeatureExtractor, ForwardDetector, method_params
    from robotd.forward.verify import camera_matrix_guess
    from robotd.io.sequence import list_images, read_image

    folder = office_sequence(folder)
    files = list_images(folder, exclude=(folder / "gt.npy",))
    params = method_params("default")
    extract = FeatureExtractor(params.features)
    k = camera_matrix_guess(640, 480, 525.0)
    det = ForwardDetector(params, camera_matrix=k)
    calls: list[tuple[int, Any, Any, Any, Any]] = []
    inner = detector_module.verify_pair
    image = 0

    def hook(old: Any, new: Any, vp: Any, km: Any) -> Any:
        calls.append((image, old, new, vp, km))
        return inner(old, new, vp, km)

    detector_module.verify_pair = hook  # type: ignore[assignment]
    try:
        for image, path in enumerate(files):
            det.process_features(extract(read_image(path)), 0.0)
    finally:
        detector_module.verify_pair = inner
    with out.open("wb") as f:
        pickle.dump(calls, f)
    return len(calls)


def _digest(v: Any) -> str:
    """A digest of everything a :class:`Verification` holds."""
    h = hashlib.sha256()
    for name in ("accepted", "reason", "n_matches", "n_inliers", "n_plane_inliers", "planar", "support_area",
                 "range_m", "n_floor_points", "sigma_bearing_rad", "sigma_yaw_rad", "noise_px", "planarity_chi2",
                 "fallback", "level_yaw_rad"):
        h.update(repr(getattr(v, name)).encode())
    import numpy as np

    for name in ("rotation", "translation_dir"):
        x = getattr(v, name)
        h.update(b"-" if x is None else np.asarray(x, np.float64).tobytes())
    if v.match_index is not None:
        for x in v.match_index:
            h.update(np.asarray(x, np.int64).tobytes())
    return h.hexdigest()


def child(calls_path: Path, out: Path) -> None:
    """Verify every recorded call with the ``robotd`` first on the path; write the times
    and digests to ``out``."""
    import robotd.forward.verify as verify_module

    with calls_path.open("rb") as f:
        calls = pickle.load(f)
    fit_s = [0.0]
    fit_n = [0]
    inner = verify_module.fit_motion

    def timed(*args: Any, **kwargs: Any) -> Any:
        t0 = time.thread_time()
        out = inner(*args, **kwargs)
        fit_s[0] += time.thread_time() - t0
        fit_n[0] += 1
        return out

    verify_module.fit_motion = timed  # type: ignore[assignment]
    times, digests, images = [], [], []
    for image, old, new, vp, km in calls:
        t0 = time.thread_time()
        v = verify_module.verify_pair(old, new, vp, km)
        times.append(time.thread_time() - t0)
        digests.append(_digest(v))
        images.append(image)
    out.write_text(json.dumps({"robotd": verify_module.__file__, "times_s": times, "images": images,
                               "fit_s": fit_s[0], "fit_calls": fit_n[0],
                               "digest": hashlib.sha256("".join(digests).encode()).hexdigest()}))


def _summary(run: dict[str, Any]) -> dict[str, float]:
    per_image: dict[int, float] = {}
    for image, t in zip(run["images"], run["times_s"], strict=True):
        per_image[image] = per_image.get(image, 0.0) + t
    return {"verify_ms_mean": 1e3 * statistics.fmean(run["times_s"]),
            "verify_ms_image_median": 1e3 * statistics.median(per_image.values()),
            "fit_ms_mean": 1e3 * run["fit_s"] / max(run["fit_calls"], 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()) / "robotd-office",
                    help="folder of the virtual office sequence (written when missing)")
    ap.add_argument("--baseline-rev", help="git revision of the baseline code (required unless --page)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--calls", type=Path, default=None, help="recorded calls to reuse (written when missing)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results"
                    / "forward_verify_calls.json")
    ap.add_argument("--page", type=Path, default=None, metavar="JSON",
                    help="only rewrite docs/benchmarks/forward_verify_calls.md from this result")
    ap.add_argument("--child", nargs=2, type=Path, metavar=("CALLS", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(*args.child)
        return 0
    try:
        from bench.common import REPO_ROOT, git_commit, machine_info, write_json
    except ImportError:
        from common import REPO_ROOT, git_commit, machine_info, write_json  # type: ignore[no-redef]
    if args.page is not None:
        write_markdown(json.loads(args.page.read_text(encoding="utf-8")))
        return 0
    if not args.baseline_rev:
        ap.error("--baseline-rev is required")
    if args.rounds < 1:
        ap.error("--rounds must be >= 1")
    work = Path(tempfile.mkdtemp(prefix="verify_calls_"))
    calls = args.calls or work / "calls.pkl"
    if not calls.exists():
        print(f"recording the office route's verifications to {calls} ...", flush=True)
        print(f"{record(args.dir, calls)} calls", flush=True)
    base_tree = work / "baseline"
    base_tree.mkdir()
    archive = subprocess.run(["git", "archive", args.baseline_rev, "robotd"], cwd=REPO_ROOT, check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(base_tree)], input=archive, check=True)
    trees = {"baseline": base_tree, "current": REPO_ROOT}
    runs: dict[str, list[dict[str, Any]]] = {"baseline": [], "current": []}
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    for r in range(args.rounds):
        for name in (("baseline", "current") if r % 2 == 0 else ("current", "baseline")):
            out = work / f"{name}_{r}.json"
            subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(calls), str(out)],
                           env=dict(env, PYTHONPATH=str(trees[name])), cwd=str(trees[name]), check=True)
            run = json.loads(out.read_text(encoding="utf-8"))
            assert Path(run["robotd"]).resolve().is_relative_to(Path(trees[name]).resolve()), run["robotd"]
            runs[name].append(run)
            s = _summary(run)
            print(f"round {r} {name:8s} verify {s['verify_ms_mean']:.3f} ms/call, image median "
                  f"{s['verify_ms_image_median']:.3f} ms, fit_motion {s['fit_ms_mean']:.3f} ms/call", flush=True)
    digests = {run["digest"] for rs in runs.values() for run in rs}
    keys = ("verify_ms_mean", "verify_ms_image_median", "fit_ms_mean")
    summary = {name: {k: statistics.median(_summary(run)[k] for run in rs) for k in keys} for name, rs in runs.items()}
    ratios = {k: statistics.median(_summary(c)[k] / _summary(b)[k]
                                   for b, c in zip(runs["baseline"], runs["current"], strict=True)) for k in keys}
    first = runs["current"][0]
    result = {"machine": machine_info(), "commit": git_commit(), "baseline_rev": args.baseline_rev,
              "baseline_commit": subprocess.run(["git", "rev-parse", args.baseline_rev], cwd=REPO_ROOT, check=True,
                                                capture_output=True, text=True).stdout.strip(),
              "load_avg": list(os.getloadavg()), "rounds": args.rounds, "calls": len(first["times_s"]),
              "fit_calls": first["fit_calls"], "images_verified": len(set(first["images"])),
              "same_outcomes": len(digests) == 1, "summary": summary, "ratio_current_over_baseline": ratios}
    write_json(args.out, result)
    print(json.dumps({"same_outcomes": result["same_outcomes"], "summary": summary, "ratios": ratios}, indent=1))
    return 0 if result["same_outcomes"] else 1


def write_markdown(res: dict[str, Any]) -> None:
    """``docs/benchmarks/forward_verify_calls.md`` from a result."""
    try:
        from bench.common import write_page
    except ImportError:
        from common import write_page  # type: ignore[no-redef]
    m = res["machine"]
    s, q = res["summary"], res["ratio_current_over_baseline"]
    lines = [
        "# Forward verification: CPU per call against a baseline revision",
        "",
        "Generated by `bench/bench_forward_verify_calls.py` from `forward_verify_calls.json` (module notes "
        "there; read in [forward.md](../forward.md), \"The time target\"): the office route's own",
        f"verifications ({res['calls']} calls of `verify_pair` on {res['images_verified']} images, "
        f"{res['fit_calls']} motion refinements),",
        f"each code in its own process, alternating, {res['rounds']} rounds; thread CPU time, the median over the",
        "rounds; the ratio is current / baseline per round, then its median.",
        "",
        f"Machine: {m.get('cpu_model', '?')}, {m.get('cpu_count', '?')} CPUs, OpenCV {m.get('opencv', '?')}, "
        f"numpy {m.get('numpy', '?')}; load average {', '.join(f'{x:.1f}' for x in res['load_avg'])} at the end.",
        "Baseline: the revision given as `--baseline-rev` (its commit in `forward_verify_calls.json`). "
        "Same outcomes for every call (digest of each verification): "
        f"**{'yes' if res['same_outcomes'] else 'NO'}**.",
        "",
        "| CPU | baseline | current | ratio |",
        "|---|---:|---:|---:|",
        f"| `verify_pair` per call (mean), ms | {s['baseline']['verify_ms_mean']:.2f} | "
        f"{s['current']['verify_ms_mean']:.2f} | {q['verify_ms_mean']:.2f} |",
        f"| verification per verifying image (median), ms | {s['baseline']['verify_ms_image_median']:.2f} | "
        f"{s['current']['verify_ms_image_median']:.2f} | {q['verify_ms_image_median']:.2f} |",
        f"| `fit_motion` per call (mean), ms | {s['baseline']['fit_ms_mean']:.2f} | "
        f"{s['current']['fit_ms_mean']:.2f} | {q['fit_ms_mean']:.2f} |",
        "",
    ]
    if not math.isfinite(q["verify_ms_mean"]):
        lines.append("(no ratio)")
    write_page(PAGE, lines)


if __name__ == "__main__":
    sys.exit(main())
