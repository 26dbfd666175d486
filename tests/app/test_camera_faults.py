"""Fault test: the floor camera unplugged and plugged back in while the daemon runs.

The whole daemon as `robotd run` assembles it, on the real clock, with real threads: the
base is the Kobuki driver on a pseudo-terminal fed 50 packets a second; the floor camera
is, in turn,

- the DepthAI driver on a host-only depthai pipeline whose ReplayVideo node plays a
  one-second video (no device: see tests/drivers/test_depthai_camera.py). The video's
  end closes the stream, which the driver takes for an unplugged camera; the file is
  then moved away (reopening fails, with backoff) and, 1.5 s later, back;
- the V4L2 driver on a simulated device at its OpenCV boundary
  (:class:`sim.cameras.device.PluggableV4L2Device`), unplugged after 30 frames and
  plugged back in 1.5 s later.

Checked: the base thread kept producing odometry during the gap, frames resumed after
the replug, and the gap (count and duration) is in STATUS (read from a real AF_UNIX
notify socket) and in the log, equal to the driver's own figures.

Marked slow: about 7 s of real time per backend. The STATUS fragment itself is checked
by hand first (fast).
"""

from __future__ import annotations

import logging
import os
import re
import socket
import threading
import time
import tty
from pathlib import Path

import cv2
import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from drivers.camera import V4L2Camera
from drivers.depthai_camera import DepthAICamera, DepthAISettings, replay_stream_opener
from drivers.kobuki.driver import KobukiDriver
from drivers.kobuki.protocol import BasicSensorData, InertialData, encode_feedback
from robotd.app.assemble import assemble_daemon, open_map
from robotd.app.daemon import Daemon, gap_text
from robotd.app.notify import Notifier
from robotd.app.pipeline import Pipeline
from robotd.base.clock import ManualClock, MonotonicClock
from robotd.base.config import Config, replace
from sim.cameras.device import PluggableV4L2Device

AWAY_S = 1.5
"""How long the camera stays unplugged, seconds."""


def test_status_names_each_source_that_lost_its_device() -> None:
    never = {"name": "base", "reads": 9, "losses": 0, "gaps": 0, "away_s": 0.0}
    away = {"losses": 1, "gaps": 0, "gap_s_total": 0.0, "last_gap_s": 0.0, "away_s": 2.25}
    back = {"losses": 2, "gaps": 2, "gap_s_total": 7.1, "last_gap_s": 4.0, "away_s": 0.0}
    both = {"losses": 3, "gaps": 2, "gap_s_total": 7.1, "last_gap_s": 4.0, "away_s": 0.5}
    assert gap_text({"base": never, "replay": {"reads": 3}}) == ""
    assert gap_text({"floor": away}) == "floor away 2.2 s"
    assert gap_text({"floor": back}) == "floor gaps 2 (7.100 s, last 4.000 s)"
    assert (gap_text({"base": both, "floor": back})
            == "base away 0.5 s, gaps 2 (7.100 s, last 4.000 s); floor gaps 2 (7.100 s, last 4.000 s)")
    stats = {"base": never, "floor": away}
    d = Daemon(ManualClock(0), Pipeline(), {}, Notifier(), wall_clock=ManualClock(0),
               driver_stats=lambda: stats)
    assert d.status_text(1.0) == ("odometry 0.0/s (0), frames 0.0/s (0), keyframes 0, stored 0, loops 0, "
                                  "drops 0, unsynced 0, floor away 2.2 s")
    stats["floor"] = never
    assert d.status_text(1.0).endswith("unsynced 0")  # nothing lost: the line is as before


