"""Config files: reading one (TOML, with the keys of earlier versions renamed), writing
one back (stored with every run), the commented default (``robotd config default``,
``systemd/robotd.toml``), and the units, descriptions and ranges the reference docs are
generated from, all read from the fields' metadata in :mod:`robotd.base.config`."""

from __future__ import annotations

import dataclasses
import logging
import tomllib
from pathlib import Path
from typing import Any

from robotd.base.config import (
    VIRTUAL_SOURCE,
    Config,
    Key,
    PoseGraphConfig,
    check_value,
    replace,
    with_virtual_floor_camera,
)
from robotd.base.errors import ConfigError

log = logging.getLogger(__name__)

_FORWARD_CAMERA_KEYS = ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px", "mount_x_m",
                        "mount_y_m", "mount_yaw_deg", "mount_height_m")

RENAMED: dict[Key, Key] = {
    ("odometry", "accel_noise_mps2"): ("odometry", "accel_noise_density_mps2_per_sqrt_hz"),
    ("odometry", "angular_accel_noise_radps2"):
        ("odometry", "angular_accel_noise_density_radps2_per_sqrt_hz"),
    ("odometry", "gyro_bias_walk_radps_sqrt_s"): ("odometry", "gyro_bias_walk_radps_per_sqrt_s"),
    ("floor_detector", "mode"): ("floor_detector", "descriptor_mode"),
    ("visual_odometry", "mode"): ("visual_odometry", "role"),
    ("pose_graph", "save_every_keyframes"): ("pose_graph", "full_solve_every_keyframes"),
    **{("forward_detector", k): ("forward_camera", k) for k in _FORWARD_CAMERA_KEYS},
}
"""Keys of earlier config files and their names now (CHANGELOG.md). A file with an old
name still loads: the value is applied to the new key, with one warning per old key; a
file with both is an error."""

def _renamed(data: dict[str, Any], origin: str) -> dict[str, Any]:
    """``data`` with the old keys of :data:`RENAMED` moved to their new names (one
    warning each); both an old key and its new one is a :class:`ConfigError`."""
    out = {name: dict(table) if isinstance(table, dict) else table for name, table in data.items()}
    where = f"{origin}: " if origin else ""
    for (old_sec, old_key), (new_sec, new_key) in RENAMED.items():
        table = out.get(old_sec)
        if not isinstance(table, dict) or old_key not in table:
            continue
        target = out.setdefault(new_sec, {})
        if not isinstance(target, dict):
            continue  # "[new_sec] must be a table" below
        if new_key in target:
            raise ConfigError(f"[{old_sec}] {old_key} and [{new_sec}] {new_key} are the same key "
                              f"([{old_sec}] {old_key} is its old name): keep only [{new_sec}] {new_key}")
        target[new_key] = table.pop(old_key)
        log.warning("%s[%s] %s is now [%s] %s: its value is used; rename it in the file "
                    "(CHANGELOG.md)", where, old_sec, old_key, new_sec, new_key)
    return out


