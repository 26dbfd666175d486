"""The odometry stage's CPU per message against the code of another git revision, in one process.

The messages the daemon's odometry stage handles on the recorded 60 s office drive
(``bench_daemon.py``'s recording: its wheel ticks, gyro readings and the floor visual
odometry steps the daemon made, in the order the stage got them) are captured once from a
replay through the whole daemon (cached beside the recording), then fed to two
:class:`~robotd.app.stages.odometry.OdometryStage` s, each owning an odometry filter built
as the daemon builds it (the default config, the shipped calibration): this checkout's and
``--baseline-rev``'s (``robotd/odometry/`` and ``robotd/app/stages/odometry.py`` read from
git and imported beside this checkout's). Each stage publishes its
:class:`~robotd.base.messages.OdometryUpdate` after every wheel reading, as in the daemon
(to a pipeline that drops it: its consumer is charged to its own stage there).

The two codes alternate pass by pass over the whole stream (which goes first alternates
by round), thread CPU time. What both published must be the same: a digest of every
published pose and covariance (fused and wheel-only), the filters' counters and final
states, and each keyframe's pose and edge as the keyframe stage reads them (so that a cut
that changes a single bit shows).

Run: ``python bench/bench_odometry_stage.py --baseline-rev REV [--rounds 5]`` (a minute, the
first run half a minute more to capture the stream). Writes ``odometry_stage.json``
(``--out``, ``--name``) and, with ``--page``, its Markdown page (``--page-from JSON``: only
the page, from an earlier run's JSON).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's robotd first
import numpy as np  # noqa: E402

try:
    from bench.common import machine_info, module_at_revision, write_json, write_page
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, module_at_revision, write_json, write_page

#: The keyframe stage's read of the wheel + gyro edge, timed apart from the stage's handlers.
EDGE = "keyframe_edge"
CACHE = Path.home() / ".cache" / "robotd-bench"
#: The modules the stage runs, in the order they import each other.
MODULES = ("robotd/odometry/kinematics.py", "robotd/odometry/ekf.py", "robotd/odometry/relative.py",
           "robotd/odometry/increments.py", "robotd/odometry/packet.py", "robotd/odometry/history.py",
           "robotd/odometry/journal.py", "robotd/odometry/fusion.py", "robotd/app/stages/odometry.py")


def _dotted(relpath: str) -> str:
    return relpath[:-3].replace("/", ".")


def baseline_modules(rev: str) -> dict[str, Any]:
    """The stage's modules at ``rev`` (``dotted name -> module``), each importing the others
    at ``rev`` (this checkout's entries in ``sys.modules`` are put back afterwards)."""
    import importlib

    saved = {}
    out: dict[str, Any] = {}
    try:
        for rel in MODULES:
            name = _dotted(rel)
            saved[name] = sys.modules.get(name) or importlib.import_module(name)
            mod = module_at_revision(rev, rel, f"baseline_{name.replace('.', '_')}")
            sys.modules[name] = mod  # the next ones' imports resolve to it
            out[name] = mod
    finally:
        for name, mod in saved.items():
            sys.modules[name] = mod
    return out


def current_modules() -> dict[str, Any]:
    import importlib

    return {_dotted(rel): importlib.import_module(_dotted(rel)) for rel in MODULES}


def daemon_config(map_path: Path) -> Any:
    """``bench_daemon.py``'s config (``robotd replay`` with the virtual floor camera)."""
    from robotd.app.demo import shipped_calibration
    from robotd.base.config import Config, replace, with_virtual_floor_camera

    cfg = with_virtual_floor_camera(Config())
    cfg = replace(cfg, "map", path=str(map_path))
    return replace(cfg, "calibration", path=str(shipped_calibration()))


def capture(recording: Path) -> list[tuple[str, Any]]:
    """Replay ``recording`` through the whole daemon; the odometry stage's handler calls in
    order, ``(handler name, message)``."""
    from drivers.recording.replay import ReplayDriver
    from robotd.app.assemble import assemble_daemon, open_map
    from robotd.app.notify import Notifier
    from robotd.app.service import replay_finished
    from robotd.base.clock import ManualClock

    calls: list[tuple[str, Any]] = []

    def wrap(stage: str, handler: str, fn: Any) -> Any:
        if stage != "odometry" or not handler.startswith("on_"):
            return fn

        def recorded(*args: Any) -> Any:
            calls.append((handler, args[0]))
            return fn(*args)

        return recorded

    with tempfile.TemporaryDirectory() as tmp:
        cfg = daemon_config(Path(tmp) / "map.sqlite")
        clock = ManualClock()
        with ReplayDriver(recording, clock, None) as rd:
            clock.set_ns(rd.time_range_ns[0])
            with open_map(cfg, clock=clock) as store:
                daemon = assemble_daemon(cfg, clock, {"replay": rd}, store, Notifier(), lossless=True)
                daemon.pipeline.instrument(wrap)
                daemon.run(stop_when=lambda: replay_finished(rd, daemon))
    return calls


def filter_arguments() -> tuple[tuple[Any, ...], dict[str, Any]]:
    """The arguments :func:`robotd.app.assemble.build_odometry` gives the daemon's filter."""
    from robotd.app import assemble

    got: list[tuple[tuple[Any, ...], dict[str, Any]]] = []
    real = assemble.OdometryFilter
    with tempfile.TemporaryDirectory() as tmp:
        cfg = daemon_config(Path(tmp) / "map.sqlite")
        try:
            assemble.OdometryFilter = lambda *a, **k: got.append((a, k))  # type: ignore[assignment,misc]
            assemble.build_odometry(cfg, assemble.load_calibration(cfg))
        finally:
            assemble.OdometryFilter = real  # type: ignore[misc]
    return got[0]


def _convert(value: Any, mods: dict[str, Any]) -> Any:
    """A params dataclass as the same class of ``mods`` (the baseline's own classes)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for mod in mods.values():
            cls = getattr(mod, type(value).__name__, None)
            if cls is not None and dataclasses.is_dataclass(cls):
                return cls(**{f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
    return value


class _Sink:
    """A pipeline that keeps a digest of what the stage published and drops it."""

    def __init__(self) -> None:
        self.digest = hashlib.sha256()
        self.published = 0
        self.poses: list[tuple[float, ...]] = []  # x, y, yaw, then the covariance's 9 entries
        self.edges: list[tuple[float, ...]] = []  # each keyframe's wheel + gyro edge: delta (3), covariance (9)

    def subscribed(self, msg_type: type) -> bool:
        return True

    def publish(self, msg: Any) -> None:
        self.published += 1
        for p in (msg.fused, msg.wheel):
            self.digest.update(repr((p.stamp_ns, p.x_m, p.y_m, p.yaw_rad)).encode())
            self.digest.update(np.ascontiguousarray(p.covariance).tobytes())
        f = msg.fused
        self.poses.append((f.x_m, f.y_m, f.yaw_rad, *np.asarray(f.covariance, float).ravel().tolist()))


def make_stage(mods: dict[str, Any], arguments: tuple[tuple[Any, ...], dict[str, Any]]) -> tuple[Any, _Sink]:
    args, kwargs = arguments
    odometry = mods["robotd.odometry.fusion"].OdometryFilter(
        *(_convert(a, mods) for a in args), **{k: _convert(v, mods) for k, v in kwargs.items()})
    stage = mods["robotd.app.stages.odometry"].OdometryStage(odometry)
    sink = _Sink()
    stage.pipeline = sink
    return stage, sink


def run_pass(stage: Any, sink: _Sink, calls: list[tuple[str, Any]]) -> dict[str, float]:
    """Feed every call to ``stage``; thread CPU seconds by handler. After each visual step
    the keyframe's pose on both filters (untimed) and the wheel + gyro filter's edge to it
    (timed apart, ``keyframe_edge``: the keyframe stage's call, charged to that stage in
    the daemon) go into ``sink``'s digest, as the keyframe stage reads them."""
    handlers = {name: getattr(stage, name) for name in {c[0] for c in calls}}
    cpu = dict.fromkeys(handlers, 0.0)
    cpu[EDGE] = 0.0
    clock = time.thread_time
    for name, msg in calls:
        t0 = clock()
        handlers[name](msg)
        cpu[name] += clock() - t0
        if name == "on_visual_step":
            h = sink.digest
            for f in (stage.odometry, stage.keyframe_odometry()):
                p = f.pose_at(msg.stamp_ns)
                if p is not None:
                    h.update(repr((p.x_m, p.y_m, p.yaw_rad)).encode() + p.covariance.tobytes())
            t0 = clock()
            edge = stage.keyframe_odometry().keyframe_edge(msg.stamp_ns)
            cpu[EDGE] += clock() - t0
            if edge is not None:
                h.update(edge[0].tobytes() + edge[1].tobytes())
                sink.edges.append((*edge[0].tolist(), *edge[1].ravel().tolist()))
    return cpu


def outcome_digest(stage: Any, sink: _Sink) -> str:
    """The published and keyframe digest, then the counters and the final states."""
    h = hashlib.sha256(sink.digest.digest())
    h.update(repr(sorted(stage.counters().items())).encode())
    for f in (stage.odometry, stage.keyframe_odometry()):
        s = f.state
        h.update(s.mean.tobytes() + s.cov.tobytes())
    return h.hexdigest()


def differences(a: _Sink, b: _Sink) -> dict[str, float]:
    """The largest differences between two runs' published fused poses and keyframe edges:
    position (m), yaw (rad), and covariance entries relative to the largest entry of their
    matrix."""
    out: dict[str, float] = {}
    for name, x, y in (("pose", a.poses, b.poses), ("edge", a.edges, b.edges)):
        if len(x) != len(y):
            out[f"{name}_count_differs"] = float(len(x) - len(y))
            continue
        u, v = np.array(x), np.array(y)
        d = np.abs(u - v)
        out[f"{name}_xy_m"] = float(d[:, :2].max())
        out[f"{name}_yaw_rad"] = float(d[:, 2].max())
        scale = np.abs(v[:, 3:]).max(axis=1, keepdims=True)
        out[f"{name}_cov_rel"] = float((d[:, 3:] / np.where(scale > 0, scale, 1.0)).max())
    return out


def page(p: dict[str, Any]) -> list[str]:
    m = p["machine"]
    lines = ["# Odometry stage: CPU per message against the code of a baseline revision", "",
             "Generated by `bench/bench_odometry_stage.py` from its JSON; do not edit.", "",
             f"- machine: {m.get('cpu_model')} ({m.get('platform')}), Python {m.get('python')}, "
             f"numpy {m.get('numpy')}, commit {m.get('git_commit')}{' (dirty)' if m.get('git_dirty') else ''}; "
             f"baseline {p['baseline_rev']}",
             f"- stream: {p['stream']} ({p['messages']} messages: " + ", ".join(
                 f"{k} {v}" for k, v in p["message_counts"].items()) + ")",
             f"- {p['rounds']} rounds, the two codes alternating pass by pass (thread CPU time); load average "
             f"{p['load_average']}", "",
             "| handler | baseline us/msg | current us/msg | ratio |", "|---|---:|---:|---:|"]
    for name, row in p["handlers"].items():
        if name != EDGE:
            lines.append(f"| {name} | {row['baseline_us']:.1f} | {row['current_us']:.1f} | {row['ratio']:.3f} |")
    t = p["total"]
    lines.append(f"| **all** | **{t['baseline_us']:.1f}** | **{t['current_us']:.1f}** | **{t['ratio']:.3f}** |")
    if EDGE in p["handlers"]:
        row = p["handlers"][EDGE]
        lines.append(f"| {EDGE} (the keyframe stage's call, per visual step; not in all) | {row['baseline_us']:.1f} "
                     f"| {row['current_us']:.1f} | {row['ratio']:.3f} |")
    lines += ["",
              "Ratio by round: " + ", ".join(f"{x:.3f}" for x in t["ratio_by_round"]) + ".", "",
              f"Same outcome (every published pose and covariance, each keyframe's poses and wheel + gyro edge, counters, final states): "
              f"**{p['identical']}** (`{p['digest']['current'][:16]}`). Largest differences from the "
              f"baseline over the drive (published fused poses, each keyframe's wheel + gyro edge; "
              f"covariances relative to their largest entry): "
              + ", ".join(f"{k} {v:.2g}" for k, v in p["differences"].items()) + ".", ""]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline-rev", help="git revision of the code to compare with (required to measure)")
    ap.add_argument("--recording", type=Path, default=CACHE / "office-60s-seed0.mcap",
                    help="the drive (bench_daemon.py records it; default %(default)s)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    ap.add_argument("--name", default="odometry_stage")
    ap.add_argument("--page", type=Path, default=None, help="write the Markdown page here")
    ap.add_argument("--page-from", type=Path, default=None, help="only write --page from this JSON")
    args = ap.parse_args(argv)
    if args.page_from is not None:
        import json

        write_page(args.page or args.page_from.with_suffix(".md"), page(json.loads(args.page_from.read_text())))
        return 0
    if args.baseline_rev is None:
        ap.error("--baseline-rev is required (or --page-from JSON)")

    stream = args.recording.with_name(args.recording.stem + "-odometry-stream.pickle")
    if stream.exists():
        calls = pickle.loads(stream.read_bytes())
    else:
        print(f"capturing the odometry stage's messages from a replay of {args.recording} ...", flush=True)
        calls = capture(args.recording)
        stream.write_bytes(pickle.dumps(calls))
    counts: dict[str, int] = {}
    for name, _ in calls:
        counts[name] = counts.get(name, 0) + 1
    arguments = filter_arguments()
    codes = {"baseline": baseline_modules(args.baseline_rev), "current": current_modules()}
    print(f"{len(calls)} messages ({', '.join(f'{k} {v}' for k, v in counts.items())}); baseline "
          f"{args.baseline_rev}", flush=True)
    cpu: dict[str, list[dict[str, float]]] = {k: [] for k in codes}
    digests: dict[str, set[str]] = {k: set() for k in codes}
    sinks: dict[str, _Sink] = {}
    for r in range(args.rounds + 1):  # round 0 warms up
        for name in (list(codes) if r % 2 == 0 else list(reversed(codes))):
            stage, sink = make_stage(codes[name], arguments)
            got = run_pass(stage, sink, calls)
            digests[name].add(outcome_digest(stage, sink))
            sinks[name] = sink
            if r:
                cpu[name].append(got)
    handlers = {}
    for h in counts:
        b = float(np.median([c[h] for c in cpu["baseline"]])) / counts[h] * 1e6
        c = float(np.median([c[h] for c in cpu["current"]])) / counts[h] * 1e6
        handlers[h] = {"messages": counts[h], "baseline_us": b, "current_us": c, "ratio": c / b}
    if counts.get("on_visual_step"):  # one edge read per visual step; not in the stage's total
        b = float(np.median([c[EDGE] for c in cpu["baseline"]])) / counts["on_visual_step"] * 1e6
        c = float(np.median([c[EDGE] for c in cpu["current"]])) / counts["on_visual_step"] * 1e6
        handlers[EDGE] = {"messages": counts["on_visual_step"], "baseline_us": b, "current_us": c, "ratio": c / b}
    tot = {k: [sum(t for h, t in c.items() if h != EDGE) for c in v] for k, v in cpu.items()}
    n = len(calls)
    total = {"baseline_us": float(np.median(tot["baseline"])) / n * 1e6,
             "current_us": float(np.median(tot["current"])) / n * 1e6,
             "baseline_s": tot["baseline"], "current_s": tot["current"],
             "ratio_by_round": [c / b for b, c in zip(tot["baseline"], tot["current"])]}
    total["ratio"] = total["current_us"] / total["baseline_us"]
    identical = len(digests["baseline"]) == 1 and digests["baseline"] == digests["current"]
    diff = differences(sinks["current"], sinks["baseline"])
    load = None
    with contextlib.suppress(OSError):
        load = [round(x, 2) for x in os.getloadavg()]
    payload = {"machine": machine_info(), "baseline_rev": args.baseline_rev, "stream": args.recording.name,
               "messages": n, "message_counts": counts, "rounds": args.rounds, "load_average": load,
               "handlers": handlers, "total": total, "identical": identical, "differences": diff,
               "digest": {k: sorted(v)[0] for k, v in digests.items()}}
    for h, row in handlers.items():
        print(f"{h:16s} {row['messages']:5d} msgs  {row['baseline_us']:7.1f} -> {row['current_us']:7.1f} us/msg "
              f"(ratio {row['ratio']:.3f})")
    print(f"{'all':16s} {n:5d} msgs  {total['baseline_us']:7.1f} -> {total['current_us']:7.1f} us/msg "
          f"(ratio {total['ratio']:.3f}; by round {', '.join(f'{x:.2f}' for x in total['ratio_by_round'])}); "
          f"same outcome: {identical}", flush=True)
    print("largest differences from the baseline: " + ", ".join(f"{k} {v:.3g}" for k, v in diff.items()))
    path = write_json(args.out / f"{args.name}.json", payload)
    print(f"wrote {path}")
    if args.page is not None:
        write_page(args.page, page(payload))
        print(f"wrote {args.page}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
