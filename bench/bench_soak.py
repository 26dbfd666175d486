"""Soak: the whole daemon over many laps of the virtual robot, for memory and time trends.

The virtual robot drives one lap of the ``figure8`` route (it ends exactly at its start
pose, 26 m, 57 s, 1719 floor frames) through the daemon once, recorded to MCAP (rendering
costs ~8-30 ms of CPU per frame, so it is paid once). The soak then replays that lap
again and again, as fast as the CPU allows, through one daemon built by
:func:`robotd.app.assemble.assemble_daemon` with the default stages (odometry, keyframes,
floor descriptors and map queries, the live pose graph, the map writer) and the demo's
shipped loop thresholds. Lap ``k`` is the recording with every stamp moved on by ``k``
laps and the raw 16-bit wheel counters moved on by ``k`` times the lap's count (the lap
starts and ends standing still at the same pose, so the seam is continuous): to the
daemon it is one long drive of the same figure eight. 100,000 frames are 59 laps.

Recorded per lap, in the same process: wall time per frame, the resident memory
(``/proc/self/statm``), keyframes, loop edges accepted, candidates above the threshold;
at the end: frames dropped (queue drops, frames without odometry), and the map's size per
keyframe against the descriptor mode's byte bound.

The daemon localises over mapped ground (``[pose_graph] localise_mapped``, as the service's
``systemd/robotd.toml`` sets it): from the second lap on, keyframes over the figure eight
are matched against the map and not stored, so the map, the floor index and the pose graph
stop growing. ``--no-localise`` stores every keyframe of every lap, as the code's default
does: then the map and the graph grow with the laps, and iSAM2's cost per keyframe with
them (each pass is tied to the earlier ones by loops).

Resident memory is recorded twice per lap: as the kernel counts it, and after glibc's
``malloc_trim(0)`` (what the process really holds; glibc's free lists grow and shrink with
the allocation pattern). Per-frame time is recorded as wall time and as this process's CPU
time, which a loaded machine disturbs less.

What it is not: every lap shows the daemon the same images (one recording), so it says
nothing about detection quality.

Run: ``.venv/bin/python bench/bench_soak.py`` (100,000 frames, keyframes every 0.2 m;
``--full``: 300,000 frames at the daemon's own keyframe spacing, ``[keyframes] distance_m``), ``--frames N``,
``--keyframe-distance M``, ``--work DIR`` (keeps the lap recording for the next run).
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import math
import os
import sqlite3
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

try:
    from bench.common import machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json

from robotd.base.clock import ManualClock
from robotd.base.config import KeyframeConfig
from robotd.base.messages import Frame, KeyframeStored, Link, WheelTicks, YawRate

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "soak.json"
ROUTE = "figure8"
_PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_mb() -> float:
    """Resident memory of this process, MB (``/proc/self/statm``, second field)."""
    with open("/proc/self/statm", encoding="ascii") as f:
        return int(f.read().split()[1]) * _PAGE / 1e6


def trimmed_rss_mb() -> float:
    """Resident memory after glibc's ``malloc_trim(0)`` hands freed heap pages back to the
    kernel: what the process still holds, without the free lists that glibc keeps (they
    grow and shrink with the allocation pattern, not with live data). The plain RSS is
    recorded beside it."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:  # not glibc
        pass
    return rss_mb()


