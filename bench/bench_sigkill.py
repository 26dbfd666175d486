"""SIGKILL during map writes, many times: is the map whole, and is every acknowledged
keyframe in it?

Each round starts ``robotd replay`` (a separate process, the real CLI) on one recording
into one map file that all rounds share, waits for READY on a real ``AF_UNIX`` notify
socket, lets it write keyframes for a random time, and kills it with SIGKILL. The
daemon's STATUS lines (every 0.1 s here) say ``stored N``: the first N keyframes of its
run are committed (see ``Daemon.status_text``); at ``--log-level debug`` it also logs
``keyframe K committed (run R, N stored)`` after each commit, the finer acknowledgement
used here (the larger of the two counts). After each kill:

- ``PRAGMA integrity_check`` says ``ok``, and so does the project's own check: the map
  opens with :meth:`MapStore.open` (``inspect_file``: header, ``quick_check``, schema)
  read-only, every keyframe and link reads back, every link joins stored keyframes;
- the killed run holds at least the N keyframes it acknowledged last;
- the next round's start says the killed run did not end cleanly (its log line), and the
  last killed run is found unfinished by ``mark_unfinished_runs`` after the rounds.

Usage: ``python bench/bench_sigkill.py [--kills 100] [--seed 0]`` (writes JSON under
``bench/results/``); the slow test ``tests/app/test_sigkill.py`` runs a few rounds.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
_STORED = re.compile(r"\bstored (\d+)\b")
_COMMITTED = re.compile(r"keyframe \d+ committed \(run (\d+), (\d+) stored\)")


@dataclass
class Round:
    """One start of the daemon: killed or not, and what was checked after it."""

    delay_s: float
    killed: bool
    """SIGKILLed before its run recorded its end (a kill that lands while the process
    exits after ending its run is a clean round)."""
    acked: int
    """Largest ``stored N`` the daemon sent before it died."""
    in_map: int
    """Keyframes of its run found in the map after the kill."""
    run_id: int
    integrity: str
    """``PRAGMA integrity_check``'s answer (``ok``) or the project's check's error."""
    previous_reported_unfinished: bool | None
    """Its start said the previous (killed) run did not end cleanly; None if the
    previous round was not killed or there was none."""

    @property
    def lost(self) -> int:
        return max(0, self.acked - self.in_map)


@dataclass
class Report:
    rounds: list[Round] = field(default_factory=list)
    last_found_unfinished: bool | None = None

    @property
    def kills(self) -> int:
        return sum(r.killed for r in self.rounds)

    @property
    def integrity_failures(self) -> int:
        return sum(r.integrity != "ok" for r in self.rounds)

    @property
    def acked_lost(self) -> int:
        return sum(r.lost for r in self.rounds)

    @property
    def acked_total(self) -> int:
        return sum(r.acked for r in self.rounds if r.killed)

    @property
    def unreported_unfinished(self) -> int:
        return sum(r.previous_reported_unfinished is False for r in self.rounds)


def make_recording(path: Path, duration_s: float = 30.0, seed: int = 0, fps: float = 15.0) -> int:
    """A recording of the virtual robot's base (Kobuki ticks and gyro) and floor camera
    on the square route, written directly (no daemon); returns the frames written."""
    from drivers.recording.writer import RecordingWriter
    from robotd.base.camera import FloorCameraModel
    from robotd.base.messages import Frame, WheelTicks
    from sim.cameras.floor import FloorRenderer, RenderParams
    from sim.emulators.kobuki import simulate_kobuki
    from sim.route import MotionLimits, build_route, plan_motion
    from sim.sensors import BaseSensorParams
    from sim.world.floor import ImageFloor

    rng = np.random.default_rng(seed)
    motion = plan_motion(build_route("square"), MotionLimits()).truncated(duration_s)
    base = simulate_kobuki(motion, BaseSensorParams(), rng)
    noise = rng.random((3000, 3000)).astype(np.float32)
    texture = cv2.normalize(cv2.GaussianBlur(noise, (0, 0), 3.0) + 0.3 * noise, None, 0, 255,
                            cv2.NORM_MINMAX).astype(np.uint8)
    floor = ImageFloor(texture, metres_per_px=0.002, origin_xy_m=(-1.5, 2.5))
    renderer = FloorRenderer(floor, FloorCameraModel.default(), RenderParams(), rng)
    items: list[tuple[int, int, object]] = [(m.stamp_ns, 0, m) for m in base.messages()]
    for j, t in enumerate(np.arange(0.0, motion.duration_s, 1.0 / fps)):
        v, w = motion.velocity_at(t)
        items.append((int(round(t * 1e9)), 1, Frame(int(round(t * 1e9)), "floor",
                                                    renderer.render(motion.pose_at(t), v, w, t), j)))
    items.sort(key=lambda i: (i[0], i[1]))
    frames = 0
    with RecordingWriter(path, image_format="jpeg", jpeg_quality=90) as w:
        for _, kind, m in items:
            if kind == 1:
                w.write_frame(m)  # type: ignore[arg-type]
                frames += 1
            elif isinstance(m, WheelTicks):
                w.write_wheel_ticks(m)
            else:
                w.write_yaw_rate(m)  # type: ignore[arg-type]
    return frames


