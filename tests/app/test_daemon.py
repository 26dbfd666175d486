"""The daemon: queues that count drops, keyframe selection, and `robotd run` as a service.

The service test starts the real `robotd run` in a subprocess with its base on a
pseudo-terminal fed with Kobuki packets, and a real AF_UNIX datagram socket as
NOTIFY_SOCKET: READY, STATUS and WATCHDOG while packets flow, no WATCHDOG once they stop,
STOPPING and a clean exit on SIGTERM, the run closed in the map.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import numpy as np
import pytest

from drivers.kobuki import protocol
from robotd.app.daemon import KeyframeSelector, SourceQueue, downsample
from robotd.io.store import MapStore


def test_live_queue_drops_oldest_and_counts():
    q = SourceQueue("floor", 3, lossless=False, wakeup=threading.Event())
    stop = threading.Event()
    for i in range(5):
        assert q.put(i, stop)
    assert q.dropped == 2
    assert [q.get_nowait() for _ in range(4)] == [2, 3, 4, None]


def test_lossless_queue_blocks_until_room_or_stop():
    q = SourceQueue("base", 1, lossless=True, wakeup=threading.Event())
    stop = threading.Event()
    assert q.put("a", stop)
    done: list[bool] = []
    t = threading.Thread(target=lambda: done.append(q.put("b", stop)))
    t.start()
    t.join(0.3)
    assert t.is_alive()  # blocked: the queue is full and nothing was dropped
    assert q.get_nowait() == "a"
    t.join(5.0)
    assert done == [True] and q.get_nowait() == "b" and q.dropped == 0
    assert q.put("c", stop)
    stop.set()
    assert q.put("d", stop) is False  # full and stopping: gives up instead of hanging


def test_keyframe_selector_by_distance_and_rotation():
    sel = KeyframeSelector(distance_m=0.1, rotation_rad=math.radians(10))
    assert sel.offer(np.array([0.0, 0.0, 0.0]))  # the first frame is always a keyframe
    assert not sel.offer(np.array([0.09, 0.0, 0.0]))
    assert sel.offer(np.array([0.06, 0.08, 0.0]))  # 0.1 m away (3-4-5)
    assert not sel.offer(np.array([0.06, 0.08, math.radians(9.9)]))
    assert sel.offer(np.array([0.06, 0.08, math.radians(-10.5)]))


def test_downsample_keeps_aspect():
    img = np.zeros((480, 640), np.uint8)
    assert downsample(img, 160).shape == (120, 160)
    assert downsample(img, 0) is None
    assert downsample(np.zeros((480, 640, 3), np.uint8), 160).shape == (120, 160)


def _packet(i: int) -> bytes:
    basic = protocol.BasicSensorData(
        timestamp_ms=(1000 + 20 * i) & 0xFFFF, bumper=0, wheel_drop=0, cliff=0,
        left_encoder=(100 + 10 * i) & 0xFFFF, right_encoder=(200 + 10 * i) & 0xFFFF,
        left_pwm=0, right_pwm=0, buttons=0, charger=0, battery_decivolts=160, overcurrent=0)
    inertial = protocol.InertialData(angle_centideg=0, angle_rate_centidegps=0)
    return protocol.encode_feedback(basic, inertial)


def _recv_until(sock: socket.socket, wanted: str, deadline_s: float) -> list[str]:
    """Datagrams received until one contains ``wanted`` (or the deadline passes)."""
    got: list[str] = []
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        sock.settimeout(max(0.01, end - time.monotonic()))
        try:
            msg = sock.recv(4096).decode()
        except socket.timeout:
            break
        got.append(msg)
        if wanted in msg:
            return got
    raise AssertionError(f"no {wanted!r} within {deadline_s} s; got {got}")


def test_service_notifies_pings_only_on_progress_and_stops_on_sigterm(tmp_path: Path):
    notify_path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(notify_path))
    master, slave = os.openpty()
    tty.setraw(slave)
    cfg = tmp_path / "robotd.toml"
    cfg.write_text(
        f'[base]\nport = "{os.ttyname(slave)}"\n'
        '[floor_camera]\nsource = "none"\n'
        f'[map]\npath = "{tmp_path / "map.sqlite"}"\n'
        '[daemon]\nstatus_interval_s = 0.2\n'
    )
    env = dict(os.environ, NOTIFY_SOCKET=str(notify_path), WATCHDOG_USEC="400000")
    proc = subprocess.Popen([sys.executable, "-m", "robotd.app.cli", "run", "--config", str(cfg)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    feeding = threading.Event()
    feeding.set()
    stop_writer = threading.Event()

    def writer() -> None:
        i = 0
        while not stop_writer.is_set():
            if feeding.is_set():
                os.write(master, _packet(i))
                i += 1
            stop_writer.wait(0.02)  # the base's 50 Hz, simulated hardware pacing

    w = threading.Thread(target=writer, daemon=True)
    try:
        _recv_until(sock, "READY=1", 20.0)
        w.start()
        msgs = _recv_until(sock, "WATCHDOG=1", 5.0)
        msgs += _recv_until(sock, "STATUS=odometry", 5.0)
        status = [m for m in msgs if m.startswith("STATUS=odometry")][-1]
        rate = float(status.split("odometry ")[1].split("/s")[0])
        assert 5.0 < rate < 80.0, status  # about 50 packets a second flowing through
        # Stop the base: the pipeline stalls, so the watchdog pings must stop too. One
        # more ping may be due for the progress made just before; none after that.
        feeding.clear()
        t0 = time.monotonic()
        pings: list[float] = []
        while time.monotonic() - t0 < 1.5:
            sock.settimeout(max(0.01, 1.5 - (time.monotonic() - t0)))
            try:
                if sock.recv(4096).decode() == "WATCHDOG=1":
                    pings.append(time.monotonic() - t0)
            except socket.timeout:
                break
        assert len(pings) <= 1 and all(p < 0.5 for p in pings), pings
        proc.send_signal(signal.SIGTERM)
        _recv_until(sock, "STOPPING=1", 10.0)
        assert proc.wait(15.0) == 0, proc.stderr.read().decode()
    finally:
        stop_writer.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        sock.close()
        os.close(master)
        os.close(slave)
    with MapStore.open(tmp_path / "map.sqlite", create=False) as store:
        runs = store.runs()
        assert len(runs) == 1 and runs[0].ended_ns is not None
        assert 'port = "' in runs[0].config


def test_run_with_a_missing_port_is_one_clear_line(tmp_path: Path):
    cfg = tmp_path / "robotd.toml"
    cfg.write_text('[base]\nport = "/dev/does-not-exist"\n[floor_camera]\nsource = "none"\n'
                   f'[map]\npath = "{tmp_path / "map.sqlite"}"\n')
    r = subprocess.run([sys.executable, "-m", "robotd.app.cli", "run", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "robotd: error: cannot open Kobuki port /dev/does-not-exist" in r.stderr
    assert "Traceback" not in r.stderr


def test_frames_held_at_the_end_of_input_are_finished(tmp_path: Path):
    """A frozen clock (virtual robot or replay at its end) never times a held frame out:
    finish() gives frames up to the newest odometry sample their (now final) pose and counts
    later ones as unsynced, so a run that ends on a frame never waits forever."""
    from robotd.app.daemon import Pipeline
    from robotd.app.service import build_odometry
    from robotd.base.clock import ManualClock
    from robotd.base.config import Config, replace
    from robotd.base.messages import Frame, WheelTicks

    cfg = replace(Config(), "base", driver="kobuki")
    clock = ManualClock(0)
    with MapStore.open(tmp_path / "map.sqlite", clock=clock) as store:
        run_id = store.begin_run("[test]")
        pipe = Pipeline(cfg, clock, build_odometry(cfg), store, run_id)
        for k in range(3):  # 1 cm per wheel message, 20 ms apart, straight ahead
            ticks = int(round(k * 0.01 / (2 * math.pi * 0.035) * 2578.33))
            pipe.on_base(WheelTicks(k * 20_000_000, ticks, ticks, 0))
        img = np.zeros((48, 64), np.uint8)
        pipe.on_frame(Frame(30_000_000, "floor", img, 0))  # after the settled stamp (20 ms)
        pipe.on_frame(Frame(55_000_000, "floor", img, 1))  # after the newest sample (40 ms)
        clock.set_ns(40_000_000)  # frozen at the last sample, as the virtual robot leaves it
        assert pipe.process_pending() == 0 and len(pipe.pending) == 2  # would wait forever
        assert pipe.finish() == 2 and not pipe.pending
        assert pipe.counters.keyframes == 1 and pipe.counters.frames_unsynced == 1
        kf = list(store.keyframes())[-1]
        assert kf.stamp_ns == 30_000_000
        assert kf.x_m == pytest.approx(0.015, abs=1e-3)  # halfway between 1 and 2 cm