class LoopedReplay:
    """A daemon source that replays one recorded lap ``laps`` times as one drive.

    Lap ``k`` hands out the recording's messages with ``k * lap_ns`` added to every stamp
    and, on :class:`WheelTicks`, ``k`` times the lap's raw-counter change added modulo
    2^16, so the counters run on across the seam as they would on the robot. ``clock``
    (the daemon's) follows the stamps handed out, as :class:`ReplayDriver` does.
    """

    def __init__(self, path: Path, clock: ManualClock, laps: int) -> None:
        from drivers.recording.replay import ReplayDriver

        self._driver_cls = ReplayDriver
        self.path = path
        self.clock = clock
        self.laps = laps
        self.lap = 0
        self._inner_clock = ManualClock()
        self._replay = ReplayDriver(path, self._inner_clock)
        span = self._replay.time_range_ns
        if span is None:
            raise ValueError(f"{path}: empty recording")
        self.t0_ns = span[0]
        self.lap_ns = span[1] - span[0] + 20_000_000  # one base period after the last message
        self._first_ticks: tuple[int, int] | None = None
        self._last_ticks: tuple[int, int] | None = None
        self._lap_ticks = (0, 0)
        self.frames = 0
        self.handed_out = 0
        self.finished = False

    def lap_of(self, stamp_ns: int) -> int:
        """The lap a shifted stamp belongs to."""
        return (stamp_ns - self.t0_ns) // self.lap_ns

    def read(self, timeout_s: float) -> list[Any] | None:
        if self.finished:
            time.sleep(min(timeout_s, 0.05))  # nothing more; do not spin against the pipeline
            return None
        msgs = self._replay.read(timeout_s)
        if not msgs and self._replay.finished:
            self._next_lap()
            if self.finished:
                return None
            msgs = self._replay.read(timeout_s)
        out = [self._shift(m) for m in msgs]
        self.handed_out += len(out)
        if out:
            newest = max(m.stamp_ns for m in out)
            if newest > self.clock.now_ns():
                self.clock.set_ns(newest)
        return out

    def _next_lap(self) -> None:
        if self.lap == 0:
            assert self._first_ticks is not None and self._last_ticks is not None
            self._lap_ticks = tuple((b - a) & 0xFFFF for a, b in zip(self._first_ticks, self._last_ticks))
        self._replay.close()
        self.lap += 1
        if self.lap >= self.laps:
            self.finished = True
            return
        self._inner_clock = ManualClock()
        self._replay = self._driver_cls(self.path, self._inner_clock)

    def _shift(self, m: Any) -> Any:
        dt = self.lap * self.lap_ns
        if isinstance(m, WheelTicks):
            if self.lap == 0:
                self._first_ticks = self._first_ticks or (m.left_ticks, m.right_ticks)
                self._last_ticks = (m.left_ticks, m.right_ticks)
            k = self.lap
            return dataclasses.replace(m, stamp_ns=m.stamp_ns + dt,
                                       left_ticks=(m.left_ticks + k * self._lap_ticks[0]) & 0xFFFF,
                                       right_ticks=(m.right_ticks + k * self._lap_ticks[1]) & 0xFFFF)
        if isinstance(m, Frame):
            self.frames += 1
            return dataclasses.replace(m, stamp_ns=m.stamp_ns + dt, seq=self.frames)
        if isinstance(m, YawRate):
            return dataclasses.replace(m, stamp_ns=m.stamp_ns + dt)
        return m

    def close(self) -> None:
        self._replay.close()

    def stats(self) -> dict[str, int]:
        return {"laps": self.lap, "frames": self.frames, "handed_out": self.handed_out}


class SoakProbe:
    """Pipeline observer: per lap, wall time, frames, keyframes, loop edges and RSS."""

    name = "soak_probe"

    def __init__(self, source: LoopedReplay, counters: Any) -> None:
        self.source = source
        self._pipeline_counters = counters  # the pipeline's counters() (read at each lap's end)
        self.rows: list[dict[str, Any]] = []
        self._lap = 0
        self._frames = 0
        self._t0 = time.perf_counter()
        self._cpu0 = time.process_time()
        self.frames = 0
        self.keyframes = 0
        self.loops = 0

    def subscriptions(self) -> dict[type, Any]:
        return {Frame: self.on_frame, KeyframeStored: self.on_keyframe, Link: self.on_link}

    def on_keyframe(self, _: KeyframeStored) -> None:
        self.keyframes += 1

    def on_link(self, link: Link) -> None:
        self.loops += int(link.kind == "loop")

    def on_frame(self, frame: Frame) -> None:
        lap = self.source.lap_of(frame.stamp_ns)
        if lap != self._lap:
            self.close_lap()
            self._lap = lap
        self.frames += 1
        self._frames += 1

    def close_lap(self) -> None:
        """Record the lap just ended (also called once at the end of the run)."""
        now, cpu_now = time.perf_counter(), time.process_time()
        c = self._pipeline_counters()
        wall, cpu = now - self._t0, cpu_now - self._cpu0
        self.rows.append({"lap": self._lap, "frames": self._frames, "wall_s": wall,
                          "ms_per_frame": 1e3 * wall / self._frames if self._frames else math.nan,
                          "cpu_ms_per_frame": 1e3 * cpu / self._frames if self._frames else math.nan,
                          "keyframes_not_stored": c.get("keyframes_not_stored", 0),
                          "localise_matches": c.get("localise_matches_accepted", 0),
                          "rss_mb": rss_mb(), "rss_trimmed_mb": trimmed_rss_mb(),
                          "keyframes_total": self.keyframes,
                          "loops_total": self.loops,
                          "above_threshold_total": c.get("loop_candidates_above_threshold", 0)})
        self._t0, self._cpu0 = now, cpu_now
        self._frames = 0
        r = self.rows[-1]
        print(f"soak: lap {r['lap']} frames {r['frames']} {r['ms_per_frame']:.2f} ms/frame "
              f"(CPU {r['cpu_ms_per_frame']:.2f}) "
              f"RSS {r['rss_mb']:.1f} MB (trimmed {r['rss_trimmed_mb']:.1f}) keyframes {r['keyframes_total']} "
              f"loop edges {r['loops_total']}",
              file=sys.stderr, flush=True)  # a run stopped early still leaves its laps