def test_status_names_a_source_silent_since_the_start(caplog: pytest.LogCaptureFixture) -> None:
    """A base on the wrong port sends nothing and loses nothing: no gap to report, so the
    STATUS line names it as silent once the run is SILENT_AFTER_S old, and the log says so
    once."""
    from robotd.app.daemon import SILENT_AFTER_S

    class Quiet:
        def read(self, timeout_s: float) -> list:
            return []

        def close(self) -> None:
            pass

    d = Daemon(ManualClock(0), Pipeline(), {"base": Quiet(), "floor": Quiet()}, Notifier(),
               wall_clock=ManualClock(0))
    assert d.status_text(SILENT_AFTER_S - 0.5).endswith("unsynced 0")
    d.queues["floor"].put(object())
    with caplog.at_level("WARNING", logger="robotd.app.daemon"):
        assert d.status_text(7.2).endswith("unsynced 0, base silent (nothing in 7 s)")
        assert d.status_text(12.0).endswith("unsynced 0, base silent (nothing in 12 s)")
    warnings = [r.getMessage() for r in caplog.records if "no message" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].startswith("base: no message in the first 7 s")


def _packet(i: int) -> bytes:
    basic = BasicSensorData(
        timestamp_ms=(20 * i) & 0xFFFF, bumper=0, wheel_drop=0, cliff=0,
        left_encoder=(10 * i) & 0xFFFF, right_encoder=(10 * i) & 0xFFFF,
        left_pwm=0, right_pwm=0, buttons=0, charger=0, battery_decivolts=160, overcurrent=0)
    return encode_feedback(basic, InertialData(angle_centideg=0, angle_rate_centidegps=0))


def _feed(master: int, stop: threading.Event) -> None:
    """Kobuki feedback at 50 Hz until ``stop``."""
    i = 0
    start = time.monotonic()
    while not stop.is_set():
        os.write(master, _packet(i))
        i += 1
        stop.wait(max(0.0, start + 0.02 * i - time.monotonic()))


def _statuses(sock: socket.socket) -> list[str]:
    out = []
    sock.setblocking(False)
    while True:
        try:
            msg = sock.recv(4096).decode()
        except BlockingIOError:
            return out
        out += [line[len("STATUS="):] for line in msg.splitlines() if line.startswith("STATUS=")]


class _DepthAIUnplug:
    """The DepthAI driver on a replayed one-second video: the video's end closes the
    stream (the driver takes the camera for lost), then the file is moved away until
    the replug (reopening fails)."""

    lost_in_log = r"floor camera DepthAI .* lost \(the frame stream closed"

    def __init__(self, tmp_path: Path, clock: MonotonicClock) -> None:
        self.video = tmp_path / "floor.avi"
        self.away = tmp_path / "floor.unplugged"
        writer = cv2.VideoWriter(str(self.video), cv2.VideoWriter.fourcc(*"MJPG"), 30, (64, 48))
        for i in range(30):
            writer.write(np.full((48, 64, 3), 8 * i, np.uint8))
        writer.release()
        self.camera = DepthAICamera(DepthAISettings(width_px=64, height_px=48, fps=30.0),
                                    opener=replay_stream_opener(self.video), clock=clock,
                                    initial_backoff_s=0.1, max_backoff_s=0.4)

    def unplug_now(self, frames: int) -> bool:
        if self.camera.connected:
            return False
        self.video.rename(self.away)
        return True

    def replug(self) -> None:
        self.away.rename(self.video)


class _V4L2Unplug:
    """The V4L2 driver on a simulated device (its OpenCV boundary), unplugged once 30
    frames went through and plugged back in later."""

    lost_in_log = (r"floor camera /dev/video0 lost \(device gone: camera device /dev/video0 "
                   r"does not exist \(unplugged\)\)")

    def __init__(self, tmp_path: Path, clock: MonotonicClock) -> None:
        self.device = PluggableV4L2Device(lambda i: np.full((48, 64, 3), i % 256, np.uint8), 30.0)
        self.camera = V4L2Camera("/dev/video0", width_px=64, height_px=48, fps=30.0, grey=True,
                                 clock=clock, capture_factory=self.device.capture,
                                 device_check=self.device.check,
                                 initial_backoff_s=0.1, max_backoff_s=0.4)

    def unplug_now(self, frames: int) -> bool:
        if frames < 30:
            return False
        self.device.unplug()
        return True

    def replug(self) -> None:
        self.device.replug()