def check_map(map_path: Path, run_id: int | None = None) -> tuple[str, int, int]:
    """``(integrity, keyframes of run_id (of the last run when None), that run's id)``.

    ``integrity`` is ``"ok"`` when ``PRAGMA integrity_check`` says so and the project's
    own checks pass, else what failed."""
    from robotd.base.errors import MapStoreError
    from robotd.io.store import MapStore

    raw = sqlite3.connect(map_path)
    try:
        answer = raw.execute("PRAGMA integrity_check").fetchall()
        dangling = raw.execute(
            "SELECT count(*) FROM links WHERE from_id NOT IN (SELECT id FROM keyframes)"
            " OR to_id NOT IN (SELECT id FROM keyframes)").fetchone()[0]
    except sqlite3.DatabaseError as exc:
        return f"sqlite: {exc}", 0, -1
    finally:
        raw.close()
    if answer != [("ok",)]:
        return f"integrity_check: {answer}", 0, -1
    if dangling:
        return f"{dangling} links join keyframes that are not stored", 0, -1
    try:
        with MapStore.open(map_path, create=False, read_only=True) as store:
            runs = store.runs()
            rid = runs[-1].id if run_id is None else run_id
            n = 0
            for kf in store.keyframes(run_id=rid):
                n += 1
                if kf.descriptor is None:
                    return f"keyframe {kf.id} has no descriptor", n, rid
            store.links()
            if n and store.keyframe_image(kf.id) is None:
                return f"keyframe {kf.id}'s image does not decode", n, rid
            return "ok", n, rid
    except MapStoreError as exc:
        return f"MapStore: {exc}", 0, -1


def _run_ended(map_path: Path, run_id: int) -> bool:
    """Whether run ``run_id`` recorded its end in the map (``runs.ended_ns`` set)."""
    raw = sqlite3.connect(map_path)
    try:
        row = raw.execute("SELECT ended_ns FROM runs WHERE id = ?", (int(run_id),)).fetchone()
    except sqlite3.DatabaseError:
        return False
    finally:
        raw.close()
    return row is not None and row[0] is not None


def _recv_all(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(65536).decode(errors="replace"))
        except BlockingIOError:
            return out


