"""The daemon: its main loop on an injected clock, and `robotd run` as a service.

The in-process tests drive :class:`Daemon` turn by turn with a manual wall clock and a
real AF_UNIX datagram socket as NOTIFY_SOCKET. The service test starts the real
`robotd run` in a subprocess with its base on a pseudo-terminal fed with Kobuki packets:
READY, STATUS counting exactly the packets written, STOPPING and a clean exit on SIGTERM,
the run closed in the map.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import tty
from pathlib import Path

import pytest

from drivers.kobuki import protocol
from robotd.io.store import MapStore


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


def test_service_notifies_counts_and_stops_on_sigterm(tmp_path: Path):
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
    try:
        _recv_until(sock, "READY=1", 20.0)
        for i in range(200):  # four seconds of base data, written at once
            os.write(master, _packet(i))
        msgs = _recv_until(sock, "STATUS=odometry", 20.0)
        for _ in range(200):
            if "(200), frames" in msgs[-1]:
                break
            msgs += _recv_until(sock, "STATUS=odometry", 5.0)
        assert "odometry" in msgs[-1] and "(200), frames" in msgs[-1], msgs[-1]
        assert any(m == "WATCHDOG=1" for m in msgs)  # progress was made, so it was fed
        proc.send_signal(signal.SIGTERM)
        _recv_until(sock, "STOPPING=1", 10.0)
        assert proc.wait(15.0) == 0, proc.stderr.read().decode()
    finally:
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
    assert not (tmp_path / "map.sqlite").exists()  # no map is made for a run that cannot start



@pytest.mark.parametrize(("setting", "message"), [
    ('[base]\ndriver = "none"\n[floor_camera]\nsource = "v4l2"\ndevice = "/dev/does-not-exist"\n',
     "robotd: error: camera device /dev/does-not-exist does not exist"),
    ('[base]\ndriver = "none"\n[floor_camera]\nsource = "depthai"\n',
     "robotd: error: no DepthAI device found (is the camera plugged in?"),
    ('[base]\ndriver = "none"\n[floor_camera]\nsource = "none"\n[calibration]\npath = "{bad}"\n',
     "robotd: error: {bad}: not valid OpenCV YAML"),
])
def test_run_that_cannot_start_makes_no_map(tmp_path: Path, setting: str, message: str):
    """A missing camera, or a calibration file that does not read, is found before the map
    is made (the calibration file used to be read after it)."""
    bad = tmp_path / "calibration.yml"
    bad.write_text("junk: [\n")
    cfg = tmp_path / "robotd.toml"
    cfg.write_text(setting.format(bad=bad) + f'[map]\npath = "{tmp_path / "map.sqlite"}"\n')
    r = subprocess.run([sys.executable, "-m", "robotd.app.cli", "run", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 2, r.stderr
    (line,) = r.stderr.splitlines()
    assert line.startswith(message.format(bad=bad))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.yml", "robotd.toml"]


class _Counter:
    """A stage that counts the integers it is fed."""

    name = "count"

    def __init__(self) -> None:
        self.n = 0

    def subscriptions(self):
        return {int: self.on_int}

    def on_int(self, _: int) -> None:
        self.n += 1


class _ListSource:
    """A driver that hands out a fixed list, then nothing."""

    def __init__(self, items: list) -> None:
        self.items = list(items)
        self.closed = 0

    def read(self, timeout_s: float):
        return [self.items.pop(0)] if self.items else None

    def close(self) -> None:
        self.closed += 1


def _datagrams(sock: socket.socket) -> list[str]:
    out = []
    sock.setblocking(False)
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


def test_watchdog_is_fed_only_while_the_pipeline_makes_progress(tmp_path, monkeypatch):
    """Turn by turn on a manual wall clock: a ping per interval while inputs flow, none
    while the pipeline stalls, STATUS when due; no wall-clock waiting."""
    from robotd.app.daemon import Daemon
    from robotd.app.notify import Notifier
    from robotd.app.pipeline import Pipeline
    from robotd.base.clock import ManualClock

    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify.sock"))
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")  # pings due every 1 s (half of it)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    wall = ManualClock(0)
    pipe = Pipeline()
    counter = pipe.add(_Counter())
    idle = _ListSource([])  # a source that has nothing to say: only the fed items are progress
    d = Daemon(ManualClock(0), pipe, {"idle": idle}, Notifier(), status_interval_s=3.0, wall_clock=wall)
    try:
        d.start()
        assert _datagrams(sock)[0].startswith("READY=1")
        for second in range(1, 4):  # progress every second: one ping each
            pipe.feed(second)
            wall.advance_ns(1_000_000_000)
            d.turn()
        got = _datagrams(sock)
        assert got.count("WATCHDOG=1") == 3 and counter.n == 3
        assert [m for m in got if m.startswith("STATUS=")] == [
            "STATUS=odometry 0.0/s (0), frames 0.0/s (0), keyframes 0, stored 0, loops 0, drops 0, unsynced 0"]
        for _ in range(5):  # stalled for 5 s: the pings stop, so systemd would restart us
            wall.advance_ns(1_000_000_000)
            d.turn()
        assert "WATCHDOG=1" not in _datagrams(sock)
        pipe.feed(99)
        wall.advance_ns(1_000_000_000)
        d.turn()
        assert "WATCHDOG=1" in _datagrams(sock)
    finally:
        d.shutdown()
        sock.close()


def test_shutdown_handles_what_the_sources_already_read(tmp_path):
    """Items already queued when the daemon stops still reach the pipeline."""
    from robotd.app.daemon import Daemon
    from robotd.app.notify import Notifier
    from robotd.app.pipeline import Pipeline
    from robotd.base.clock import ManualClock

    pipe = Pipeline()
    counter = pipe.add(_Counter())
    src = _ListSource(list(range(50)))
    d = Daemon(ManualClock(0), pipe, {"list": src}, Notifier(), lossless=True, wall_clock=ManualClock(0))
    report = d.run(stop_when=lambda: not src.items and d.queues["list"].qsize() == 0)
    assert counter.n == 50 and report.counters["inputs"] == 50
    assert report.queue_drops == {"list": 0} and report.stopped_by == "finished"


class _FailingSource(_ListSource):
    """Hands out its list, then fails the way a recording tee on a full disk does."""

    def __init__(self, items: list, error: Exception) -> None:
        super().__init__(items)
        self.error = error

    def read(self, timeout_s: float):
        if not self.items:
            raise self.error
        return super().read(timeout_s)


@pytest.mark.parametrize("kind", ["recording", "driver"])
def test_a_source_failing_for_good_stops_the_run(tmp_path, kind):
    """A recording that cannot be written, or a driver that raises (drivers reconnect
    themselves, so a DriverError out of read() means it cannot go on), stops the daemon,
    which still handles what was read, ends the run in the map, and raises the error;
    before, the source thread died and the daemon ran on forever."""
    from robotd.app.daemon import Daemon
    from robotd.app.notify import Notifier
    from robotd.app.pipeline import Pipeline
    from robotd.base.clock import ManualClock
    from robotd.base.errors import DriverError, RecordingError

    pipe = Pipeline()
    counter = pipe.add(_Counter())
    error = (RecordingError("x.mcap.partial: cannot write: No space left on device")
             if kind == "recording" else DriverError("floor camera: gave up"))
    src = _FailingSource(list(range(20)), error)
    with MapStore.open(tmp_path / "map.sqlite", clock=ManualClock(7)) as store:
        run_id = store.begin_run("")
        d = Daemon(ManualClock(0), pipe, {"floor": src}, Notifier(), store=store, run_id=run_id,
                   lossless=True, wall_clock=ManualClock(0))
        deadline = time.monotonic() + 10.0  # the old daemon never stopped by itself
        with pytest.raises(type(error)) as failure:
            d.run(stop_when=lambda: time.monotonic() > deadline)
        assert failure.value is error and time.monotonic() < deadline
        assert counter.n == 20
        assert d.threads["floor"].fatal is error
        assert d.report().stopped_by == f"floor failed: {error}"
        assert store.runs()[0].ended_ns == 0  # the run is closed (the daemon's clock)


def test_the_next_start_says_a_killed_run_did_not_end_cleanly(tmp_path: Path) -> None:
    """`robotd run` killed with SIGKILL left ended_ns NULL and nothing said so later."""
    cfg = tmp_path / "robotd.toml"
    path = tmp_path / "map.sqlite"
    cfg.write_text('[base]\ndriver = "none"\n[floor_camera]\nsource = "none"\n'
                   f'[map]\npath = "{path}"\n')

    def start(stop: signal.Signals) -> str:
        proc = subprocess.Popen([sys.executable, "-m", "robotd.app.cli", "run", "--config", str(cfg)],
                                stderr=subprocess.PIPE, text=True)
        lines = []
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append(line)
            if "robotd running" in line:
                proc.send_signal(stop)
                break
        lines.append(proc.communicate(timeout=60)[1])
        assert proc.returncode == (-signal.SIGKILL if stop == signal.SIGKILL else 0), lines
        return "".join(lines)

    start(signal.SIGKILL)
    with MapStore.open(path, create=False) as store:
        assert [r.ended_ns for r in store.runs()] == [None]
    err = start(signal.SIGTERM)
    assert (f"WARNING robotd.app.assemble: map {path}: run 1 did not end cleanly (killed or power "
            "cut?); its 0 keyframes are kept and it is marked as ended at its last one") in err
    with MapStore.open(path, create=False) as store:
        first, second = store.runs()
        assert first.ended_ns == first.started_ns and not first.ended_cleanly
        assert second.ended_cleanly
    assert "did not end cleanly" not in start(signal.SIGTERM)  # said once


_SIGNAL_WHILE_HOLDING_WAKEUP = """
import signal
from robotd.app.daemon import Daemon
from robotd.app.notify import Notifier
from robotd.app.pipeline import Pipeline
from robotd.base.clock import ManualClock

