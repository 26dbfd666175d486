"""SIGHUP: read the config file (and the calibration file) again, apply what can change live.

``systemctl reload robotd`` sends SIGHUP; the daemon calls :class:`ConfigReloader` from its
main loop, between two turns, so no stage is in the middle of a message. The new files are
read and validated completely before anything changes: a config or calibration file that
does not read is one ERROR line, and the daemon runs on with everything it had.

What changes live is what the running stages can take between two messages, marked
``live`` in the config's metadata (:func:`robotd.base.config.live_keys`, the one list: the
configuration reference and ``robotd config default`` show it; :data:`LIVE_KEYS` says how
each is applied, and a test keeps the two the same), and the loop threshold of the
calibration file. Everything else (devices, the map file, the robot's geometry and noise
model, the descriptor mode, the camera model, which stages exist, ...) is fixed when the
daemon is assembled: a change there is logged as needing a restart and is not applied,
so the log says exactly what the running daemon uses.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from robotd.base.config import Config, live_keys
from robotd.base.configfile import load_config
from robotd.base.errors import RobotdError

__all__ = ["LIVE_KEYS", "ConfigReloader", "changed_keys"]

log = logging.getLogger(__name__)

Key = tuple[str, str]  # (section, key)


def _set_log_level(daemon: Any, value: str) -> None:
    logging.getLogger().setLevel(value.upper())


def _set_status_interval(daemon: Any, value: float) -> None:
    daemon.set_status_interval(value)


def _set_keyframe_distance(daemon: Any, value: float) -> None:
    daemon.pipeline.stage("keyframes").set_spacing(distance_m=value)


def _set_keyframe_rotation(daemon: Any, value: float) -> None:
    daemon.pipeline.stage("keyframes").set_spacing(rotation_rad=math.radians(value))


def _detector_param(name: str) -> Callable[[Any, Any], None]:
    def apply(daemon: Any, value: Any) -> None:
        stage = _stage(daemon, "floor")
        if stage is not None:
            stage.set_query_params(**{name: value})
    return apply


def _graph_call(method: str) -> Callable[[Any, Any], None]:
    """The pose graph stage's own reload method (``set_gate``, ``set_save_every``)."""
    def apply(daemon: Any, value: Any) -> None:
        stage = _stage(daemon, "graph")
        if stage is not None:
            getattr(stage, method)(value)
    return apply


LIVE_KEYS: dict[Key, Callable[[Any, Any], None]] = {
    ("daemon", "log_level"): _set_log_level,
    ("daemon", "status_interval_s"): _set_status_interval,
    ("keyframes", "distance_m"): _set_keyframe_distance,
    ("keyframes", "rotation_deg"): _set_keyframe_rotation,
    ("floor_detector", "candidates"): _detector_param("candidates"),
    ("floor_detector", "shortlist"): _detector_param("shortlist"),
    ("floor_detector", "exclude_recent_s"): _detector_param("exclude_recent_s"),
    ("pose_graph", "gate_chi2"): _graph_call("set_gate"),
    ("pose_graph", "full_solve_every_keyframes"): _graph_call("set_save_every"),
    ("calibration", "path"): lambda daemon, value: None,  # its thresholds: see ConfigReloader
}
"""How a reload applies each key the config's metadata marks live (its keys are
:func:`~robotd.base.config.live_keys`)."""


def _stage(daemon: Any, name: str) -> Any:
    try:
        return daemon.pipeline.stage(name)
    except KeyError:  # that stage is not part of this daemon (disabled in the config)
        return None


def changed_keys(old: Config, new: Config) -> list[Key]:
    """Every ``(section, key)`` whose value differs between two configs, in file order."""
    out: list[Key] = []
    for sf in dataclasses.fields(old):
        a, b = getattr(old, sf.name), getattr(new, sf.name)
        out.extend((sf.name, f.name) for f in dataclasses.fields(a)
                   if getattr(a, f.name) != getattr(b, f.name))
    return out


def _fmt(keys: list[str]) -> str:
    return ", ".join(keys) if keys else "none"