def config_from_dict(data: dict[str, Any], *, origin: str = "", stored: bool = False) -> Config:
    """Build a :class:`Config` from parsed TOML, validating every key.

    Old key names (:data:`RENAMED`) are taken with a warning naming ``origin`` (the file).
    ``stored``: the config robotd wrote itself into a recording or a map, where
    ``[floor_camera] source`` may be :data:`VIRTUAL_SOURCE`."""
    data = _renamed(data, origin)
    sections = {f.name: f for f in dataclasses.fields(Config)}
    built: dict[str, Any] = {}
    virtual = False
    for name, table in data.items():
        if name not in sections:
            raise ConfigError(f"unknown section [{name}] (known: {', '.join(sections)})")
        if not isinstance(table, dict):
            raise ConfigError(f"[{name}] must be a table, got {table!r}")
        cls: Any = sections[name].default_factory
        fields = {f.name: f for f in dataclasses.fields(cls)}
        values = {}
        for key, value in table.items():
            if key not in fields:
                raise ConfigError(f"unknown key [{name}] {key} (known: {', '.join(fields)})")
            if (name, key) == ("floor_camera", "source") and value == VIRTUAL_SOURCE:
                if not stored:
                    raise ConfigError(
                        "[floor_camera] source: 'virtual' is not a camera of `robotd run` (the "
                        "virtual robot is built by `robotd demo` itself): use 'v4l2', 'depthai', "
                        "'ros2' or 'none'")
                virtual = True
                continue
            values[key] = check_value(name, fields[key], value)
        built[name] = cls(**values)
    cfg = Config(**built)
    fc = cfg.floor_camera
    if not (0 <= fc.cx_px < fc.width_px and 0 <= fc.cy_px < fc.height_px):
        raise ConfigError("[floor_camera] cx_px/cy_px: the principal point must lie inside the image")
    if cfg.odometry.wheel_rounding and not cfg.odometry.wheel_increments:
        # The roundings are carried between the packets of wheel_increments; alone the key
        # would do nothing, which a user who set it would not expect.
        raise ConfigError("[odometry] wheel_rounding: works only with wheel_increments = true")
    if cfg.odometry.slip_event_rate_hz > 0.0 and cfg.odometry.slip_gate_sigma <= 0.0:
        # The events' variances are those the slip test lets through or sees: no test, no term.
        raise ConfigError("[odometry] slip_event_rate_hz: works only with slip_gate_sigma > 0")
    fd = cfg.forward_detector
    if fd.checks_per_keyframe > 0 and fd.max_deferred_tests == 0:
        # The budget leaves the rest of a verification to later keyframes, which a queue of
        # none forbids: the key would do nothing.
        raise ConfigError("[forward_detector] checks_per_keyframe: works only with max_deferred_tests > 0")
    pg = cfg.pose_graph
    if pg.odometry_model != "bias_scale_window" and pg.scale_wear != PoseGraphConfig().scale_wear:
        # The wear widens the scale variable's prior; without the variable it would do nothing.
        raise ConfigError("[pose_graph] scale_wear: works only with odometry_model = \"bias_scale_window\"")
    if pg.odometry_model != "bias_scale_window" and pg.scale_wear_gyro != PoseGraphConfig().scale_wear_gyro:
        raise ConfigError("[pose_graph] scale_wear_gyro: works only with odometry_model = \"bias_scale_window\"")
    return with_virtual_floor_camera(cfg) if virtual else cfg