d = Daemon(ManualClock(0), Pipeline(), {}, Notifier(), wall_clock=ManualClock(0))
d.start()
# The main loop spends its idle time in wakeup.wait()/clear(), holding the Event's lock
# for a few bytecodes each time; a SIGTERM taken there runs the handler right here.
with d.wakeup._cond:
    signal.raise_signal(signal.SIGTERM)
turns = 0
while not d.stopping_requested() and turns < 100:
    d.turn()
    turns += 1
d.shutdown()
print(d.report().stopped_by, turns)
"""


def test_sigterm_while_the_main_loop_holds_the_wakeup_lock_stops_the_daemon():
    """The cause of the flaky service test: the SIGTERM handler set threading Events, so
    a signal that landed while the main thread was inside ``wakeup.wait()`` deadlocked it
    on the Event's own lock (and it ignored every later SIGTERM). The handler now only
    assigns attributes; the old one hangs here until the timeout."""
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(root))
    env.pop("NOTIFY_SOCKET", None)
    r = subprocess.run([sys.executable, "-c", _SIGNAL_WHILE_HOLDING_WAKEUP], env=env, cwd=root,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["SIGTERM", "0"]  # stopped before a single turn


_SIGTERM_DURING_START_UP = """
import signal, sys
import robotd.app.service as service
from robotd.base.configfile import load_config

real_open_map = service.open_map

def open_map_then_sigterm(cfg, **kw):  # systemctl stop while the map is being opened
    store = real_open_map(cfg, **kw)
    signal.raise_signal(signal.SIGTERM)
    return store

service.open_map = open_map_then_sigterm
sys.exit(service.run_service(load_config(sys.argv[1])))
"""


def test_sigterm_during_start_up_ends_the_run_cleanly(tmp_path: Path) -> None:
    """A SIGTERM before the daemon's handlers exist (systemctl stop during a start: here
    right after the map is opened) used to kill the process by Python's default action,
    in the middle of making its run; now it is held, the run opens and closes cleanly and
    the exit status is 0."""
    cfg = tmp_path / "robotd.toml"
    path = tmp_path / "map.sqlite"
    cfg.write_text('[base]\ndriver = "none"\n[floor_camera]\nsource = "none"\n'
                   f'[map]\npath = "{path}"\n')
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(root))
    env.pop("NOTIFY_SOCKET", None)
    r = subprocess.run([sys.executable, "-c", _SIGTERM_DURING_START_UP, str(cfg)], env=env, cwd=root,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    with MapStore.open(path, create=False) as store:
        (run,) = store.runs()
        assert run.ended_cleanly
