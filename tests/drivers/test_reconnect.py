"""Reconnection, owned by the driver (drivers.base): the backoff, the gap accounting, and
the Kobuki port reopened by path.

A minimal backend shows the gap bookkeeping on a manual clock. The Kobuki test uses real
pseudo-terminals behind a symlink, as udev's ``/dev/kobuki`` is one: closing the pty's
master is an unplugged USB adapter (reads fail with EIO), a new pty behind the same
symlink is the adapter plugged back in.
"""

from __future__ import annotations

import logging
import os
import tty
from pathlib import Path

import pytest

from drivers.base import Driver
from drivers.kobuki.driver import KobukiDriver
from drivers.kobuki.protocol import BasicSensorData, InertialData, encode_feedback
from robotd.base.clock import ManualClock
from robotd.base.errors import DriverError
from robotd.base.messages import WheelTicks

S = 1_000_000_000


class _Flaky(Driver):
    """Hands out one integer per read while ``present``; raises while it is not."""

    def __init__(self, clock: ManualClock) -> None:
        super().__init__("flaky", clock=clock, initial_backoff_s=1.0, max_backoff_s=4.0)
        self.present = True
        self.opens = 0
        self.releases = 0
        self._start()

    def _open_internal(self) -> None:
        if not self.present:
            raise DriverError("not there")
        self.opens += 1

    def _release_internal(self) -> None:
        self.releases += 1

    def _read_internal(self, timeout_s: float):
        if not self.present:
            raise DriverError("gone")
        return self.opens


def test_a_lost_device_is_a_counted_gap_from_the_loss_to_the_next_message(caplog) -> None:
    clock = ManualClock(10 * S)
    drv = _Flaky(clock)
    assert drv.read(0.0) == [1]
    assert drv.stats()["losses"] == 0 and drv.stats()["connected"] == 1
    drv.present = False
    assert drv.read(0.0) == []  # lost: no exception out of read()
    assert drv.releases == 1 and drv.stats()["errors"] == 0
    clock.advance_ns(S)
    assert drv.read(0.0) == []  # attempt 1 s after the loss fails; next in 2 s
    clock.advance_ns(S + S // 2)
    assert drv.stats()["away_s"] == 2.5
    drv.present = True
    assert drv.read(0.0) == []  # not due yet (2 s after the failed attempt)
    clock.advance_ns(S // 2)
    with caplog.at_level(logging.WARNING, logger="drivers.base"):
        assert drv.read(0.0) == [2]  # reopened and read in one call
    st = drv.stats()
    assert (st["losses"], st["reopen_failures"], st["reconnects"], st["gaps"]) == (1, 1, 1, 1)
    assert st["last_gap_s"] == 3.0 and st["gap_s_total"] == 3.0 and st["away_s"] == 0.0
    assert "flaky driver back after 3.000 s without data (gap 1; 3.000 s in all)" in caplog.text

    drv.present = False  # a second gap adds up
    drv.read(0.0)
    drv.present = True
    clock.advance_ns(S)
    assert drv.read(0.0) == [3]
    st = drv.stats()
    assert st["gaps"] == 2 and st["last_gap_s"] == 1.0 and st["gap_s_total"] == 4.0
    drv.close()
    drv.close()
    assert drv.releases == 3  # two losses and one close


def test_a_driver_without_reconnection_still_raises() -> None:
    class Plain(Driver):
        def _read_internal(self, timeout_s: float):
            raise DriverError("broken")

    drv = Plain("plain")
    with pytest.raises(DriverError, match="broken"):
        drv.read(0.0)
    assert "losses" not in drv.stats() and drv.stats()["errors"] == 1


def _packet(i: int) -> bytes:
    basic = BasicSensorData(
        timestamp_ms=(1000 + 20 * i) & 0xFFFF, bumper=0, wheel_drop=0, cliff=0,
        left_encoder=(100 + 10 * i) & 0xFFFF, right_encoder=(200 + 10 * i) & 0xFFFF,
        left_pwm=0, right_pwm=0, buttons=0, charger=0, battery_decivolts=160, overcurrent=0)
    return encode_feedback(basic, InertialData(angle_centideg=0, angle_rate_centidegps=0))


def _plug(link: Path) -> tuple[int, int]:
    master, slave = os.openpty()
    tty.setraw(slave)
    tmp = link.with_suffix(".new")
    tmp.symlink_to(os.ttyname(slave))
    tmp.replace(link)
    return master, slave


def _wheels(drv: KobukiDriver, n: int) -> list[WheelTicks]:
    got: list[WheelTicks] = []
    for _ in range(200):
        got += [m for m in drv.read(0.05) if isinstance(m, WheelTicks)]
        if len(got) >= n:
            break
    return got


def test_the_kobuki_port_is_reopened_by_path_after_the_adapter_comes_back(tmp_path: Path) -> None:
    link = tmp_path / "kobuki"
    master, slave = _plug(link)
    clock = ManualClock(50 * S)
    drv = KobukiDriver(str(link), clock, initial_backoff_s=0.5, max_backoff_s=2.0)
    try:
        os.close(slave)  # only the driver holds the slave side now
        os.write(master, _packet(0) + _packet(1))
        assert len(_wheels(drv, 2)) == 2
        os.close(master)  # unplugged: the next read fails with EIO
        link.unlink()
        for _ in range(20):
            if drv.read(0.05) == [] and not drv.connected:
                break
        assert drv.stats()["losses"] == 1 and not drv.connected
        clock.advance_ns(S // 2)
        assert drv.read(0.0) == []  # the link is missing: the attempt fails
        assert drv.stats()["reopen_failures"] == 1
        master, slave = _plug(link)  # plugged back in, a new pty behind the same name
        os.close(slave)
        clock.advance_ns(S)
        assert drv.read(0.0) == [] and drv.connected  # reopened; nothing written yet
        assert drv.stats()["away_s"] == 1.5  # the gap lasts until data flows
        os.write(master, _packet(2))
        wheels = _wheels(drv, 1)
        st = drv.stats()
        assert len(wheels) == 1 and st["reconnects"] == 1 and st["connected"] == 1
        assert st["gaps"] == 1 and st["last_gap_s"] == 1.5
        assert wheels[0].left_ticks == 120  # the packet written after the replug
    finally:
        drv.close()
        os.close(master)