def record_lap(work: Path, seed: int) -> Path:
    """One lap of the figure eight, recorded through the daemon (kept in ``work``)."""
    from robotd.app.demo import run_demo, shipped_calibration
    from robotd.base.config import Config, replace

    lap = work / f"lap-{ROUTE}-seed{seed}.mcap"
    if lap.exists():
        return lap
    cfg = replace(Config(), "calibration", path=str(shipped_calibration()))
    t0 = time.perf_counter()
    run_demo(cfg, out=work / "lap-demo", route=ROUTE, seed=seed, plot=False, record=lap)
    print(f"recorded one lap of {ROUTE} in {time.perf_counter() - t0:.0f} s -> {lap}", file=sys.stderr)
    return lap


def map_sizes(path: Path, mode: int) -> dict[str, Any]:
    """The map's bytes per keyframe: descriptor (against the mode's bound), stored image,
    and the whole file (with its WAL)."""
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        n, desc_avg, desc_max, img_avg = con.execute(
            "SELECT count(*), avg(length(descriptor)), max(length(descriptor)), "
            "avg(length(image)) FROM keyframes").fetchone()
        loops = con.execute("SELECT count(*) FROM links WHERE kind = 'loop'").fetchone()[0]
    finally:
        con.close()
    files = sum(p.stat().st_size for p in (path, Path(f"{path}-wal")) if p.exists())
    return {"keyframes": n, "descriptor_bytes_mean": desc_avg, "descriptor_bytes_max": desc_max,
            "descriptor_bound_bytes": 512 << (mode - 1), "image_bytes_mean": img_avg,
            "file_bytes": files, "file_bytes_per_keyframe": files / n if n else None,
            "loop_links": loops}


