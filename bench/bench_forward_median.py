"""The default forward detector's CPU per image, this checkout against the code of
``--baseline-rev``, in the same run, image by image, and whether every answer is the same.

Two worker processes, one per tree (the baseline's ``robotd/`` is exported from git into a
temporary folder), each holding its own detector (``method_params("default")``) over the same
images; the driver hands each image to both in turn (which goes first alternates), so the
load falls on both alike. Each worker measures its own process CPU per image: OpenCV's ORB
features (the detector's own extractor) and ``process_features``, and the detector's stages
on the process CPU clock (``ForwardDetector(timer=time.process_time)``). Sequences:
rtabmap_samples (no pose), the virtual office route without a pose and with the daemon's
fused pose (``bench/bench_forward_ablation.py``'s ``odometry_fused.csv``, computed when
missing).

The answers compared per image: the words of the image, the status, loop and candidate, the
candidate's probability and the virtual image's vote (to 1e-9), one SHA-256 over the image's
votes, likelihoods, posterior and hypothesis ids (to the bit: :func:`filter_digest`), and of a
verification its outcome, reason, matches, inliers, plane inliers and the motion (rotation and
translation direction, to 1e-9). Printed: differences (none expected), per sequence the CPU per image
(features included) median and p99 of both and their ratio (now / before), and each stage's.
Written: JSON (``--out``); ``--page FILE.json`` writes docs/benchmarks/forward_median.md
from one.

Run: ``PYTHONPATH=. .venv/bin/python bench/bench_forward_median.py --dir /tmp/office
--baseline-rev REV`` (about 3 minutes per sequence on the shared 2-core machine).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import REPO_ROOT, machine_info, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import REPO_ROOT, machine_info, write_json  # type: ignore[no-redef]

DATA = REPO_ROOT.parent / "shared" / "data"
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "forward_median.json"
PAGE = REPO_ROOT / "docs" / "benchmarks" / "forward_median.md"
TOL = 1e-9


def filter_digest(d: Any) -> str:
    """SHA-256 (hex) over a detection's votes, likelihoods, posterior and hypothesis ids, each
    array's dtype, shape and bytes: equal only when every value is the same to the bit."""
    h = hashlib.sha256()
    for a in (d.scores, d.likelihood, d.posterior, d.hypothesis_ids):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


# -- the worker: one tree's detector, one image per request --------------------------------
def _worker(folder: str, truth: str, office: bool, fused: str) -> None:
    import time

    from robotd.forward import FeatureExtractor, ForwardDetector, method_params
    from robotd.forward.verify import camera_matrix_guess
    from robotd.io.sequence import list_images, read_image

    clock = time.process_time
    files = list_images(Path(folder), exclude=(Path(truth),))
    images = [read_image(p) for p in files]
    h, w = images[0].shape[:2]
    params = method_params("default")
    ex = FeatureExtractor(params.features)
    det = ForwardDetector(params, camera_matrix=camera_matrix_guess(w, h, 525.0 if office else None), timer=clock)
    odo = None
    if fused:
        z = np.load(fused)
        odo = (z["poses"], z["covs"])
    out = sys.stdout.buffer
    for line in sys.stdin:
        t = int(line)
        c0 = clock()
        fe = ex(images[t])
        c1 = clock()
        d = (det.process_features(fe, c1 - c0) if odo is None
             else det.process_features(fe, c1 - c0, odo[0][t], odo[1][t]))
        c2 = clock()
        v = d.verification
        answer = {"words": det.features_of(t).words.tolist(), "status": str(d.status), "loop": d.loop_id,
                  "candidate": d.candidate_id, "p": d.candidate_probability, "virtual": d.virtual_score,
                  "filter_sha256": filter_digest(d),
                  "verification": None if v is None else
                  {"accepted": v.accepted, "reason": v.reason, "n_matches": v.n_matches,
                   "n_inliers": v.n_inliers, "n_plane_inliers": v.n_plane_inliers, "fallback": v.fallback,
                   "rotation": None if v.rotation is None else v.rotation.tolist(),
                   "translation_dir": None if v.translation_dir is None else v.translation_dir.tolist()}}
        row = {"cpu_ms": (c2 - c0) * 1e3, "features_ms": (c1 - c0) * 1e3,
               **{f"stage_{k}": s * 1e3 for k, s in d.times_s.items()}, "answer": answer}
        blob = pickle.dumps(row)
        out.write(len(blob).to_bytes(8, "little") + blob)
        out.flush()


