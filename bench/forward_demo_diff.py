"""Whether two ``robotd demo --forward`` runs gave the same answers (the code before and a
cut that must keep them): the forward detector's counts in ``summary.json``, every forward
loop there (its pair of keyframes, inliers and fate; the published heading change and
bearing, their sigmas and their errors against the truth) and the keyframes' poses after
the pose graph (``corrected.tum``, ``keyframes.tum``). Times are left out.

Run: ``python bench/forward_demo_diff.py DIR_A DIR_B [--tol 0]`` (the two ``--out``
folders); prints each difference and exits 1 when there is one. ``--tol``: the largest
difference of a number still called the same (default 0: to the bit). ``--by-pair``: the
loops matched by their pair of keyframes (to, then from) instead of in the order they were
published (a change that publishes a loop later, such as the forward stage's deferred level
test, reorders them); a pair in one run only is named.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

#: The forward summary's counts compared (``summary.json``'s ``forward_detector``).
COUNTS = ("images", "verified_loops", "verified_right", "accepted", "accepted_right", "accepted_outside_own_noise",
          "refused_by_gate", "grouped", "failed_verification", "not_planar")

#: The trajectories compared, one row per keyframe (TUM: stamp, x, y, z, quaternion).
POSES = ("corrected.tum", "keyframes.tum")


def _same(a: Any, b: Any, tol: float) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol
    return bool(a == b)


def _pair(loop: dict[str, Any]) -> tuple[int, int]:
    return int(loop.get("to", -1)), int(loop.get("from", -1))


def summary_differences(a: dict[str, Any], b: dict[str, Any], tol: float = 0.0, by_pair: bool = False) -> list[str]:
    """The differences of two demo summaries' forward answers, each named where it is
    (``by_pair``: the loops matched by their keyframes, not by their order)."""
    fa, fb = a.get("forward_detector") or {}, b.get("forward_detector") or {}
    out = [f"{k}: {fa.get(k)!r} != {fb.get(k)!r}" for k in COUNTS if fa.get(k) != fb.get(k)]
    la, lb = fa.get("loops") or [], fb.get("loops") or []
    if by_pair:
        pa, pb = {_pair(x) for x in la}, {_pair(y) for y in lb}
        out += [f"loop {p[1]} -> {p[0]}: in the first run only" for p in sorted(pa - pb)]
        out += [f"loop {p[1]} -> {p[0]}: in the second run only" for p in sorted(pb - pa)]
        la = sorted((x for x in la if _pair(x) in pb), key=_pair)
        lb = sorted((y for y in lb if _pair(y) in pa), key=_pair)
    if len(la) != len(lb):
        out.append(f"loops: {len(la)} != {len(lb)}")
    for n, (x, y) in enumerate(zip(la, lb)):
        for k in sorted(set(x) | set(y)):
            if not _same(x.get(k), y.get(k), tol):
                out.append(f"loop {n} ({x.get('from')} -> {x.get('to')}).{k}: {x.get(k)!r} != {y.get(k)!r}")
    return out


def pose_differences(a: list[list[float]], b: list[list[float]], name: str, tol: float = 0.0) -> list[str]:
    """The rows of two trajectories that differ by more than ``tol`` in any column."""
    if len(a) != len(b):
        return [f"{name}: {len(a)} rows != {len(b)}"]
    out = []
    for n, (x, y) in enumerate(zip(a, b)):
        worst = max((abs(p - q) for p, q in zip(x, y)), default=0.0)
        if len(x) != len(y) or worst > tol:
            out.append(f"{name} row {n}: differs by {worst:.3g}")
    return out


def _tum(path: Path) -> list[list[float]]:
    return [[float(v) for v in line.split()] for line in path.read_text().splitlines()
            if line.strip() and not line.startswith("#")]


def differences(dir_a: Path, dir_b: Path, tol: float = 0.0, by_pair: bool = False) -> list[str]:
    """Every difference of the two runs' forward answers and keyframe poses."""
    out = summary_differences(json.loads((dir_a / "summary.json").read_text()),
                              json.loads((dir_b / "summary.json").read_text()), tol, by_pair)
    for name in POSES:
        if (dir_a / name).exists() or (dir_b / name).exists():
            if not ((dir_a / name).exists() and (dir_b / name).exists()):
                out.append(f"{name}: in one run only")
            else:
                out += pose_differences(_tum(dir_a / name), _tum(dir_b / name), name, tol)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir_a", type=Path)
    ap.add_argument("dir_b", type=Path)
    ap.add_argument("--tol", type=float, default=0.0, help="largest difference still the same (default 0)")
    ap.add_argument("--by-pair", action="store_true",
                    help="match the loops by their pair of keyframes, not by the order they were published")
    args = ap.parse_args(argv)
    diff = differences(args.dir_a, args.dir_b, args.tol, args.by_pair)
    for line in diff:
        print(line)
    fa = json.loads((args.dir_a / "summary.json").read_text()).get("forward_detector") or {}
    print(f"{len(fa.get('loops') or [])} forward loops, {len(diff)} differences")
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