def soak(lap: Path, work: Path, frames: int | None, keyframe_distance_m: float,
         laps: int | None = None, localise: bool = True) -> dict[str, Any]:
    """Replay ``lap`` until ``frames`` frames (or ``laps`` laps) went through one daemon;
    the figures."""
    from robotd.app.assemble import assemble_daemon, open_map
    from robotd.app.demo import shipped_calibration
    from robotd.app.notify import Notifier
    from robotd.base.config import Config, replace, with_virtual_floor_camera
    from robotd.app.service import replay_finished

    cfg = replace(Config(), "calibration", path=str(shipped_calibration()))
    cfg = with_virtual_floor_camera(cfg)
    cfg = replace(cfg, "keyframes", distance_m=keyframe_distance_m)
    cfg = replace(cfg, "pose_graph", localise_mapped=localise)
    map_path = work / "soak.sqlite"
    cfg = replace(cfg, "map", path=str(map_path))
    for p in (map_path, Path(f"{map_path}-wal"), Path(f"{map_path}-shm")):
        p.unlink(missing_ok=True)
    clock = ManualClock()
    lap_frames = _frames_in(lap)
    if laps is None:
        laps = max(1, math.ceil((frames or 0) / lap_frames))
    source = LoopedReplay(lap, clock, laps)
    clock.set_ns(source.t0_ns)
    rss0 = rss_mb()
    with open_map(cfg, clock=clock) as store:
        daemon = assemble_daemon(cfg, clock, {"replay": source}, store, Notifier(), lossless=True,
                                 driver_stats=lambda: {"replay": source.stats()})
        probe = SoakProbe(source, daemon.pipeline.counters)
        daemon.pipeline.add(probe)
        t0 = time.perf_counter()
        report = daemon.run(stop_when=lambda: replay_finished(source, daemon))
        wall = time.perf_counter() - t0
        probe.close_lap()
    c = report.counters
    return {"laps": laps, "frames_per_lap": lap_frames, "frames_handed_out": source.frames,
            "frames_processed": c.get("frames", 0), "frames_unsynced": c.get("frames_unsynced", 0),
            "queue_drops": report.queue_drops, "keyframes": c.get("keyframes", 0),
            "keyframes_stored": c.get("keyframes_stored", 0),
            "loop_edges": c.get("links_loop", 0),
            "keyframes_not_stored": c.get("keyframes_not_stored", 0),
            "relocalisations": c.get("localise_matches_accepted", 0),
            "relocalisations_failed_gate": c.get("localise_matches_failed_gate", 0),
            "mapped_ground_left": c.get("localise_left_new_ground", 0) + c.get("localise_left_unlocalised", 0),
            "above_threshold": c.get("loop_candidates_above_threshold", 0),
            "wall_s": wall, "rss_mb_before_daemon": rss0, "laps_table": probe.rows,
            "map": map_sizes(map_path, cfg.floor_detector.descriptor_mode),
            "keyframe_distance_m": keyframe_distance_m, "config_mode": cfg.floor_detector.descriptor_mode}