@pytest.mark.slow
@pytest.mark.parametrize("backend", [_DepthAIUnplug, _V4L2Unplug], ids=["depthai", "v4l2"])
def test_the_floor_camera_unplugged_and_replugged_while_odometry_runs(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        backend: type) -> None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify.sock"))
    master, slave = os.openpty()
    tty.setraw(slave)
    cfg = replace(Config(), "floor_detector", enabled=False)
    cfg = replace(cfg, "pose_graph", enabled=False)
    cfg = replace(cfg, "map", path=str(tmp_path / "map.sqlite"))
    cfg = replace(cfg, "calibration", path=str(tmp_path / "none.yml"))
    cfg = replace(cfg, "daemon", status_interval_s=0.2)
    clock = MonotonicClock()
    stop_feeding = threading.Event()
    feeder = threading.Thread(target=_feed, args=(master, stop_feeding), daemon=True)
    fault = backend(tmp_path, clock)
    camera = fault.camera
    marks: dict[str, float] = {}
    wheel_at: dict[str, int] = {}
    frames_at: dict[str, int] = {}
    try:
        with KobukiDriver(os.ttyname(slave), clock) as base, open_map(cfg) as store:
            drivers = {"base": base, "floor": camera}
            daemon = assemble_daemon(cfg, clock, drivers, store, Notifier(), lossless=False,
                                     driver_stats=lambda: {n: d.stats() for n, d in drivers.items()})
            counters = daemon.pipeline.counters

            lines: list[str] = []

            def step() -> bool:
                """The test's script, run by the daemon's main loop every turn (it also
                reads the notify socket, whose sender blocks when it is full)."""
                lines.extend(_statuses(sock))
                now = time.monotonic()
                if "lost" not in marks and fault.unplug_now(counters()["frames"]):
                    marks["lost"] = now
                    wheel_at["lost"] = counters()["wheel_msgs"]
                elif "lost" in marks and "back" not in marks and now - marks["lost"] >= AWAY_S:
                    fault.replug()
                    marks["back"] = now
                    wheel_at["back"] = counters()["wheel_msgs"]
                    frames_at["back"] = counters()["frames"]
                elif "back" in marks and "resumed" not in marks and camera.stats()["gaps"] == 1:
                    marks["resumed"] = now
                elif "resumed" in marks and now - marks["resumed"] >= 0.5:
                    return True
                return now - marks.get("start", now) > 30.0  # a safety net, never reached

            marks["start"] = time.monotonic()
            feeder.start()
            with caplog.at_level(logging.INFO):
                report = daemon.run(stop_when=step)
    finally:
        stop_feeding.set()
        feeder.join()
        camera.close()
        os.close(master)
        os.close(slave)
    assert "resumed" in marks, marks
    cam = report.driver_stats["floor"]
    base_stats = report.driver_stats["base"]

    # The base thread kept producing while the camera was away (50 Hz for >= 1.5 s).
    assert wheel_at["back"] - wheel_at["lost"] >= 50, wheel_at
    assert base_stats["losses"] == 0 and report.stopped_by == "finished"
    # Frames resumed after the replug.
    assert report.counters["frames"] > frames_at["back"] >= 25
    assert report.counters["frames"] - frames_at["back"] >= 5
    # One gap, at least as long as the camera was away, and not much longer (backoff <= 0.4 s).
    assert cam["losses"] == 1 and cam["gaps"] == 1 and cam["reconnects"] == 1
    assert cam["reopen_failures"] >= 2
    gap_s = float(cam["last_gap_s"])
    assert AWAY_S - 0.2 <= gap_s <= AWAY_S + 3.0, gap_s  # detecting the loss takes a read
    # STATUS said the camera was away, then the gap with the driver's own figures.
    lines += _statuses(sock)
    assert any(re.search(r"\bfloor away \d+\.\d s\b", line) for line in lines), lines
    assert any(f"floor gaps 1 ({gap_s:.3f} s, last {gap_s:.3f} s)" in line for line in lines), lines
    assert not any("base away" in line or "base gaps" in line for line in lines)
    # And the log: the loss, then the return with the gap's length.
    assert re.search(fault.lost_in_log, caplog.text), caplog.text
    assert f"back after {gap_s:.3f} s without data (gap 1; {gap_s:.3f} s in all)" in caplog.text
    sock.close()
