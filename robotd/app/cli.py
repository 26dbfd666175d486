"""The ``robotd`` command: one entry point, one subcommand per job.

A known error (:class:`~robotd.base.errors.RobotdError`) ends with one line on stderr and exit
status 2; ``--traceback`` shows the whole stack instead.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from pathlib import Path
from typing import Any, NoReturn

from robotd import __version__

from robotd.base.errors import RobotdError
from robotd.base.files import nonempty_path

log = logging.getLogger("robotd")

EPILOG = """\
examples:
  robotd demo                          run the daemon on the built-in virtual robot
  robotd demo --route square --duration 60 --out /tmp/demo
  robotd run --config /etc/robotd/robotd.toml
  robotd config check robotd.toml      validate a config file
  robotd kobuki decode capture.txt     decode a serial capture (raw or pyserial spy://)
  robotd calibrate intrinsics left*.jpg --board 9x6 --square 0.025 --out calibration.yml
  robotd calibrate loop-curve drive.mcap --calibration calibration.yml --plot curves.png
  robotd calibrate validate other-drive.mcap --calibration calibration.yml
  robotd record run.mcap --virtual --route figure8    record the virtual robot to MCAP
  robotd replay run.mcap --map replay.sqlite          feed a recording through the daemon
  robotd graph optimize CSAIL.g2o --out CSAIL-opt.g2o --isotropic
  robotd graph export map.sqlite --out /tmp/graph     g2o + odometry/optimised TUM files
  robotd eval forward --images seq/ --ground-truth seq/gt.bmp --out /tmp/fw   forward loops
"""


class OneLineParser(argparse.ArgumentParser):
    """argparse with its usage errors on one line (the CLI contract: one line on stderr)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="robotd",
        description="On-robot odometry and loop-closure daemon for Turtlebot-class robots.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"robotd {__version__}")
    p.add_argument("--log-level", choices=("debug", "info", "warning", "error"), default=None,
                   help="logging level (default: the config's, or info)")
    p.add_argument("--traceback", action="store_true", help="show a traceback on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _add_daemon_commands(sub)
    _add_config_commands(sub)
    _add_calibrate_commands(sub)
    _add_kobuki_commands(sub)
    from robotd.app import graph_cli  # light module: gtsam loads when a graph command runs
    graph_cli.add_arguments(sub)
    from robotd.app import forward_eval  # light module: OpenCV and usearch load when it runs
    forward_eval.add_arguments(sub)
    return p


def _add_daemon_commands(sub: argparse._SubParsersAction[Any]) -> None:
    """``run``, ``record``, ``replay`` and ``demo``: the daemon on hardware, a recording,
    or the virtual robot."""
    run = sub.add_parser("run", help="run the daemon on real hardware, as the config says",
                         description="Run the daemon on real hardware (the systemd service's command).")
    run.add_argument("--config", type=nonempty_path, required=True, help="TOML config file")
    run.set_defaults(func=_cmd_run)

    rec = sub.add_parser("record", help="run the daemon and record everything to an MCAP file",
                         description="Record a run to MCAP with ROS 2 message types (floor frames, "
                                     "wheel ticks, gyro, fused and wheel-only odometry; ground truth "
                                     "with --virtual; /tf, /tf_static and CameraInfo), readable by "
                                     "Foxglove and ros2 bag. Frames are JPEG or PNG as the config's "
                                     "[recording] section says (default: JPEG, quality 15).")
    rec.add_argument("output", type=nonempty_path, metavar="OUT.mcap")
    rec.add_argument("--virtual", action="store_true",
                     help="record the built-in virtual robot (takes the demo's options)")
    rec.add_argument("--config", type=nonempty_path, default=None,
                     help="config file (required on real hardware)")
    rec.add_argument("--route", default="office", help="virtual robot's route")
    rec.add_argument("--floor", action="append", type=nonempty_path, default=None, metavar="FILE",
                     help="virtual robot's floor photo(s)")
    rec.add_argument("--floor-pattern", choices=("planks", "tiles"), default=None)
    rec.add_argument("--duration", type=float, default=None, metavar="S")
    rec.add_argument("--seed", type=int, default=0)
    rec.add_argument("--base-seed", type=int, default=None, metavar="N",
                     help="virtual robot: the base (wheel and gyro errors) of seed N on this drive "
                          "(default: the drive's own seed), e.g. a calibration drive of the demo's robot")
    rec.set_defaults(func=_cmd_record)

    rep = sub.add_parser("replay", help="feed a recording through the daemon",
                         description="Replay an MCAP recording through the daemon (odometry, "
                                     "keyframes, floor descriptors), writing the map --map names.")
    rep.add_argument("recording", type=nonempty_path, metavar="FILE.mcap")
    rep.add_argument("--config", type=nonempty_path, default=None, help="config file (default: defaults)")
    rep.add_argument("--map", type=nonempty_path, required=True,
                     help="map file to write (created, or continued if it exists); required, so "
                          "that a replay never writes into the service's map by accident")
    rep.add_argument("--speed", type=float, default=None,
                     help="replay at this multiple of recorded time (default: as fast as possible)")
    rep.set_defaults(func=_cmd_replay)

    from robotd.app import demo as demo_mod  # light module: heavy imports happen inside run()
    d = sub.add_parser("demo", help="run the daemon on the built-in virtual robot",
                       description="Run the whole daemon against the virtual robot: Kobuki "
                                   "bytes over a pseudo-terminal, a rendered floor camera, "
                                   "ground truth. Writes a map, trajectories, a plot and a summary.")
    demo_mod.add_arguments(d)
    d.set_defaults(func=demo_mod.run_from_args)


def _add_config_commands(sub: argparse._SubParsersAction[Any]) -> None:
    cfg = sub.add_parser("config", help="check or print configuration files")
    cfg_sub = cfg.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    chk = cfg_sub.add_parser("check", help="validate a config file")
    chk.add_argument("file", type=nonempty_path)
    chk.set_defaults(func=_cmd_config_check)
    dflt = cfg_sub.add_parser("default", help="print the default configuration as TOML")
    dflt.add_argument("--service", action="store_true",
                      help="the service's configuration instead (systemd/robotd.toml: the defaults "
                           "with the service's choices)")
    dflt.set_defaults(func=_cmd_config_default)
    ref = cfg_sub.add_parser("reference", help="print the configuration reference (Markdown, "
                                               "docs/configuration.md)")
    ref.set_defaults(func=_cmd_config_reference)


def _add_calibrate_commands(sub: argparse._SubParsersAction[Any]) -> None:
    """``calibrate intrinsics|floor-mount|loop-curve|validate``: the offline tools."""
    from calibration import floor_mount, intrinsics, odometry as odometry_cal, train_cli

    cal = sub.add_parser("calibrate", help="camera and floor calibration")
    cal_sub = cal.add_subparsers(dest="calibrate_command", metavar="ACTION", required=True)
    ci = cal_sub.add_parser("intrinsics", help="camera intrinsics from chessboard photos",
                            description="Calibrate the camera from chessboard photos and write (or "
                                        "update) an OpenCV YAML calibration file.")
    intrinsics.add_intrinsics_arguments(ci)
    ci.set_defaults(func=intrinsics.run_intrinsics)
    cm = cal_sub.add_parser("floor-mount", help="the floor camera's height, tilt and offset from a "
                                                "chessboard lying on the floor",
                            description="Measure the downward camera's mounting from one photo of a "
                                        "chessboard lying at a known place in the robot frame.")
    floor_mount.add_floor_mount_arguments(cm)
    cm.set_defaults(func=floor_mount.run_floor_mount)
    cl = cal_sub.add_parser("loop-curve", help="train P(loop | score) and the loop thresholds "
                                               "from a calibration recording",
                            description="Score keyframe pairs of a recorded drive in every descriptor "
                                        "mode, label them by footprint overlap from the fused odometry, "
                                        "fit P(J >= r | score) and write each mode's threshold into the "
                                        "calibration file the daemon loads (paper 003 Sec. IV-C, Fig. 5, "
                                        "Table III).")
    train_cli.add_loop_curve_arguments(cl)
    cl.set_defaults(func=train_cli.run_loop_curve)
    cv = cal_sub.add_parser("validate", help="precision and recall of the thresholds on another "
                                             "recording (labelled by its ground truth)",
                            description="Apply the calibration file's thresholds to the keyframe pairs "
                                        "of another recording of the virtual robot and report, per "
                                        "mode, precision and recall of the declared loops against the "
                                        "ground-truth footprint overlap.")
    train_cli.add_validate_arguments(cv)
    cv.set_defaults(func=train_cli.run_validate)
    co = cal_sub.add_parser("odometry", help="fit this robot's wheel radii, wheel base, gyro scale and "
                                             "noise to a calibration drive",
                            description="Replay a calibration drive (the loop curve's) with floor loops and "
                                        "the pose graph, fit the left and right wheel radii, the wheel "
                                        "base, the gyro's scale and turn-on bias and the noise densities "
                                        "to the loop-corrected trajectory, with their uncertainties, and "
                                        "write them into the calibration file. A drive that cannot make "
                                        "them observable is refused and the file kept as it was.")
    odometry_cal.add_odometry_arguments(co)
    co.set_defaults(func=odometry_cal.run_odometry)


def _add_kobuki_commands(sub: argparse._SubParsersAction[Any]) -> None:
    from drivers.kobuki import capture

    kob = sub.add_parser("kobuki", help="Kobuki base tools")
    kob_sub = kob.add_subparsers(dest="kobuki_command", metavar="ACTION", required=True)
    dec = kob_sub.add_parser("decode", help="decode a serial capture into JSON lines",
                             description="Decode a raw serial capture, or the hex dump written "
                                         "by pyserial's spy:// URL, into one JSON line per packet, "
                                         "with the error counts on the last line.")
    capture.add_decode_arguments(dec)
    dec.set_defaults(func=capture.run_decode)


def _cmd_run(args: argparse.Namespace) -> int:
    from robotd.base.configfile import load_config
    from robotd.app.service import run_service

    cfg = load_config(args.config)
    if args.log_level is None:
        logging.getLogger().setLevel(cfg.daemon.log_level.upper())
    return run_service(cfg, config_path=args.config, log_level_fixed=args.log_level is not None,
                       startup=args.startup)


def _cmd_record(args: argparse.Namespace) -> int:
    from robotd.base.config import Config
    from robotd.base.configfile import load_config
    from robotd.base.errors import ConfigError

    cfg = load_config(args.config) if args.config else Config()
    if args.virtual:
        from robotd.app.demo import exit_status, run_demo
        from robotd.app.demo_report import print_summary

        out = args.output.with_name(args.output.stem + "-demo")
        s = run_demo(cfg, out=out, route=args.route, floor_files=tuple(str(f) for f in args.floor or ()),
                     floor_pattern=args.floor_pattern, duration_s=args.duration, seed=args.seed,
                     record=args.output, startup=args.startup,
                     base_seed=getattr(args, "base_seed", None))
        print_summary(s, sys.stdout)
        print(f"recording: {args.output} ({args.output.stat().st_size / 1e6:.1f} MB); "
              f"demo outputs in {out}")
        return exit_status(s) if s["interrupted"] else 0
    if args.config is None:
        raise ConfigError("robotd record needs --config on real hardware (or --virtual)")
    from robotd.app.service import run_service

    return run_service(cfg, record=args.output, startup=args.startup)


def _cmd_replay(args: argparse.Namespace) -> int:
    from robotd.base.config import Config, replace, with_virtual_floor_camera
    from robotd.base.configfile import load_config
    from robotd.base.errors import ConfigError
    from robotd.app.service import run_replay
    from robotd.base.files import check_utf8_path

    if args.speed is not None and not MIN_REPLAY_SPEED <= args.speed <= MAX_REPLAY_SPEED:
        raise ConfigError(f"--speed must be from {MIN_REPLAY_SPEED:g} to {MAX_REPLAY_SPEED:g} times "
                          f"recorded time, got {args.speed:g} (leave it out to replay as fast as "
                          "possible)")
    check_input_file(args.recording, "recording")
    if args.map is not None:
        check_utf8_path(args.map, "--map")
    cfg = load_config(args.config) if args.config else Config()
    cfg = with_virtual_floor_camera(cfg)
    if args.map is not None:
        cfg = replace(cfg, "map", path=str(args.map))
    r = run_replay(cfg, args.recording, args.speed, startup=args.startup)
    done = (f"{r['odometry_samples']} odometry samples, {r['frames']} frames "
            f"({r['frames_unsynced']} without odometry), {r['keyframes']} keyframes -> {cfg.map.path}")
    if r["interrupted"]:
        print(f"robotd: replay of {args.recording} interrupted ({r['interrupted']}) after "
              f"{r['recording_s']:.1f} of its {r['recording_total_s']:.1f} s, in {r['wall_s']:.1f} s; "
              f"the run is closed in the map; {done}", file=sys.stderr)
        return 128 + signal.Signals[r["interrupted"]].value
    print(f"replayed {args.recording}: {r['recording_s']:.1f} s of recording in {r['wall_s']:.1f} s; "
          f"{done}")
    return 0


MIN_REPLAY_SPEED = 0.01
MAX_REPLAY_SPEED = 1000.0
"""``robotd replay --speed`` bounds (times recorded time); without it, as fast as possible."""


def check_input_file(path: Path, what: str) -> None:
    """ConfigError unless ``path`` is a regular file (not missing, a folder, a device or a
    pipe that would be read forever)."""
    from robotd.base.errors import ConfigError
    from robotd.base.files import describe_path_kind

    kind = describe_path_kind(path)
    if kind == "missing":
        raise ConfigError(f"{what} {path}: no such file")
    if kind != "a regular file":
        raise ConfigError(f"{what} {path} is {kind}, not a file")


def _cmd_config_check(args: argparse.Namespace) -> int:
    from robotd.base.configfile import load_config

    load_config(args.file)
    print(f"{args.file}: OK")
    return 0


def _cmd_config_default(args: argparse.Namespace) -> int:
    from robotd.base.configfile import commented_toml

    print(commented_toml(service=args.service), end="")
    return 0


DAEMON_COMMANDS = ("run", "record", "replay", "demo")
"""Commands that run the daemon: SIGINT/SIGTERM stay held until it takes them over."""


def _cmd_config_reference(args: argparse.Namespace) -> int:
    print(config_reference(), end="")
    return 0


def config_reference() -> str:
    """The configuration reference as Markdown: every section and key with its type,
    default, range and description from the config's own metadata, and whether SIGHUP
    applies it live (the ``live`` of its metadata). ``docs/configuration.md`` is this text
    (a test keeps them equal)."""
    import dataclasses

    from robotd.base.config import Config, live_keys
    from robotd.base.configfile import RENAMED, section_doc, toml_value, unit_of

    out = ["# Configuration reference\n",
           "Generated by `robotd config reference` from the config's own definitions "
           "(`robotd/base/config.py`); do not edit by hand. One TOML file "
           "(`/etc/robotd/robotd.toml` for the service; `systemd/robotd.toml` is the "
           "commented default). Unknown keys and out-of-range values are errors that name "
           "the key. **unit**: the unit the key's name ends in (`_m`, `_deg`, `_s`, ...). **live**: "
           "`systemctl reload robotd` (SIGHUP) applies the key at once; the others need a "
           "restart. `robotd config default` prints the same as a commented TOML file, and "
           "`robotd config default --service` is `systemd/robotd.toml`.\n"]
    defaults = Config()
    for section in dataclasses.fields(Config):
        cls = type(getattr(defaults, section.name))
        out.append(f"## [{section.name}]\n")
        for par in section_doc(cls):
            out.append(f"{par}\n")
        out.append("| key | type | unit | default | range | live | description |")
        out.append("|---|---|---|---|---|---|---|")
        for f in dataclasses.fields(cls):
            meta = f.metadata
            kind = type(f.default).__name__ if f.default is not dataclasses.MISSING else "?"
            kind = {"str": "string", "float": "number", "int": "integer", "bool": "boolean",
                    "tuple": "list of numbers"}.get(kind, kind)
            lo, hi, choices = meta.get("lo"), meta.get("hi"), meta.get("choices")
            rng = (" or ".join(f"`{c}`" for c in choices) if choices else
                   f"{lo:g} to {hi:g}" if lo is not None and hi is not None else
                   f">= {lo:g}" if lo is not None else f"<= {hi:g}" if hi is not None else "")
            if meta.get("length"):
                rng = f"{meta['length']} numbers"
            if meta.get("nonempty"):
                rng = "not empty"
            live = "yes" if (section.name, f.name) in live_keys() else ""
            desc = " ".join(str(meta.get("doc", "")).split()).replace("|", "\\|")
            out.append(f"| `{f.name}` | {kind} | {unit_of(f)} | `{toml_value(f.default)}` | {rng} | {live} "
                       f"| {desc} |")
        out.append("")
    out.append("## Renamed keys\n")
    out.append("Files with these old names still load: each old key is taken as its new one, with one "
               "warning naming both; a file with both the old and the new name is an error. "
               "CHANGELOG.md says when each changed.\n")
    out.append("| old | new |")
    out.append("|---|---|")
    for (old_sec, old_key), (new_sec, new_key) in RENAMED.items():
        out.append(f"| `[{old_sec}] {old_key}` | `[{new_sec}] {new_key}` |")
    out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    from robotd.app.signals import Interrupted, StartupSignals
    # From the first line: building the parser imports the simulator and the calibration
    # tools, which takes a second on a loaded robot; a Ctrl-C then is held, not a traceback.
    startup = StartupSignals().__enter__()
    try:
        return _main(argv, startup)
    except Interrupted as exc:
        print("robotd: interrupted during start-up; nothing was written", file=sys.stderr)
        return exc.exit_status
    finally:
        startup.release()


def _main(argv: list[str] | None, startup: Any) -> int:
    from robotd.app.signals import Interrupted
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # the process's setting, made here rather than on import (robotd.base.blas)

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command in DAEMON_COMMANDS:
        args.startup = startup  # held until the daemon runs (robotd.app.signals)
    else:  # a Ctrl-C from now on interrupts at once
        startup.release()
        startup.stop_if_received()
    # The demo (and recording the virtual robot) shows its own progress line; its log is
    # warnings only unless asked.
    quiet = args.command == "demo" or (args.command == "record" and args.virtual)
    default_level = "warning" if quiet else "info"
    from robotd.app.logsetup import configure_logging

    configure_logging(args.log_level or default_level)  # the journal under systemd, else stderr
    try:
        return int(args.func(args) or 0)
    except RobotdError as exc:
        if args.traceback:
            raise
        print(f"robotd: error: {exc}", file=sys.stderr)
        return 2
    except Interrupted:
        raise  # held during start-up: main says so
    except KeyboardInterrupt:
        print("robotd: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader of our output went away (`robotd ... | head`): stop quietly, as a
        # process killed by SIGPIPE would, and keep Python from complaining at exit.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except OSError as exc:
        # The last resort for a file-system failure no command foresaw (a folder it may not
        # enter, a full or read-only disk): one line, as for a known error.
        if args.traceback:
            raise
        where = f": {exc.filename}" if exc.filename else ""
        print(f"robotd: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 2
    except UnicodeEncodeError as exc:
        if args.traceback:
            raise
        print(f"robotd: error: a path or name that is not valid UTF-8 ({exc.reason}); rename it",
              file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
