"""`robotd run`'s forward camera: [forward_camera] opens a V4L2 or DepthAI device whose frames
are named "forward", at the size of [forward_detector]'s camera model, only when the
detector is on."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pytest

import drivers.camera
from robotd.app.service import open_sources
from robotd.base.clock import ManualClock
from robotd.base.config import Config, replace
from robotd.base.errors import DriverError


def _cfg(tmp_path: Path, *, detector: bool, source: str = "v4l2") -> Config:
    cfg = replace(Config(), "base", driver="none")
    cfg = replace(cfg, "floor_camera", source="none")
    cfg = replace(replace(cfg, "forward_detector", enabled=detector), "forward_camera", width_px=320, height_px=240)
    return replace(cfg, "forward_camera", source=source, device=str(tmp_path / "video7"), fps=10.0)


def test_the_forward_camera_is_opened_through_the_real_device_check(tmp_path: Path) -> None:
    with pytest.raises(DriverError, match=r"video7 does not exist"):
        open_sources(_cfg(tmp_path, detector=True), ManualClock())


def test_the_forward_camera_has_the_detectors_size_and_its_frames_are_named_forward(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    made: list[dict[str, Any]] = []

    class Recorder:
        def __init__(self, device: str, **kw: Any) -> None:
            made.append(dict(kw, device=device))

        def close(self) -> None:
            pass

    monkeypatch.setattr(drivers.camera, "V4L2Camera", Recorder)
    sources = open_sources(_cfg(tmp_path, detector=True), ManualClock())
    assert list(sources) == ["forward"]
    (kw,) = made
    assert kw["name"] == "forward" and kw["device"] == str(tmp_path / "video7")
    assert (kw["width_px"], kw["height_px"], kw["fps"], kw["grey"]) == (320, 240, 10.0, True)


def test_without_the_detector_the_forward_camera_is_not_opened_and_the_log_says_so(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        assert open_sources(_cfg(tmp_path, detector=False), ManualClock()) == {}
    assert "[forward_detector] is off: the forward camera is not opened" in caplog.text


def test_an_unknown_forward_source_is_a_config_error_naming_the_key() -> None:
    from robotd.base.configfile import config_from_dict
    from robotd.base.errors import ConfigError

    with pytest.raises(ConfigError, match=r"\[forward_camera\] source"):
        config_from_dict({"forward_camera": {"source": "usb"}})
