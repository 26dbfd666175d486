"""SIGHUP reloads the config: live keys reach the running stages, the others are logged as
needing a restart, and a broken file changes nothing and is one clear error.

The daemon is the real one (assembled from a config file, its stages as `robotd run`
builds them) in this process's main thread; the signal is a real SIGHUP to ourselves,
taken by the daemon's handler and acted on at the next turn of its main loop.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import socket
from pathlib import Path

import pytest

from robotd.app.assemble import assemble_daemon, load_calibration
from robotd.app.notify import Notifier
from robotd.app.reload import LIVE_KEYS, ConfigReloader, changed_keys
from robotd.base.clock import ManualClock
from robotd.base.config import Config, live_keys, replace
from robotd.base.configfile import load_config
from robotd.io.calibfile import CalibrationFile, LoopThresholds, write_calibration
from robotd.io.store import MapStore


def _thresholds(mode4: float) -> CalibrationFile:
    return CalibrationFile(loop=LoopThresholds(thresholds=(None, None, None, mode4, None, None)))


def _config(tmp_path: Path, extra: str = "") -> str:
    return ('[base]\nport = "/dev/kobuki"\n'
            f'[calibration]\npath = "{tmp_path / "calibration.yml"}"\n'
            f'[map]\npath = "{tmp_path / "map.sqlite"}"\n' + extra)


@pytest.fixture
def running(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A daemon assembled from ``robotd.toml`` with a reloader, started (handlers on),
    with a notify socket; yields (daemon, reloader, socket, config path)."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "n.sock"))
    sock.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "n.sock"))
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    write_calibration(tmp_path / "calibration.yml", _thresholds(40.0))
    path = tmp_path / "robotd.toml"
    path.write_text(_config(tmp_path))
    cfg = load_config(path)
    calibration = load_calibration(cfg)
    store = MapStore.open(cfg.map.path)
    daemon = assemble_daemon(cfg, ManualClock(0), {}, store, Notifier(), lossless=True,
                             calibration=calibration, load_calibration_file=False)
    reloader = ConfigReloader(path, cfg, calibration)
    daemon.on_reload = reloader
    root_level = logging.getLogger().level
    daemon.start()
    try:
        yield daemon, reloader, sock, path
    finally:
        daemon.shutdown()
        store.close()
        sock.close()
        logging.getLogger().setLevel(root_level)


def _datagrams(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


def _hup(daemon) -> None:
    os.kill(os.getpid(), signal.SIGHUP)
    daemon.turn()


def test_sighup_applies_live_keys_and_reports_restart_keys(running, tmp_path, caplog):
    daemon, reloader, sock, path = running
    caplog.set_level(logging.INFO, logger="robotd.app.reload")
    keyframes, floor, graph = (daemon.pipeline.stage(n) for n in ("keyframes", "floor", "graph"))
    assert (floor.detector.threshold, graph.gate_chi2, keyframes.selector.distance_m) == (
        40.0, 16.27, Config().keyframes.distance_m)
    _datagrams(sock)
    path.write_text(_config(tmp_path, '[keyframes]\ndistance_m = 0.1\nrotation_deg = 20.0\n'
                                      '[floor_detector]\nshortlist = 12\ndescriptor_mode = 5\n'
                                      '[pose_graph]\ngate_chi2 = 9.0\n'
                                      '[daemon]\nstatus_interval_s = 1.5\nlog_level = "warning"\n')
                    .replace('"/dev/kobuki"', '"/dev/ttyUSB7"'))
    write_calibration(tmp_path / "calibration.yml", _thresholds(55.5))
    _hup(daemon)

    assert daemon.reloads == 1
    assert keyframes.selector.distance_m == 0.1
    assert keyframes.selector.rotation_rad == pytest.approx(math.radians(20.0))
    assert floor.detector.params.shortlist == 12
    assert floor.detector.params.descriptor_mode == 4  # needs a restart: not applied
    assert floor.detector.threshold == 55.5
    assert graph.gate_chi2 == 9.0
    assert daemon.status_interval_s == 1.5
    assert logging.getLogger().level == logging.WARNING
    (line,) = [r.getMessage() for r in caplog.records if r.name == "robotd.app.reload"]
    assert line == (
        f"reloaded {path}: applied live: [keyframes] distance_m = 0.1, [keyframes] rotation_deg = 20.0, "
        "[floor_detector] shortlist = 12, [pose_graph] gate_chi2 = 9.0, "
        "[daemon] status_interval_s = 1.5, [daemon] log_level = 'warning', "
        "loop threshold (mode 4) 40.0 -> 55.5; "
        "need a restart (not applied): [base] port, [floor_detector] descriptor_mode")
    got = _datagrams(sock)
    assert got[0].startswith("RELOADING=1\nMONOTONIC_USEC=") and got[1] == "READY=1"
    # The running config holds the live values and the old restart-only ones.
    assert reloader.config.base.port == "/dev/kobuki" and reloader.config.pose_graph.gate_chi2 == 9.0

    caplog.clear()
    _hup(daemon)  # nothing new: only the pending restart is said again
    (line,) = [r.getMessage() for r in caplog.records if r.name == "robotd.app.reload"]
    assert line.endswith("applied live: none; need a restart (not applied): [base] port, "
                         "[floor_detector] descriptor_mode")


@pytest.mark.parametrize(("broken", "error"), [
    ("config", "[pose_graph] gate_chi2: -1.0 is below the minimum 0.1"),
    ("toml", "not valid TOML"),
    ("calibration", "not valid OpenCV YAML"),
])
def test_a_broken_file_on_sighup_keeps_everything_and_is_one_error(running, tmp_path, caplog,
                                                                   broken, error):
    daemon, reloader, sock, path = running
    caplog.set_level(logging.INFO, logger="robotd.app.reload")
    if broken == "config":
        path.write_text(_config(tmp_path, "[pose_graph]\ngate_chi2 = -1\n[keyframes]\ndistance_m = 0.3\n"))
    elif broken == "toml":
        path.write_text(_config(tmp_path, "[keyframes\ndistance_m = 0.3\n"))
    else:
        path.write_text(_config(tmp_path, "[keyframes]\ndistance_m = 0.3\n"))
        (tmp_path / "calibration.yml").write_text("junk: [\n")
    _hup(daemon)
    records = [r for r in caplog.records if r.name == "robotd.app.reload"]
    assert [r.levelno for r in records] == [logging.ERROR]
    assert records[0].getMessage().startswith("reload refused, running on with the previous "
                                              "configuration: ")
    assert error in records[0].getMessage() and "\n" not in records[0].getMessage()
    assert reloader.failures == 1 and daemon.reloads == 1  # the reload ran and refused
    assert daemon.pipeline.stage("keyframes").selector.distance_m == Config().keyframes.distance_m
    assert daemon.pipeline.stage("graph").gate_chi2 == 16.27
    assert daemon.pipeline.stage("floor").detector.threshold == 40.0
    assert reloader.config == load_config_default(tmp_path)
    assert not daemon.stop_event.is_set()


def load_config_default(tmp_path: Path) -> Config:
    cfg = Config()
    cfg = replace(cfg, "calibration", path=str(tmp_path / "calibration.yml"))
    return replace(cfg, "map", path=str(tmp_path / "map.sqlite"))


def test_the_reload_table_is_the_live_keys_of_the_config_metadata_and_changed_keys_finds_each_difference():
    """Every key the config's metadata marks live has a way to be applied, and no other
    key has one (a renamed key would otherwise silently become restart-only); and
    changed_keys reports exactly the keys that differ."""
    cfg = Config()
    assert set(LIVE_KEYS) == live_keys()
    assert ("keyframes", "distance_m") in live_keys() and ("floor_detector", "descriptor_mode") not in live_keys()
    for section, key in LIVE_KEYS:
        assert hasattr(getattr(cfg, section), key), (section, key)
    new = replace(replace(cfg, "base", port="/dev/x"), "pose_graph", gate_chi2=3.0)
    assert changed_keys(cfg, new) == [("base", "port"), ("pose_graph", "gate_chi2")]
    assert changed_keys(cfg, cfg) == []
