"""Tests of robotd.app.notify against a real AF_UNIX datagram socket playing systemd."""

from __future__ import annotations

import logging
import os
import socket
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from robotd.base.clock import ManualClock
from robotd.app.notify import Notifier, WatchdogGate

S = 1_000_000_000  # ns per second


@pytest.fixture
def notify_socket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[socket.socket]:
    """A bound datagram socket with NOTIFY_SOCKET pointing at it; non-blocking, so a
    missing message shows as BlockingIOError instead of a hang."""
    for name in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
        monkeypatch.delenv(name, raising=False)
    path = tmp_path / "notify.sock"
    short_dir = None
    if len(str(path)) > 100:  # sun_path holds 108 bytes
        short_dir = tempfile.TemporaryDirectory(prefix="rn", dir="/tmp")
        path = Path(short_dir.name) / "n.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    try:
        yield sock
    finally:
        sock.close()
        if short_dir is not None:
            short_dir.cleanup()


def _received(sock: socket.socket) -> list[str]:
    """Every datagram queued on the socket (sendmsg on AF_UNIX queues before returning)."""
    messages = []
    while True:
        try:
            messages.append(sock.recv(4096).decode())
        except BlockingIOError:
            return messages


def test_messages_arrive_verbatim(notify_socket: socket.socket) -> None:
    notifier = Notifier()
    assert notifier.enabled
    assert notifier.ready()
    assert notifier.status("fusing odometry, 12 keyframes")
    assert notifier.watchdog()
    assert notifier.stopping()
    assert notifier.extend_timeout(2_500_000_001)  # rounds up to whole microseconds
    assert _received(notify_socket) == [
        "READY=1",
        "STATUS=fusing odometry, 12 keyframes",
        "WATCHDOG=1",
        "STOPPING=1",
        "EXTEND_TIMEOUT_USEC=2500001",
    ]


def test_ready_with_status_is_one_datagram_and_newlines_cannot_inject(
    notify_socket: socket.socket,
) -> None:
    notifier = Notifier()
    notifier.ready(status="map loaded")
    notifier.status("line one\nWATCHDOG=1")
    assert _received(notify_socket) == [
        "READY=1\nSTATUS=map loaded",
        "STATUS=line one WATCHDOG=1",
    ]


def test_abstract_socket(monkeypatch: pytest.MonkeyPatch) -> None:
    name = f"robotd-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
    try:
        assert Notifier().ready()
        assert _received(sock) == ["READY=1"]
    finally:
        sock.close()


def test_disabled_outside_systemd(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    notifier = Notifier()
    assert not notifier.enabled
    assert notifier.ready() is False
    assert notifier.watchdog() is False


def test_a_vanished_socket_is_logged_not_raised(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "gone.sock"))
    with caplog.at_level(logging.WARNING, logger="robotd.app.notify"):
        assert Notifier().status("x") is False
    assert "gone.sock" in caplog.text


@pytest.mark.parametrize(
    ("usec", "pid", "timeout_ns"),
    [
        ("10000000", "self", 10 * S),
        ("10000000", None, 10 * S),
        ("10000000", "other", None),  # inherited by a process that is not the service
        ("0", "self", None),
        ("ten", "self", None),
        ("10000000", "x", None),
        (None, "self", None),
    ],
)
def test_watchdog_timeout_follows_sd_watchdog_enabled(
    monkeypatch: pytest.MonkeyPatch, usec: str | None, pid: str | None, timeout_ns: int | None
) -> None:
    for name, value in (("WATCHDOG_USEC", usec), ("WATCHDOG_PID", pid)):
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            value = {"self": str(os.getpid()), "other": str(os.getpid() + 1)}.get(value, value)
            monkeypatch.setenv(name, value)
    notifier = Notifier()
    assert notifier.watchdog_timeout_ns() == timeout_ns
    expected_interval = None if timeout_ns is None else timeout_ns // 2
    assert notifier.watchdog_interval_ns() == expected_interval


def test_gate_pings_only_after_progress_and_at_most_once_per_interval(
    notify_socket: socket.socket, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", str(10_000_000))  # WatchdogSec=10s
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    clock = ManualClock(100 * S)
    gate = Notifier().watchdog_gate(clock)
    assert gate.interval_ns == 5 * S

    assert gate.tick(0) is False  # nothing due yet
    clock.advance_ns(6 * S)
    assert gate.tick(0) is False  # due, but no progress: withheld
    assert _received(notify_socket) == []
    assert gate.stalled_ns() == 6 * S

    assert gate.tick(1) is True  # progress and due
    assert _received(notify_socket) == ["WATCHDOG=1"]
    clock.advance_ns(1 * S)
    assert gate.tick(2) is False  # progress, but only 1 s since the last ping
    clock.advance_ns(4 * S)
    assert gate.tick(2) is True  # the progress at 1 s still counts
    clock.advance_ns(6 * S)
    assert gate.tick(2) is False  # stalled since the last ping
    clock.advance_ns(60 * S)
    assert gate.tick(2) is False  # still stalled: systemd will restart us
    assert gate.stalled_ns() == 70 * S  # since the counter became 2
    assert _received(notify_socket) == ["WATCHDOG=1"]
    assert gate.pings == 2


def test_gate_without_watchdog_never_pings(notify_socket: socket.socket) -> None:
    clock = ManualClock()
    gate = WatchdogGate(Notifier(), clock)
    assert not gate.enabled
    for progress in range(1, 5):
        clock.advance_ns(100 * S)
        assert gate.tick(progress) is False
    assert _received(notify_socket) == []
