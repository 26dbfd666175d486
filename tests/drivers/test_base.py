"""drivers.base (the Driver base class) and drivers.registry (backends by name)."""

from __future__ import annotations

import logging
import math
import sys

import numpy as np
import pytest

from drivers import registry
from drivers.base import Driver
from drivers.kobuki.driver import KobukiDriver
from drivers.kobuki.protocol import InertialData, RawGyroData, encode_feedback
from drivers.registry import BACKENDS, known_backends, open_driver, resolve
from robotd.base.clock import ManualClock
from robotd.base.config import BaseConfig, FloorCameraConfig
from robotd.base.errors import ConfigError, DriverError
from robotd.base.messages import Frame, WheelTicks, YawRate


class ScriptedDriver(Driver):
    """Returns (or raises) the scripted results in order; records the timeouts asked."""

    def __init__(self, script: list, name: str = "scripted") -> None:
        super().__init__(name)
        self.script = list(script)
        self.timeouts: list[float] = []
        self.close_calls = 0

    def _read_internal(self, timeout_s: float):
        self.timeouts.append(timeout_s)
        item = self.script.pop(0)
        if isinstance(item, Exception):
            raise item
        return item

    def _close_internal(self) -> None:
        self.close_calls += 1

    def _stats_internal(self) -> dict[str, int | float | str]:
        return {"scripted_left": len(self.script)}


TICKS = WheelTicks(10, 1, 2, 3)
YAW = YawRate(11, 0.25, "raw_gyro")
FRAME = Frame(12, "floor", np.zeros((2, 2), np.uint8), 0)


def test_read_always_returns_a_list():
    drv = ScriptedDriver([None, FRAME, [TICKS, YAW], []])
    assert drv.read(0.5) == []
    assert drv.read(0.0) == [FRAME]
    assert drv.read(0.1) == [TICKS, YAW]
    assert drv.read(0.1) == []
    assert drv.timeouts == [0.5, 0.0, 0.1, 0.1]


def test_counters_and_backend_stats_in_one_flat_mapping():
    drv = ScriptedDriver([None, [TICKS, YAW], FRAME, DriverError("gone"), None])
    drv.read(0.0)
    drv.read(0.0)
    drv.read(0.0)
    with pytest.raises(DriverError):
        drv.read(0.0)
    assert drv.stats() == {"name": "scripted", "reads": 4, "messages_out": 3,
                           "empty_reads": 1, "errors": 1, "scripted_left": 1}


def test_a_bad_timeout_is_refused_before_the_backend_is_asked():
    drv = ScriptedDriver([None])
    for bad in (-0.1, math.nan, math.inf, None):
        with pytest.raises(ValueError, match="timeout_s"):
            drv.read(bad)  # type: ignore[arg-type]
    assert drv.timeouts == []
    assert drv.stats()["reads"] == 0


def test_driver_error_is_counted_logged_once_per_message_and_reraised(caplog):
    errors = [DriverError("port vanished"), DriverError("port vanished"), DriverError("EIO")]
    drv = ScriptedDriver(errors, name="base")
    with caplog.at_level(logging.WARNING, logger="drivers.base"):
        for expected in errors:
            with pytest.raises(DriverError) as info:
                drv.read(0.0)
            assert info.value is expected
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == ["base driver: port vanished", "base driver: EIO"]
    assert drv.stats()["errors"] == 3


def test_other_exceptions_pass_through_uncounted():
    drv = ScriptedDriver([RuntimeError("bug")])
    with pytest.raises(RuntimeError, match="bug"):
        drv.read(0.0)
    assert drv.stats()["errors"] == 0


def test_close_twice_closes_the_device_once_and_read_after_close_raises():
    drv = ScriptedDriver([TICKS])
    assert not drv.closed
    drv.close()
    drv.close()
    assert drv.close_calls == 1 and drv.closed
    with pytest.raises(DriverError, match="scripted driver is closed"):
        drv.read(0.0)
    assert drv.timeouts == []


def test_every_driver_is_a_context_manager():
    with ScriptedDriver([]) as drv:
        assert isinstance(drv, ScriptedDriver)
    assert drv.close_calls == 1
    with pytest.raises(KeyError), ScriptedDriver([]) as failing:
        raise KeyError("inside")
    assert failing.close_calls == 1


# -- registry ----------------------------------------------------------------------------


def test_unknown_backend_names_the_known_ones():
    with pytest.raises(ConfigError, match=r"unknown base driver 'roomba'; known: can, kobuki, ros2"):
        open_driver("base", "roomba", BaseConfig(), ManualClock())
    with pytest.raises(ConfigError, match=r"unknown floor_camera driver 'gige'; known: depthai, ros2, v4l2"):
        open_driver("floor_camera", "gige", FloorCameraConfig(), ManualClock())
    with pytest.raises(ConfigError, match=r"no driver role 'lidar'; known roles: base, floor_camera, forward_camera, replay"):
        open_driver("lidar", "rplidar", None, ManualClock())


def test_the_depthai_floor_camera_without_a_device_is_one_clear_error():
    """Registered, importable, and on this host (no device) one line saying so."""
    dai = pytest.importorskip("depthai")
    if dai.Device.getAllAvailableDevices():
        pytest.skip("a DepthAI device is present")
    with pytest.raises(DriverError, match=r"^no DepthAI device found \(is the camera plugged in\?"):
        open_driver("floor_camera", "depthai", FloorCameraConfig(source="depthai"), ManualClock())


def test_a_backend_is_imported_only_when_chosen(monkeypatch):
    module = "tests.drivers._lazy_backend"
    monkeypatch.delitem(sys.modules, module, raising=False)
    monkeypatch.setitem(BACKENDS, ("base", "lazy"), f"{module}:open_fake")
    assert "lazy" in known_backends("base")
    with pytest.raises(ConfigError):
        open_driver("base", "nonexistent", None, ManualClock())
    assert module not in sys.modules  # a failed lookup imports nothing either
    drv = open_driver("base", "lazy", "rear", ManualClock())
    assert module in sys.modules
    assert isinstance(drv, Driver) and drv.name == "rear"


def test_a_backend_whose_module_cannot_be_imported_is_a_config_error(monkeypatch):
    monkeypatch.setitem(BACKENDS, ("base", "ghost"), "drivers.no_such_backend:open_ghost")
    with pytest.raises(ConfigError, match="'ghost' cannot be loaded.*no_such_backend"):
        open_driver("base", "ghost", None, ManualClock())


def test_every_registered_backend_resolves_to_a_callable():
    for role, name in BACKENDS:
        assert callable(resolve(role, name)), (role, name)
    assert registry.BACKENDS is BACKENDS


def test_kobuki_is_built_from_its_config_section():
    section = BaseConfig(port="loop://", yaw_source="inertial")
    with open_driver("base", "kobuki", section, ManualClock()) as drv:
        assert isinstance(drv, KobukiDriver) and drv.name == "base"
        assert drv.port.baudrate == section.baudrate
        drv.port.write(encode_feedback(InertialData(0, 250), RawGyroData(0, ((0, 0, 9),))))
        (yaw,) = drv.read(0.0)
        assert yaw.source == "inertial"  # the section's yaw_source, not the default raw_gyro


def test_v4l2_is_built_from_its_config_section(tmp_path):
    path = str(tmp_path / "video7")
    with pytest.raises(DriverError, match=f"camera device {path} does not exist"):
        open_driver("floor_camera", "v4l2", FloorCameraConfig(device=path), ManualClock())