def load_config(path: str | Path) -> Config:
    """Read and validate a TOML config file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {p}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read config file {p}: {exc}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return config_from_dict(data, origin=str(p))


UNIT_SUFFIXES: tuple[tuple[str, str], ...] = (
    ("_mps2_per_sqrt_hz", "m/s^2/sqrt(Hz)"), ("_radps2_per_sqrt_hz", "rad/s^2/sqrt(Hz)"),
    ("_radps_per_sqrt_s", "rad/s/sqrt(s)"), ("_per_mps", "per m/s"), ("_radps", "rad/s"),
    ("_mps", "m/s"), ("_frac", "fraction"), ("_deg", "deg"), ("_px", "px"), ("_hz", "Hz"),
    ("_m", "m"), ("_s", "s"),
)
"""A key's unit from the end of its name (the project's naming rule: SI units in names)."""


def unit_of(f: dataclasses.Field[Any]) -> str:
    """The unit of a config field: its metadata's ``unit`` when given, else the one its
    name ends in (:data:`UNIT_SUFFIXES`), else ``""`` (a count, a name, a choice)."""
    unit = f.metadata.get("unit")
    if unit is not None:
        return str(unit)
    if isinstance(f.default, str) or isinstance(f.default, bool):
        return ""
    return next((u for suffix, u in UNIT_SUFFIXES if f.name.endswith(suffix)), "")


def to_toml(cfg: Config) -> str:
    """Serialise a config back to TOML (stored with every run in the map file)."""
    lines: list[str] = []
    for sf in dataclasses.fields(cfg):
        lines.append(f"[{sf.name}]")
        for f in dataclasses.fields(getattr(cfg, sf.name)):
            v = getattr(getattr(cfg, sf.name), f.name)
            lines.append(f"{f.name} = {toml_value(v)}")
        lines.append("")
    return "\n".join(lines)


SERVICE_CHOICES: dict[Key, Any] = {("pose_graph", "localise_mapped"): True}
"""Where the service's config (``systemd/robotd.toml``) differs from the defaults: a robot
that drives the same rooms for weeks stops growing its map over mapped ground (the demo
and the paper's experiment keep every keyframe)."""


def service_config() -> Config:
    """The defaults with :data:`SERVICE_CHOICES`: what ``systemd/robotd.toml`` holds."""
    cfg = Config()
    for (section, key), value in SERVICE_CHOICES.items():
        cfg = replace(cfg, section, **{key: value})
    return cfg


def section_doc(cls: Any) -> list[str]:
    """A section's docstring as paragraphs, each on one line."""
    text = (cls.__doc__ or "").strip()
    return [" ".join(par.split()).replace("``", "`") for par in text.split("\n\n") if par.strip()]


_NBSP = "\u00a0"  # joins a range to its unit in field_note, for commented_toml's wrapping


def field_note(f: dataclasses.Field[Any]) -> str:
    """A key's description with its unit, range and liveness, on one line."""
    meta = f.metadata
    note = " ".join(str(meta.get("doc", "")).split())
    unit = unit_of(f)
    lo, hi, choices = meta.get("lo"), meta.get("hi"), meta.get("choices")
    if choices:
        note += f" (one of {', '.join(map(repr, choices))})"
    elif lo is not None or hi is not None:
        rng = f"{'' if lo is None else f'{lo:g}'}..{'' if hi is None else f'{hi:g}'}"
        note += f" ({rng}{_NBSP + unit if unit else ''})"
    elif unit:
        note += f" ({unit})"
    if meta.get("live"):
        note += "; reload applies it live"
    return note


def commented_toml(cfg: Config | None = None, *, service: bool = False) -> str:
    """``cfg`` (default: the defaults; ``service``: :func:`service_config`) as TOML with
    each section's and key's description, unit, valid range and whether a reload applies
    it live, as comments: what ``robotd config default`` prints, a config file to start
    from. ``robotd config default --service`` is ``systemd/robotd.toml`` (a test keeps
    them equal)."""
    import textwrap

    if cfg is None:
        cfg = service_config() if service else Config()
    if service:
        lines = ["# robotd's service configuration (systemd/robotd.toml): copy to",
                 "# /etc/robotd/robotd.toml and edit. Generated by `robotd config default --service`",
                 "# from the definitions in robotd/base/config.py: the defaults but for the keys",
                 "# marked as the service's choice."]
    else:
        lines = ["# robotd configuration (robotd config default): the defaults."]
    lines += ["# Unknown keys and out-of-range values are errors that name the key, so a typo never",
              "# silently falls back to a default. Units are in the key names and in brackets.",
              "# `systemctl reload robotd` (SIGHUP) applies the keys marked 'reload applies it",
              "# live' at once; any other change is logged as needing a restart.", ""]

    def comment(text: str) -> list[str]:  # a range and its unit stay on one line
        return [line.replace(_NBSP, " ") for line in textwrap.wrap(
            text, 88, initial_indent="# ", subsequent_indent="# ", break_on_hyphens=False,
            break_long_words=False)]

    for sf in dataclasses.fields(cfg):
        section = getattr(cfg, sf.name)
        lines.append(f"[{sf.name}]")
        for par in section_doc(type(section)):
            lines += comment(par)
        for f in dataclasses.fields(section):
            note = field_note(f)
            if service and (sf.name, f.name) in SERVICE_CHOICES:
                note += f" [the service's choice; the default is {toml_value(f.default)}]"
            lines += comment(note)
            lines.append(f"{f.name} = {toml_value(getattr(section, f.name))}")
        lines.append("")
    return "\n".join(lines)


def toml_value(v: Any) -> str:
    """One value as TOML."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'
