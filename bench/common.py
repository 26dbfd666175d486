"""Helpers shared by the benchmarks: machine description, repeated timing, JSON, tables.

Benchmarks are command-line programs, not tests: they time with the wall clock
(``time.perf_counter``), report the median and the interquartile range after a warm-up,
and record the machine, the library versions and the git commit next to the numbers.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parent.parent


def git_commit(repo_dir: Path = REPO_ROOT) -> str | None:
    """``git rev-parse HEAD`` of ``repo_dir``; outside a git work tree (a tree exported by
    ``git archive`` to run a long benchmark while the work tree changes) the commit named by
    the ``ROBOTD_GIT_COMMIT`` environment variable; else ``None``."""
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo_dir, capture_output=True,
                              text=True, timeout=10, check=True)
    except (OSError, subprocess.SubprocessError):
        return os.environ.get("ROBOTD_GIT_COMMIT") or None
    return done.stdout.strip() or None


def git_dirty(repo_dir: Path = REPO_ROOT) -> bool | None:
    """Whether the work tree has uncommitted changes (``None`` when unknown)."""
    try:
        done = subprocess.run(["git", "status", "--porcelain"], cwd=repo_dir,
                              capture_output=True, text=True, timeout=10, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return bool(done.stdout.strip())


def module_at_revision(rev: str, relpath: str, name: str) -> Any:
    """The module at ``relpath`` as it is at git revision ``rev``, imported as ``name``
    (for a bench's baseline: the code before, run in the same process as the code now)."""
    import importlib.util
    import tempfile

    src = subprocess.run(["git", "show", f"{rev}:{relpath}"], cwd=REPO_ROOT, check=True,
                         capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / f"{name}.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def cpu_model() -> str | None:
    """The CPU's model name from ``/proc/cpuinfo`` (Linux), else None.

    Two machines of one kind can differ here (an instruction set, a clock), which moves
    absolute times as much as the load does; the ratios against a baseline do not move.
    """
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "Model") and value.strip():
                    return value.strip()
    except OSError:
        return None
    return None


def machine_info() -> dict[str, Any]:
    """Platform, CPU model and count, Python, numpy and OpenCV versions, git commit, UTC date."""
    try:
        import numpy
        numpy_version: str | None = numpy.__version__
    except ImportError:
        numpy_version = None
    try:
        import cv2
        opencv_version: str | None = cv2.__version__
    except ImportError:
        opencv_version = None
    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or None,
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "python_implementation": platform.python_implementation(),
        "numpy": numpy_version,
        "opencv": opencv_version,
        "git_commit": git_commit(),
        "git_dirty": git_dirty(),
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def time_repeats(fn: Callable[[], object], repeats: int = 7, warmup: int = 1) -> dict[str, Any]:
    """Call ``fn`` ``warmup`` times untimed, then ``repeats`` times timed.

    Returns ``median_s``, ``iqr_s`` (interquartile range, the spread), ``min_s`` and
    ``runs`` (every timed run, seconds).
    """
    if repeats < 1:
        raise ValueError("repeats must be >= 1")
    for _ in range(warmup):
        fn()
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    if len(runs) >= 2:
        q1, _, q3 = statistics.quantiles(runs, n=4, method="inclusive")
        iqr = q3 - q1
    else:
        iqr = 0.0
    return {"median_s": statistics.median(runs), "iqr_s": iqr, "min_s": min(runs), "runs": runs}


def write_json(path: str | Path, payload: Any) -> Path:
    """Write ``payload`` as indented JSON, creating the parent directories."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")
    return path


def write_page(path: Path, lines: Sequence[str]) -> None:
    """A benchmark's Markdown page from its lines (the folder made if needed), replaced
    atomically."""
    from robotd.base.files import write_text_replacing

    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_replacing(path, "\n".join(lines))


def grow_repeated_map(path: Path, blobs: Sequence[bytes], mode: int, n: int, kf_ids: list[int]) -> list[int]:
    """Grow the map at ``path`` to ``n`` keyframes, as the daemon stores them: the floor
    descriptors ``blobs`` (of ``mode``) repeated in order under new ids, each copy one more
    pass over the same floor. ``kf_ids`` holds the ids stored so far (grown in place), so
    one map grows through increasing sizes; it is returned."""
    import numpy as np

    from robotd.io.store import MapStore

    with MapStore.open(path, synchronous="NORMAL") as store:
        run = store.begin_run("", started_ns=0)
        for i in range(len(kf_ids), n):
            kf_ids.append(store.add_keyframe(run, i, (0.0, 0.0, 0.0), np.eye(3), None, blobs[i % len(blobs)], mode))
    return kf_ids


def print_table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    """Print an aligned text table: text left-aligned, numbers right-aligned."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in row] for row in rows]
    widths = [max(len(row[k]) for row in cells) for k in range(len(headers))]
    numeric = [all(isinstance(row[k], (int, float)) for row in rows) for k in range(len(headers))]

    def fmt(row: list[str]) -> str:
        return "  ".join(c.rjust(w) if num else c.ljust(w)
                         for c, w, num in zip(row, widths, numeric)).rstrip()

    print(fmt(cells[0]))
    print("  ".join("-" * w for w in widths))
    for row in cells[1:]:
        print(fmt(row))
