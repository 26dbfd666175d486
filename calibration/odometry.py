"""``robotd calibrate odometry``: this robot's odometry model from a calibration drive.

The drive (the loop curve's: floor frames, wheels, gyro) is replayed through the daemon's
own pipeline, as :func:`calibration.train.load_run` does, but with the floor loop
detector and the pose graph on (the calibration file's loop thresholds, so
``robotd calibrate loop-curve`` comes first) and floor visual odometry as the config
says: the loop-corrected keyframe poses are the reference trajectory. The wheel ticks
and gyro readings the pipeline saw are collected beside it, and
:func:`robotd.odometry.calibration.fit_odometry` fits the model; it goes into the
calibration file's ``odometry_*`` keys (:class:`robotd.io.calibfile.OdometryModel`). A
drive that cannot make the model observable is refused with one line naming what it
lacks, and the file is left as it was, byte for byte.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from robotd.base.errors import CalibrationError

log = logging.getLogger(__name__)


@dataclass(eq=False)
class OdometryDriveData:
    """The drive as the fit reads it, and the ground truth when the recording has one
    (the virtual robot's ``/ground_truth``: ``(stamps (T,), poses (T, 3))``)."""

    drive: Any  # robotd.odometry.calibration.CalibrationDrive
    truth: tuple[np.ndarray, np.ndarray] | None
    keyframes: int
    loops: int


class _SensorCollector:
    """A pipeline observer keeping every wheel and gyro reading the pipeline saw."""

    name = "odometry calibration"

    def __init__(self) -> None:
        self.wheel: list[tuple[int, int, int]] = []
        self.gyro: list[tuple[int, float]] = []

    def subscriptions(self) -> dict[type, Any]:
        from robotd.base.messages import WheelTicks, YawRate

        return {WheelTicks: self.on_wheels, YawRate: self.on_gyro}

    def on_wheels(self, m: Any) -> None:
        self.wheel.append((int(m.stamp_ns), int(m.left_ticks), int(m.right_ticks)))

    def on_gyro(self, m: Any) -> None:
        self.gyro.append((int(m.stamp_ns), float(m.yaw_rate_radps)))


def unwrapped_angles(ticks: np.ndarray, ticks_per_rev: float) -> np.ndarray:
    """Cumulative wheel angles ``(N, 2)`` rad from raw 16-bit counters ``(N, 2)``."""
    d = np.diff(ticks.astype(np.int64), axis=0)
    d = np.mod(d + 32768, 65536) - 32768
    return np.concatenate([np.zeros((1, 2)), np.cumsum(d, axis=0)]) * (2.0 * math.pi / ticks_per_rev)


def load_drive(path: Path, cfg: Any, calib: Any) -> OdometryDriveData:
    """Replay ``path`` through the daemon (floor loops, pose graph, visual odometry as
    ``cfg`` says; ``calib`` without its odometry part) and return the fit's input."""
    from drivers.recording.reader import RecordingReader
    from drivers.recording.replay import ReplayDriver
    from robotd.app.assemble import assemble_daemon
    from robotd.app.notify import Notifier
    from robotd.app.service import replay_finished
    from robotd.base.clock import ManualClock
    from robotd.base.config import replace
    from robotd.base.messages import PoseStamped
    from robotd.io.store import MapStore
    from robotd.odometry.calibration import CalibrationDrive

    with RecordingReader(path) as reader:
        span = reader.time_range_ns
    if span is None:
        raise CalibrationError(f"{path}: the recording holds no messages")
    cfg = replace(cfg, "keyframes", image_width_px=0)
    clock = ManualClock(span[0])
    collector = _SensorCollector()
    truth: list[tuple[int, tuple[float, float, float]]] = []

    def other(topic: str, m: Any) -> None:
        if topic == "/ground_truth" and isinstance(m, PoseStamped):
            truth.append((m.stamp_ns, (m.x_m, m.y_m, m.yaw_rad)))

    with tempfile.TemporaryDirectory(prefix="robotd-odocal-") as tmp, \
            ReplayDriver(path, clock, on_other=other) as replay, \
            MapStore.open(Path(tmp) / "odocal.sqlite", synchronous="NORMAL", clock=clock) as store:
        daemon = assemble_daemon(cfg, clock, {"replay": replay}, store, Notifier(), lossless=True,
                                 observers=[collector], calibration=calib, load_calibration_file=False)
        report = daemon.run(stop_when=lambda: replay_finished(replay, daemon))
        if report.source_errors.get("replay"):
            raise CalibrationError(f"{path}: the replay stopped on an error (see the log)")
        optimized = store.optimized_poses()
        kfs = [(kf.stamp_ns, kf.id) for kf in store.keyframes() if kf.id in optimized]
        loops = len(store.links("loop"))
    kfs.sort()
    if len(collector.wheel) < 2 or len(collector.gyro) < 2:
        raise CalibrationError(f"{path}: the drive lacks wheel and gyro readings")
    wheel = np.asarray(collector.wheel, np.int64)
    gyro = np.asarray(collector.gyro, float)
    drive = CalibrationDrive(
        wheel_stamp_ns=wheel[:, 0], wheel_angle_rad=unwrapped_angles(wheel[:, 1:], cfg.robot.ticks_per_rev),
        gyro_stamp_ns=gyro[:, 0].astype(np.int64), gyro_radps=gyro[:, 1],
        ref_stamp_ns=np.asarray([t for t, _ in kfs], np.int64),
        ref_pose=np.asarray([optimized[k] for _, k in kfs], float).reshape(-1, 3),
    )
    tr = None
    if len(truth) >= 2:
        tr = (np.asarray([t for t, _ in truth], np.int64), np.asarray([p for _, p in truth], float))
    return OdometryDriveData(drive, tr, len(kfs), loops)


def add_odometry_arguments(p: Any) -> None:
    p.add_argument("recording", type=Path, help="MCAP recording of a calibration drive (the loop curve's)")
    p.add_argument("--calibration", type=Path, required=True,
                   help="calibration file with the loop thresholds (robotd calibrate loop-curve); the "
                        "odometry model is written into it")
    p.add_argument("--config", type=Path, default=None,
                   help="robotd config (default: the one the recording was made with, else the defaults)")
    p.add_argument("--passes", type=int, default=2, metavar="N",
                   help="replays of the drive: each after the first makes the reference trajectory "
                        "with the model the one before fitted (default 2)")
    p.add_argument("--plot", type=Path, default=None, help="write the residuals before and after (PNG)")
    p.add_argument("--json", type=Path, default=None, metavar="FILE", help="also write the results as JSON")


#: The calibration file's slip event fields (:class:`~robotd.io.calibfile.OdometryModel`).
SLIP_EVENT_FIELDS = ("slip_event_rate_hz", "slip_event_duration_s", "slip_event_rate_sigma_hz",
                     "slip_event_duration_sigma_s")


def model_from_fit(fit: Any, old: Any = None) -> Any:
    """The calibration file's :class:`~robotd.io.calibfile.OdometryModel` of a fit. When the
    fit refused the slip events (too few seen), ``old``'s slip event values (the file's
    model before) are kept, or none."""
    from robotd.io.calibfile import OdometryModel

    pr = fit.process
    process = {} if pr is None else {
        "accel_noise_mps2_sqrt_hz": pr.accel_mps2_sqrt_hz, "accel_noise_sigma": pr.accel_sigma,
        "angular_accel_noise_radps2_sqrt_hz": pr.angular_accel_radps2_sqrt_hz,
        "angular_accel_noise_sigma": pr.angular_accel_sigma}
    ev = fit.slip_events
    if ev is not None and not ev.refused:
        process.update(slip_event_rate_hz=ev.rate_hz, slip_event_duration_s=ev.duration_s,
                       slip_event_rate_sigma_hz=ev.rate_sigma_hz, slip_event_duration_sigma_s=ev.duration_sigma_s)
    elif old is not None and old.has_slip_events:
        process.update({k: getattr(old, k) for k in SLIP_EVENT_FIELDS})
    return OdometryModel(
        **process,
        wheel_radius_left_m=fit.wheel_radius_left_m, wheel_radius_right_m=fit.wheel_radius_right_m,
        wheel_base_m=fit.wheel_base_m, gyro_scale=fit.gyro_scale, gyro_bias_radps=fit.gyro_bias_radps,
        gyro_noise_radps_sqrt_hz=fit.gyro_noise_radps_sqrt_hz, wheel_noise_m_sqrt_m=fit.wheel_noise_m_sqrt_m,
        wheel_radius_left_sigma_m=fit.wheel_radius_left_sigma,
        wheel_radius_right_sigma_m=fit.wheel_radius_right_sigma,
        wheel_base_sigma_m=fit.wheel_base_sigma, gyro_scale_sigma=fit.gyro_scale_sigma,
        gyro_bias_sigma_radps=fit.gyro_bias_sigma,
    )


def format_fit(fit: Any, nominal_radius_m: float, nominal_base_m: float) -> str:
    """The fitted values with their uncertainties and the change from nominal."""
    rows = [
        ("left wheel radius", fit.wheel_radius_left_m, fit.wheel_radius_left_sigma, nominal_radius_m, "m"),
        ("right wheel radius", fit.wheel_radius_right_m, fit.wheel_radius_right_sigma, nominal_radius_m, "m"),
        ("wheel base", fit.wheel_base_m, fit.wheel_base_sigma, nominal_base_m, "m"),
        ("gyro scale", fit.gyro_scale, fit.gyro_scale_sigma, 1.0, ""),
    ]
    lines = [f"{'':<20}{'value':>12}{'1 sigma':>12}{'vs nominal':>12}"]
    for name, v, s, nom, unit in rows:
        lines.append(f"{name:<20}{v:>12.6f}{s:>12.6f}{100 * (v / nom - 1):>+11.3f}% {unit}")
    lines.append(f"{'gyro turn-on bias':<20}{math.degrees(fit.gyro_bias_radps):>12.4f}"
                 f"{math.degrees(fit.gyro_bias_sigma):>12.4f} deg/s (drift "
                 f"{math.degrees(fit.gyro_bias_drift_radps2) * 60:+.4f} deg/s per minute)")
    lines.append(f"{'gyro noise':<20}{math.degrees(fit.gyro_noise_radps_sqrt_hz):>12.4f} deg/s/sqrt(Hz)")
    lines.append(f"{'wheel slip noise':<20}{1e3 * fit.wheel_noise_m_sqrt_m:>12.3f} mm/sqrt(m)")
    if fit.process is not None:
        pr = fit.process
        lines.append(f"{'white acceleration':<20}{pr.accel_mps2_sqrt_hz:>12.5f}{pr.accel_sigma:>12.5f} "
                     "m/s^2/sqrt(Hz) (maximum likelihood)")
        lines.append(f"{'white angular acc.':<20}{pr.angular_accel_radps2_sqrt_hz:>12.5f}"
                     f"{pr.angular_accel_sigma:>12.5f} rad/s^2/sqrt(Hz) (maximum likelihood)")
    ev = fit.slip_events
    if ev is not None and not ev.refused:
        lines.append(f"{'slip events':<20}{ev.rate_hz:>12.4f}{ev.rate_sigma_hz:>12.4f} a second of accelerating "
                     f"or turning ({ev.events_seen} seen, {ev.events_estimated:.1f} with those the gate missed, "
                     f"in {ev.demand_s:.1f} s)")
        lines.append(f"{'slip event duration':<20}{ev.duration_s:>12.4f}{ev.duration_sigma_s:>12.4f} s RMS "
                     f"(slip ratio taken uniform in {ev.ratio_lo:.3f}-{ev.ratio_hi:.3f})")
    rms_b = np.sqrt(np.mean(fit.residuals_before ** 2, axis=0))
    rms_a = np.sqrt(np.mean(fit.residuals_after[fit.used] ** 2, axis=0))
    lines.append(f"residuals per keyframe interval (RMS), nominal -> fitted: wheel dx "
                 f"{1e3 * rms_b[0]:.2f} -> {1e3 * rms_a[0]:.2f} mm, dy {1e3 * rms_b[1]:.2f} -> "
                 f"{1e3 * rms_a[1]:.2f} mm, wheel heading {math.degrees(rms_b[2]):.3f} -> "
                 f"{math.degrees(rms_a[2]):.3f} deg, gyro heading {math.degrees(rms_b[3]):.3f} -> "
                 f"{math.degrees(rms_a[3]):.3f} deg; {int((~fit.used).sum())} of {len(fit.used)} intervals "
                 "left out of the wheel fit (slip)")
    return "\n".join(lines)


def plot_residuals(path: Path, fit: Any) -> None:
    """Residuals per keyframe interval before and after, against time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = fit.interval_end_s
    fig, axes = plt.subplots(6, 1, figsize=(10, 12), sharex=True)
    names = [("wheel dx (mm)", 1e3), ("wheel dy (mm)", 1e3), ("wheel heading (deg)", 180 / math.pi),
             ("gyro heading (deg)", 180 / math.pi)]
    for ax, (name, k), n in zip(axes, names, range(4)):
        ax.plot(t, k * fit.residuals_before[:, n], ".", ms=3, color="tab:red", label="nominal")
        ax.plot(t, k * fit.residuals_after[:, n], ".", ms=3, color="tab:blue", label="fitted")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    # Summed over the drive, the systematic part stands out of the per-interval noise: the
    # heading error dead reckoning from the wheels alone, or the gyro alone, would build up.
    for ax, n, name in ((axes[4], 2, "wheel heading,\nsummed (deg)"), (axes[5], 3, "gyro heading,\nsummed (deg)")):
        ax.plot(t, np.degrees(np.cumsum(fit.residuals_before[:, n])), color="tab:red", label="nominal")
        ax.plot(t, np.degrees(np.cumsum(fit.residuals_after[:, n])), color="tab:blue", label="fitted")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("time since the first keyframe (s)")
    fig.suptitle("odometry against the loop-corrected trajectory, per keyframe interval")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_odometry(args: Any) -> int:
    """``robotd calibrate odometry``."""
    from dataclasses import replace as dc_replace

    from calibration.train import drive_config
    from robotd.base.files import check_output_file
    from robotd.io.calibfile import CalibrationFile, read_calibration, update_calibration
    from robotd.odometry.calibration import fit_odometry
    from robotd.odometry.ekf import EkfParams

    # The arguments checked before the recording is opened (a damaged one logs a warning).
    if not args.calibration.exists():
        raise CalibrationError(f"{args.calibration}: no such calibration file (run `robotd calibrate "
                               "loop-curve` on the drive first: the reference trajectory needs its loops)")
    if args.passes < 1:
        raise CalibrationError(f"--passes must be at least 1, got {args.passes}")
    cfg = drive_config(args.config, args.recording)
    # The outputs are checked before the replay (minutes), not when they are written.
    for option, path in (("--plot", args.plot), ("--json", args.json)):
        if path is not None:
            check_output_file(path, force=True, inputs=[args.recording, args.calibration],
                              option=option)
    calib = read_calibration(args.calibration)
    if calib.loop is None or calib.loop.for_mode(cfg.floor_detector.descriptor_mode) is None:
        raise CalibrationError(f"{args.calibration}: no loop threshold for descriptor mode "
                               f"{cfg.floor_detector.descriptor_mode} (run `robotd calibrate loop-curve` first)")
    nominal_r, nominal_b = cfg.robot.wheel_radius_m, cfg.robot.wheel_base_m
    out = sys.stdout
    model = None
    for rnd in range(args.passes):
        # Pass 1 makes the reference with the nominal model, each later one with the model
        # the pass before fitted: the loop-corrected poses between loops still lean on the
        # odometry, so a reference made with the wrong model pulls the fit towards it.
        data = load_drive(args.recording, cfg, dc_replace(calib, odometry=model))
        try:
            fit = fit_odometry(data.drive, nominal_r, nominal_b, noise=EkfParams.from_config(cfg.odometry),
                               ticks_per_rev=cfg.robot.ticks_per_rev)
        except CalibrationError as exc:
            raise CalibrationError(f"{args.recording}: {exc}; {args.calibration} is left as it was") from None
        model = model_from_fit(fit, calib.odometry)
        if args.passes > 1:
            print(f"pass {rnd + 1}: radii {fit.wheel_radius_left_m:.6f} / {fit.wheel_radius_right_m:.6f} m, "
                  f"wheel base {fit.wheel_base_m:.6f} m, gyro scale {fit.gyro_scale:.6f}", file=out)
    print(f"\n{data.keyframes} keyframes with loop-corrected poses ({data.loops} loops); drive "
          f"{fit.distance_m:.1f} m, turning {fit.turn_left_deg:.0f} deg left and {fit.turn_right_deg:.0f} "
          f"deg right, {fit.still_s:.1f} s still", file=out)
    print(format_fit(fit, nominal_r, nominal_b), file=out)
    update_calibration(args.calibration, CalibrationFile(odometry=model))
    print(f"odometry model written to {args.calibration}", file=out)
    if fit.slip_events is not None and fit.slip_events.refused:
        kept = ("its slip event values are kept" if calib.odometry is not None and calib.odometry.has_slip_events
                else "it holds no slip event values")
        print(f"robotd: {args.recording}: the slip events' rate and duration not fitted: "
              f"{fit.slip_events.refused}; {args.calibration}: {kept}", file=sys.stderr)
    if args.plot is not None:
        plot_residuals(args.plot, fit)
        print(f"residuals: {args.plot}", file=out)
    if args.json is not None:
        args.json.write_text(json.dumps({
            "recording": str(args.recording), "keyframes": data.keyframes, "loops": data.loops,
            "distance_m": fit.distance_m, "turn_left_deg": fit.turn_left_deg,
            "turn_right_deg": fit.turn_right_deg, "still_s": fit.still_s,
            "model": {k: float(getattr(model, k)) for k in (
                "wheel_radius_left_m", "wheel_radius_right_m", "wheel_base_m", "gyro_scale", "gyro_bias_radps",
                "gyro_noise_radps_sqrt_hz", "wheel_noise_m_sqrt_m", "wheel_radius_left_sigma_m",
                "wheel_radius_right_sigma_m", "wheel_base_sigma_m", "gyro_scale_sigma",
                "gyro_bias_sigma_radps", "accel_noise_mps2_sqrt_hz", "accel_noise_sigma",
                "angular_accel_noise_radps2_sqrt_hz", "angular_accel_noise_sigma", *SLIP_EVENT_FIELDS)
                if getattr(model, k) is not None},
            "slip_events": (None if fit.slip_events is None else {
                "refused": fit.slip_events.refused, "events_seen": fit.slip_events.events_seen,
                "events_estimated": fit.slip_events.events_estimated, "demand_s": fit.slip_events.demand_s,
                "ratio_lo": fit.slip_events.ratio_lo, "ratio_hi": fit.slip_events.ratio_hi}),
            "residual_rms_before": np.sqrt(np.mean(fit.residuals_before ** 2, axis=0)).tolist(),
            "residual_rms_after": np.sqrt(np.mean(fit.residuals_after[fit.used] ** 2, axis=0)).tolist(),
        }, indent=2) + "\n")
    return 0
