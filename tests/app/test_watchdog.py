"""The watchdog on real threads and the real clock: WATCHDOG=1 keeps coming while the
pipeline works and stops when it stalls, so systemd (WatchdogSec=) restarts a wedged
daemon.

A fake systemd: an AF_UNIX datagram socket as $NOTIFY_SOCKET, WATCHDOG_USEC=200 ms (a
ping due every 100 ms). The daemon runs its own main loop in a thread, fed by a source
thread. Two ways to stall: a stage blocks inside its handler (a stuck solve: the main
loop itself is stuck), and the source blocks in its read (a hung serial port: the main
loop turns but nothing comes in). Absence of pings can only be shown by waiting, so
each stalled phase listens for 1 s (ten ping intervals).
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from pathlib import Path

import pytest

from robotd.app.daemon import Daemon
from robotd.app.notify import Notifier
from robotd.app.pipeline import Pipeline
from robotd.base.clock import ManualClock

QUIET_S = 1.0  # ten ping intervals


class _Ticker:
    """A source handing out increasing ints; while ``hang`` is set its read blocks."""

    def __init__(self) -> None:
        self.n = 0
        self.hang = threading.Event()
        self.resume = threading.Event()

    def read(self, timeout_s: float):
        if self.hang.is_set():
            self.resume.wait(30.0)
        time.sleep(0.002)
        self.n += 1
        return self.n

    def close(self) -> None:
        self.resume.set()


class _Wedge:
    """A stage that takes ints and, while ``wedge`` is set, blocks in its handler."""

    name = "wedge"

    def __init__(self) -> None:
        self.wedge = threading.Event()
        self.entered = threading.Event()
        self.release = threading.Event()
        self.n = 0

    def subscriptions(self):
        return {int: self.on_int}

    def on_int(self, _: int) -> None:
        self.n += 1
        if self.wedge.is_set():
            self.entered.set()
            self.release.wait(30.0)


@pytest.fixture
def systemd(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify.sock"))
    monkeypatch.setenv("WATCHDOG_USEC", "200000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    yield sock
    sock.close()


def _pings(sock: socket.socket, seconds: float) -> int:
    """WATCHDOG=1 datagrams received during ``seconds`` (reading all the while)."""
    n = 0
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            n += sock.recv(4096) == b"WATCHDOG=1"
        except socket.timeout:
            break
    return n


def _until_pings(sock: socket.socket, count: int, deadline_s: float = 20.0) -> None:
    got = 0
    end = time.monotonic() + deadline_s
    while got < count and time.monotonic() < end:
        got += _pings(sock, 0.1)
    assert got >= count, f"only {got} WATCHDOG=1 in {deadline_s} s"


def _drain(sock: socket.socket) -> None:
    _pings(sock, 0.0)
    sock.setblocking(False)
    try:
        while True:
            sock.recv(4096)
    except BlockingIOError:
        pass
    sock.setblocking(True)


def _start(pipe: Pipeline, sources: dict) -> tuple[Daemon, threading.Event, threading.Thread]:
    d = Daemon(ManualClock(0), pipe, sources, Notifier(), status_interval_s=3600.0)
    done = threading.Event()
    t = threading.Thread(target=d.run, kwargs={"stop_when": done.is_set}, daemon=True)
    t.start()
    return d, done, t


def test_pings_stop_while_a_stage_is_wedged_and_resume_after(systemd):
    pipe = Pipeline()
    wedge = pipe.add(_Wedge())
    d, done, thread = _start(pipe, {"ticks": _Ticker()})
    try:
        _until_pings(systemd, 3)  # healthy: fed
        wedge.wedge.set()
        assert wedge.entered.wait(20.0)  # the main loop is now stuck inside the stage
        _drain(systemd)
        assert _pings(systemd, QUIET_S) == 0
        wedge.wedge.clear()
        wedge.release.set()
        _until_pings(systemd, 2)  # progressing again: fed again
    finally:
        done.set()
        wedge.release.set()
        thread.join(30.0)
    assert not thread.is_alive()


def test_pings_stop_while_the_source_hangs_and_the_loop_idles(systemd, caplog):
    caplog.set_level(logging.INFO, logger="robotd.app.notify")
    pipe = Pipeline()
    wedge = pipe.add(_Wedge())
    ticker = _Ticker()
    d, done, thread = _start(pipe, {"ticks": ticker})
    try:
        _until_pings(systemd, 3)
        ticker.hang.set()
        end = time.monotonic() + 20.0
        while time.monotonic() < end and (d._gate is None or d._gate.stalled_ns() < QUIET_S * 1e9):
            _pings(systemd, 0.05)
        turns = d._turns
        assert _pings(systemd, QUIET_S) == 0
        assert d._turns > turns  # the loop kept turning: it is the gate that withheld
        assert any("withholding the watchdog ping" in r.getMessage() for r in caplog.records)
        ticker.hang.clear()
        ticker.resume.set()
        _until_pings(systemd, 2)
        assert any("watchdog pings resumed" in r.getMessage() for r in caplog.records)
    finally:
        done.set()
        ticker.resume.set()
        thread.join(30.0)
    assert not thread.is_alive() and wedge.n > 0


def test_a_daemon_without_sources_keeps_feeding_the_watchdog(systemd):
    """`robotd run` with no base and no camera only keeps the map open: nothing will ever
    come in, and the gate used to withhold every ping, so systemd restarted it every
    WatchdogSec. Its progress is now the main loop turning."""
    d, done, thread = _start(Pipeline(), {})
    try:
        _until_pings(systemd, 5)
    finally:
        done.set()
        thread.join(30.0)