def export_tree(rev: str) -> Path:
    """``robotd/`` as it is at git revision ``rev``, in a new temporary folder."""
    tar = subprocess.run(["git", "archive", "--format=tar", rev, "robotd"], cwd=REPO_ROOT, check=True,
                         capture_output=True).stdout
    dest = Path(tempfile.mkdtemp(prefix="forward_median_"))
    with tarfile.open(fileobj=io.BytesIO(tar)) as tf:
        tf.extractall(dest, filter="data")
    return dest


class Worker:
    def __init__(self, tree: Path, args: list[str]) -> None:
        env = {**os.environ, "PYTHONPATH": str(tree)}
        self.proc = subprocess.Popen([sys.executable, __file__, "--worker", *args], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, env=env, cwd=str(tree))

    def ask(self, t: int) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(f"{t}\n".encode())
        self.proc.stdin.flush()
        n = int.from_bytes(self.proc.stdout.read(8), "little")
        row: dict[str, Any] = pickle.loads(self.proc.stdout.read(n))
        return row

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


def differences(a: Any, b: Any, path: str = "") -> list[str]:
    """Where two answers differ (floats to :data:`TOL`)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b)) for d in differences(a.get(k), b.get(k), f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float):
        return [] if abs(a - b) <= TOL or (a != a and b != b) else [f"{path}: {a!r} != {b!r}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


def run_sequence(name: str, folder: Path, truth: Path, office: bool, fused: Path | None,
                 base_tree: Path, head_tree: Path) -> dict[str, Any]:
    from robotd.io.sequence import list_images

    n = len(list_images(folder, exclude=(truth,)))
    args = [str(folder), str(truth), "1" if office else "0", str(fused or "")]
    workers = {"before": Worker(base_tree, args), "now": Worker(head_tree, args)}
    rows: dict[str, list[dict[str, Any]]] = {"before": [], "now": []}
    diffs: list[str] = []
    try:
        for t in range(n):
            order = ("before", "now") if t % 2 == 0 else ("now", "before")
            for who in order:
                rows[who].append(workers[who].ask(t))
            d = differences(rows["before"][-1].pop("answer"), rows["now"][-1].pop("answer"), f"image {t}")
            diffs.extend(d)
    finally:
        for w in workers.values():
            w.close()
    keys = [k for k in rows["now"][0] if k in rows["before"][0]]
    stats: dict[str, Any] = {}
    for k in keys:
        b = np.array([r[k] for r in rows["before"]])
        h = np.array([r[k] for r in rows["now"]])
        stats[k] = {"before": {"median": float(np.median(b)), "p99": float(np.percentile(b, 99))},
                    "now": {"median": float(np.median(h)), "p99": float(np.percentile(h, 99))},
                    "ratio_median": float(np.median(h) / max(np.median(b), 1e-12)),
                    "ratio_p99": float(np.percentile(h, 99) / max(np.percentile(b, 99), 1e-12))}
    print(f"\n{name}: {n} images, answers differing: {len(diffs)}", flush=True)
    for d in diffs[:20]:
        print("   ", d)
    print(f"    {'ms':<22}{'before med':>11}{'now med':>9}{'ratio':>7}{'before p99':>12}{'now p99':>9}{'ratio':>7}")
    for k, s in stats.items():
        print(f"    {k:<22}{s['before']['median']:>11.2f}{s['now']['median']:>9.2f}{s['ratio_median']:>7.3f}"
              f"{s['before']['p99']:>12.2f}{s['now']['p99']:>9.2f}{s['ratio_p99']:>7.3f}", flush=True)
    return {"images": n, "pose": fused is not None, "answers_differing": len(diffs), "first_differences": diffs[:20],
            "ms": stats}


def write_markdown(result: dict[str, Any], json_name: str) -> None:
    """docs/benchmarks/forward_median.md from a run's JSON."""
    try:
        from bench.common import write_page
    except ImportError:
        from common import write_page  # type: ignore[no-redef]
    m = result["machine"]
    lines = ["# Forward detector: CPU per image against the code before, every answer compared", "",
             f"Generated by `bench/bench_forward_median.py --page` from `{json_name}` (module notes there; "
             "read in [forward.md](../forward.md), \"The time target\", its cuts that keep every answer): the default detector "
             "of this checkout and of the baseline revision in two worker processes, handed each image in "
             "turn (which goes first alternates); each process's own CPU per image, OpenCV's ORB features "
             "included, and the detector's stages on the process CPU clock.", "",
             f"Machine: {m.get('cpu_model') or m.get('machine', '?')}, {m.get('cpu_count', '?')} CPUs, "
             f"OpenCV {m.get('opencv', '?')}, numpy {m.get('numpy', '?')}; load average "
             f"{', '.join(f'{x:.1f}' for x in result['load_before'])} before, "
             f"{', '.join(f'{x:.1f}' for x in result['load_after'])} after. "
             f"Baseline: the code before the cuts, the revision given as `--baseline-rev` (in `{json_name}`).", ""]
    arrays = "the votes, likelihoods and posterior to the bit, " if result.get("filter_digest") else ""
    for name, seq in result["sequences"].items():
        lines += [f"## {name} ({seq['images']} images)", "",
                  f"Answers differing (words, decision, candidate, probability, {arrays}verification and its motion): "
                  f"**{seq['answers_differing']}**.", "",
                  "| ms | before median | now median | ratio | before p99 | now p99 | ratio |",
                  "|---|---:|---:|---:|---:|---:|---:|"]
        for k, st in seq["ms"].items():
            if k == "features_ms":
                continue
            label = "CPU per image, features included" if k == "cpu_ms" else k.replace("stage_", "stage: ")
            lines.append(f"| {label} | {st['before']['median']:.2f} | {st['now']['median']:.2f} | "
                         f"{st['ratio_median']:.3f} | {st['before']['p99']:.2f} | {st['now']['p99']:.2f} | "
                         f"{st['ratio_p99']:.3f} |")
        lines.append("")
    write_page(PAGE, lines)
    print(f"wrote {PAGE}")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--worker":
        _worker(argv[1], argv[2], argv[3] == "1", argv[4])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", type=Path, help="folder of the virtual office sequence (required unless --page)")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--baseline-rev", help="git revision of the code before (required unless --page)")
    ap.add_argument("--sequences", default="rtabmap_samples;office;office, fused pose",
                    help="semicolon-separated, of: rtabmap_samples, office, office, fused pose")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--page", type=Path, default=None, metavar="JSON",
                    help="write docs/benchmarks/forward_median.md from this JSON and stop")
    a = ap.parse_args(argv)
    if a.page is not None:
        write_markdown(json.loads(a.page.read_text(encoding="utf-8")), a.page.name)
        return 0
    if not a.baseline_rev or a.dir is None:
        ap.error("--baseline-rev and --dir are required (unless --page)")
    try:
        from bench.bench_forward_ablation import office_fused_odometry, office_sequence
    except ImportError:
        from bench_forward_ablation import office_fused_odometry, office_sequence  # type: ignore[no-redef]
    base_tree = export_tree(a.baseline_rev)
    result: dict[str, Any] = {"machine": machine_info(), "load_before": os.getloadavg(),
                              "baseline_rev": a.baseline_rev, "filter_digest": True, "sequences": {}}
    for name in a.sequences.split(";"):
        name = name.strip()
        if name == "rtabmap_samples":
            folder = a.data / "forward" / "rtabmap_samples"
            res = run_sequence(name, folder, folder / "ground_truth.bmp", False, None, base_tree, REPO_ROOT)
        else:
            folder = office_sequence(a.dir)
            fused = None
            if name == "office, fused pose":
                poses, covs = office_fused_odometry(folder)
                fused = Path(tempfile.mkdtemp(prefix="forward_median_")) / "fused.npz"
                np.savez(fused, poses=poses, covs=covs)
            res = run_sequence(name, folder, folder / "gt.npy", True, fused, base_tree, REPO_ROOT)
        result["sequences"][name] = res
    result["load_after"] = os.getloadavg()
    write_json(a.out, result)
    print(json.dumps({k: v["answers_differing"] for k, v in result["sequences"].items()}))
    return 0 if all(v["answers_differing"] == 0 for v in result["sequences"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