class ConfigReloader:
    """The daemon's :attr:`~robotd.app.daemon.Daemon.on_reload` for ``robotd run``.

    ``cfg`` is the config the daemon was assembled with and ``calibration`` the
    calibration file's contents it loaded (None: there was none). ``log_level_fixed``:
    ``--log-level`` was given on the command line, which a reload does not override.
    After each reload :attr:`config` is what the daemon runs with: the new values of the
    live keys, the old values of the others (so a key that needs a restart is reported
    again at every reload until the restart).
    """

    def __init__(self, path: Path, cfg: Config, calibration: Any, *,
                 log_level_fixed: bool = False) -> None:
        self.path = Path(path)
        self.config = cfg
        self.calibration = calibration
        self.log_level_fixed = log_level_fixed
        self.failures = 0

    def __call__(self, daemon: Any) -> None:
        try:
            new = load_config(self.path)
            calibration = self._read_calibration(new)
        except RobotdError as exc:
            self.failures += 1
            log.error("reload refused, running on with the previous configuration: %s", exc)
            return
        live: list[str] = []
        restart: list[str] = []
        merged = self.config
        for section, key in changed_keys(self.config, new):
            name = f"[{section}] {key}"
            value = getattr(getattr(new, section), key)
            apply = LIVE_KEYS.get((section, key)) if (section, key) in live_keys() else None
            if apply is None:
                restart.append(name)
                continue
            if (section, key) == ("daemon", "log_level") and self.log_level_fixed:
                restart.append(f"{name} (--log-level on the command line wins)")
                continue
            apply(daemon, value)
            live.append(f"{name} = {value!r}")
            merged = dataclasses.replace(merged, **{section: dataclasses.replace(
                getattr(merged, section), **{key: value})})
        live += self._apply_calibration(daemon, merged, calibration, restart)
        self.config = merged
        log.info("reloaded %s: applied live: %s; need a restart (not applied): %s",
                 self.path, _fmt(live), _fmt(restart))

    def _read_calibration(self, cfg: Config) -> Any:
        """The calibration file the new config names, read now (None when absent);
        a file that does not read raises, refusing the whole reload."""
        from robotd.io.calibfile import read_calibration

        path = Path(cfg.calibration.path)
        return read_calibration(path) if path.exists() else None

    def _apply_calibration(self, daemon: Any, cfg: Config, calibration: Any,
                           restart: list[str]) -> list[str]:
        """Apply the calibration file's loop threshold for the running mode; list a changed
        camera model (intrinsics, mount) as needing a restart. Returns what was applied."""
        old = self.calibration
        for part in ("intrinsics", "mount"):
            before = repr(getattr(old, part, None)) if old is not None else "None"
            after = repr(getattr(calibration, part, None)) if calibration is not None else "None"
            if before != after:
                restart.append(f"calibration file: {part}")
        self.calibration = _with_camera_of(calibration, old)
        stage = _stage(daemon, "floor")
        if stage is None:
            return []
        mode = stage.mode
        loop = calibration.loop if calibration is not None else None
        threshold = loop.for_mode(mode) if loop is not None else None
        if threshold == stage.threshold:
            return []
        before = stage.threshold
        stage.set_threshold(threshold)
        if threshold is None:
            log.warning("the calibration file %s has no loop threshold for mode %d: no floor loops "
                        "are declared from now on", cfg.calibration.path, mode)
        return [f"loop threshold (mode {mode}) {before} -> {threshold}"]


def _with_camera_of(new: Any, running: Any) -> Any:
    """``new`` with the camera parts the daemon still runs with (``running``'s), so the
    next reload compares against what is in use."""
    if new is None and running is None:
        return None
    from robotd.io.calibfile import CalibrationFile

    return CalibrationFile(
        intrinsics=getattr(running, "intrinsics", None),
        reprojection_error_px=getattr(running, "reprojection_error_px", None),
        mount=getattr(running, "mount", None),
        loop=getattr(new, "loop", None))
