"""Fuzzing run: inputs tried and crashes per target, and how deep the inputs went.

The targets and their strategies are those of the test suite (``tests/fuzz/targets.py``):
the Kobuki packet parser, the pyserial ``spy://`` capture decoder, the g2o reader and the
floor descriptor decoder. A crash is an exception other than the target's documented
error; here a crash is counted (its first three are kept) and the run goes on, where the
test stops at the first and shrinks it. Also reported: how many inputs were accepted
whole and how many were refused with the documented error, by the error's reason, which
shows whether the inputs get past the first checks.

Run: ``.venv/bin/python bench/bench_fuzz.py [--examples 20000] [--seed 0] [--out FILE]``.
"""

from __future__ import annotations

import argparse
import collections
import re
import sys
import time
from pathlib import Path
from typing import Any

try:
    from bench.common import REPO_ROOT, machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import REPO_ROOT, machine_info, print_table, write_json

sys.path.insert(0, str(REPO_ROOT))  # tests.fuzz.targets

from hypothesis import HealthCheck, given, settings, seed  # noqa: E402

from tests.fuzz.targets import TARGETS, Target  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "fuzz.json"


def _reason(exc: BaseException) -> str:
    """The error's message without its numbers and quoted values (groups alike refusals)."""
    text = str(exc).split(": ", 1)[-1] if ":" in str(exc) else str(exc)
    text = re.sub(r"'[^']*'|\"[^\"]*\"|-?\d+(\.\d+)?", "#", text)
    return text[:70]


def fuzz(target: Target, examples: int, rng_seed: int) -> dict[str, Any]:
    """Run ``examples`` inputs through ``target``; counts, crashes and refusal reasons."""
    counts = collections.Counter()
    reasons: collections.Counter[str] = collections.Counter()
    crashes: list[str] = []

    @seed(rng_seed)
    @settings(max_examples=examples, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(target.strategy)
    def run(example: Any) -> None:
        counts["tried"] += 1
        try:
            target.check(example)
        except target.allowed as exc:
            counts["refused"] += 1
            reasons[_reason(exc)] += 1
            return
        except Exception as exc:  # a crash: count it, keep the first few, go on
            counts["crashes"] += 1
            if len(crashes) < 3:
                crashes.append(f"{type(exc).__name__}: {exc} <- {example!r:.300}")
            return
        counts["accepted"] += 1

    t0 = time.perf_counter()
    run()
    return {"target": target.name, "tried": counts["tried"], "accepted": counts["accepted"],
            "refused": counts["refused"], "crashes": counts["crashes"], "crash_examples": crashes,
            "refusal_reasons": dict(reasons.most_common(8)), "wall_s": time.perf_counter() - t0,
            "documented_error": [e.__name__ for e in target.allowed] or ["none (never raises)"]}


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--examples", type=int, default=20000, help="inputs per target (default 20000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--targets", nargs="*", default=None, help="run only these targets")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    chosen = [t for t in TARGETS if not args.targets or t.name in args.targets]
    results = [fuzz(t, args.examples, args.seed) for t in chosen]
    print_table(["target", "inputs tried", "accepted", "refused (documented error)", "crashes", "s"],
                [[r["target"], r["tried"], r["accepted"], r["refused"], r["crashes"], round(r["wall_s"], 1)]
                 for r in results])
    for r in results:
        if r["refusal_reasons"]:
            print(f"\n{r['target']}: most common refusals")
            for reason, n in r["refusal_reasons"].items():
                print(f"  {n:7d}  {reason}")
        for c in r["crash_examples"]:
            print(f"\n{r['target']} CRASH: {c}")
    out = write_json(args.out, {"machine": machine_info(), "examples": args.examples,
                                "seed": args.seed, "targets": results})
    print(f"\nwrote {out}")
    return 1 if any(r["crashes"] for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