def _frames_in(lap: Path) -> int:
    """Floor frames in the recording, from its MCAP summary statistics."""
    from mcap.reader import make_reader

    with open(lap, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None, f"{lap}: no MCAP summary"
    topics = {cid: ch.topic for cid, ch in summary.channels.items()}
    return sum(n for cid, n in summary.statistics.channel_message_counts.items()
               if topics.get(cid) == "/floor_camera/image/compressed")


def trend(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Lap 2 (the first after warm-up) against the last full lap, and the least-squares
    slope of RSS over laps 2..last (MB per lap and per 1000 keyframes)."""
    import numpy as np

    full = [r for r in rows[1:] if r["frames"] > 0]
    if len(rows) > 2 and rows[-1]["frames"] < rows[1]["frames"]:
        full = full[:-1]  # a partial last lap is not comparable
    if len(full) < 2:
        return {}
    first, last = full[0], full[-1]
    laps = np.array([r["lap"] for r in full], dtype=float)

    def slope(key: str) -> float:
        return float(np.polyfit(laps, np.array([r[key] for r in full], dtype=float), 1)[0])

    return {"first_lap": first["lap"], "last_lap": last["lap"],
            "rss_mb_first": first["rss_mb"], "rss_mb_last": last["rss_mb"],
            "rss_trimmed_mb_first": first["rss_trimmed_mb"], "rss_trimmed_mb_last": last["rss_trimmed_mb"],
            "ms_per_frame_first": first["ms_per_frame"], "ms_per_frame_last": last["ms_per_frame"],
            "cpu_ms_per_frame_first": first["cpu_ms_per_frame"],
            "cpu_ms_per_frame_last": last["cpu_ms_per_frame"],
            "cpu_ms_per_frame_ratio_last_to_first": last["cpu_ms_per_frame"] / first["cpu_ms_per_frame"],
            "rss_slope_mb_per_lap": slope("rss_mb"), "rss_trimmed_slope_mb_per_lap": slope("rss_trimmed_mb"),
            "cpu_ms_per_frame_slope_per_lap": slope("cpu_ms_per_frame"),
            "keyframes_per_lap_last": last["keyframes_total"] - full[-2]["keyframes_total"]}


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=None, help="frames to soak (default 100000)")
    p.add_argument("--laps", type=int, default=None, help="soak this many laps instead")
    p.add_argument("--keyframe-distance", type=float, default=None, metavar="M",
                   help="[keyframes] distance_m of the soak (default 0.2)")
    p.add_argument("--full", action="store_true",
                   help="300000 frames at the daemon's default keyframe spacing ([keyframes] distance_m)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--work", type=Path, default=None, help="folder for the lap recording and map")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--no-localise", action="store_true",
                   help="store every keyframe on every lap ([pose_graph] localise_mapped = false): "
                        "the map and the graph grow with the distance driven")
    args = p.parse_args(argv)
    frames = args.frames or (300_000 if args.full else 100_000)
    distance = args.keyframe_distance or (KeyframeConfig().distance_m if args.full else 0.2)
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="robotd-soak-")
        work = Path(tmp.name)
    else:
        work = args.work
        work.mkdir(parents=True, exist_ok=True)
    try:
        lap = record_lap(work, args.seed)
        result = soak(lap, work, frames, distance, laps=args.laps, localise=not args.no_localise)
    finally:
        if tmp is not None:
            tmp.cleanup()
    result["trend"] = trend(result["laps_table"])
    result["machine"] = machine_info()
    result["args"] = {"frames": frames, "laps": args.laps, "keyframe_distance_m": distance,
                      "localise_mapped": not args.no_localise,
                      "seed": args.seed}
    print_table(["lap", "frames", "ms/frame", "CPU ms/frame", "RSS MB", "RSS trimmed", "keyframes",
                 "not stored", "relocalised", "loop edges", "above thr."],
                [[r["lap"], r["frames"], round(r["ms_per_frame"], 2), round(r["cpu_ms_per_frame"], 2),
                  round(r["rss_mb"], 1), round(r["rss_trimmed_mb"], 1), r["keyframes_total"],
                  r["keyframes_not_stored"], r["localise_matches"], r["loops_total"],
                  r["above_threshold_total"]]
                 for r in result["laps_table"]])
    m, t = result["map"], result["trend"]
    print(f"\nframes {result['frames_processed']} processed of {result['frames_handed_out']} handed out, "
          f"{result['laps']} laps, {result['wall_s']:.0f} s; unsynced {result['frames_unsynced']}, "
          f"queue drops {sum(result['queue_drops'].values())}")
    print(f"keyframes {result['keyframes']} taken, {result['keyframes_stored']} stored; "
          f"loop edges {result['loop_edges']}, "
          f"candidates above threshold {result['above_threshold']}; over mapped ground: "
          f"{result['keyframes_not_stored']} keyframes not stored, {result['relocalisations']} "
          f"re-localisations ({result['relocalisations_failed_gate']} matches refused by the gate), "
          f"left {result['mapped_ground_left']} times")
    print(f"map: {m['file_bytes'] / 1e6:.1f} MB, {m['file_bytes_per_keyframe']:.0f} B per keyframe; "
          f"descriptor mean {m['descriptor_bytes_mean']:.0f} B, max {m['descriptor_bytes_max']} B "
          f"(bound {m['descriptor_bound_bytes']} B); stored image mean {m['image_bytes_mean']:.0f} B")
    if t:
        print(f"lap {t['first_lap']} -> lap {t['last_lap']}: RSS {t['rss_mb_first']:.1f} -> "
              f"{t['rss_mb_last']:.1f} MB (slope {t['rss_slope_mb_per_lap']:+.2f} MB/lap), trimmed "
              f"{t['rss_trimmed_mb_first']:.1f} -> {t['rss_trimmed_mb_last']:.1f} MB "
              f"({t['rss_trimmed_slope_mb_per_lap']:+.2f} MB/lap); CPU {t['cpu_ms_per_frame_first']:.2f} -> "
              f"{t['cpu_ms_per_frame_last']:.2f} ms/frame (x{t['cpu_ms_per_frame_ratio_last_to_first']:.2f}, "
              f"{t['cpu_ms_per_frame_slope_per_lap']:+.3f} ms/frame per lap); keyframes added in the last "
              f"lap {t['keyframes_per_lap_last']}")
    print(f"wrote {write_json(args.out, result)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