def kill_rounds(recording: Path, map_path: Path, rounds: int, *, seed: int = 0,
                max_delay_s: float = 6.0, work: Path | None = None) -> Report:
    """Start ``robotd replay`` ``rounds`` times into ``map_path``, SIGKILL each at a random
    moment after READY (uniform in 0 .. ``max_delay_s``), and check the map after each."""
    rng = np.random.default_rng(seed)
    work = Path(tempfile.mkdtemp(prefix="sigkill-")) if work is None else work
    work.mkdir(parents=True, exist_ok=True)
    config = work / "robotd.toml"
    config.write_text("[daemon]\nstatus_interval_s = 0.1\n"
                      f"[calibration]\npath = \"{work / 'none.yml'}\"\n")
    sock_path = work / "notify.sock"
    report = Report()
    previous_killed_run: int | None = None
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(REPO_ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]), "NOTIFY_SOCKET": str(sock_path)}
    for i in range(rounds):
        sock_path.unlink(missing_ok=True)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(str(sock_path))
        sock.setblocking(False)
        log_path = work / f"round{i}.log"
        try:
            with open(log_path, "w") as log_file:
                proc = subprocess.Popen(
                    [sys.executable, "-m", "robotd.app.cli", "--log-level", "debug", "replay",
                     str(recording), "--map", str(map_path), "--config", str(config)],
                    stdout=subprocess.DEVNULL, stderr=log_file, env=env, cwd=work)
                msgs: list[str] = []
                deadline = time.monotonic() + 120.0
                while not any("READY=1" in m for m in msgs):
                    if proc.poll() is not None or time.monotonic() > deadline:
                        proc.kill()
                        proc.wait()
                        raise RuntimeError(f"round {i}: no READY (see {log_path})")
                    time.sleep(0.01)
                    msgs += _recv_all(sock)
                delay = float(rng.uniform(0.0, max_delay_s))
                until = time.monotonic() + delay
                while time.monotonic() < until and proc.poll() is None:
                    time.sleep(0.005)
                killed = proc.poll() is None
                if killed:
                    proc.kill()  # SIGKILL
                proc.wait()
                msgs += _recv_all(sock)
        finally:
            sock.close()
        integrity, in_map, run_id = check_map(map_path)
        if killed and _run_ended(map_path, run_id):
            killed = False  # the kill landed after the run recorded its end (the process was exiting)
        text = log_path.read_text(errors="replace")
        acked = max([int(m.group(1)) for s in msgs for m in [_STORED.search(s)] if m]
                    + [int(m.group(2)) for m in _COMMITTED.finditer(text) if int(m.group(1)) == run_id]
                    + [0])
        reported = None
        if previous_killed_run is not None:
            reported = f"run {previous_killed_run} did not end cleanly" in text
        report.rounds.append(Round(delay, killed, acked, in_map, run_id, integrity, reported))
        previous_killed_run = run_id if killed else None
    if previous_killed_run is not None:
        from robotd.io.store import MapStore

        probe = work / "probe.sqlite"
        for suffix in ("", "-wal", "-shm"):
            src = Path(str(map_path) + suffix)
            if src.exists():
                shutil.copyfile(src, Path(str(probe) + suffix))
        with MapStore.open(probe, create=False) as store:
            report.last_found_unfinished = previous_killed_run in [r.id for r, _ in store.mark_unfinished_runs()]
    return report


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    try:
        from bench.common import machine_info, print_table, write_json
    except ImportError:  # run as a script: bench/ is on sys.path
        from common import machine_info, print_table, write_json  # type: ignore[no-redef]

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kills", type=int, default=100, help="rounds (each killed unless it ends first)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=30.0, help="recording length, s")
    p.add_argument("--max-delay", type=float, default=6.0, help="latest kill after READY, s")
    p.add_argument("--out", type=Path, default=REPO_ROOT / "bench" / "results" / "sigkill.json")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="sigkill-") as tmp:
        work = Path(tmp)
        frames = make_recording(work / "drive.mcap", args.duration, args.seed)
        t0 = time.monotonic()
        rep = kill_rounds(work / "drive.mcap", work / "map.sqlite", args.kills, seed=args.seed,
                          max_delay_s=args.max_delay, work=work)
        wall = time.monotonic() - t0
    print_table(["rounds", "kills", "integrity failures", "acked keyframes (killed runs)",
                 "acked lost", "kill not reported at next start", "last kill found unfinished"],
                [[len(rep.rounds), rep.kills, rep.integrity_failures, rep.acked_total, rep.acked_lost,
                  rep.unreported_unfinished, rep.last_found_unfinished]])
    write_json(args.out, {"machine": machine_info(), "frames": frames, "wall_s": wall,
                          "kills": rep.kills, "integrity_failures": rep.integrity_failures,
                          "acked_total": rep.acked_total, "acked_lost": rep.acked_lost,
                          "unreported_unfinished": rep.unreported_unfinished,
                          "last_found_unfinished": rep.last_found_unfinished,
                          "rounds": [asdict(r) for r in rep.rounds]})
    ok = rep.integrity_failures == 0 and rep.acked_lost == 0 and rep.unreported_unfinished == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
