"""Trajectories as TUM text files (so ``evo`` can read them), and the observer that writes
the daemon's odometry to them as it comes.

A trajectory is ``stamps_ns (N,) int64`` with ``poses (N, 3) float64`` as
``(x_m, y_m, yaw_rad)``. TUM lines are ``t x y z qx qy qz qw`` with ``t`` in seconds. The
error metrics against ground truth are :mod:`robotd.evaluation.metrics`'.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TextIO

import numpy as np

from robotd.base.files import replacing
from robotd.base.geometry import quaternion_to_yaw, yaw_to_quaternion
from robotd.base.messages import OdometryUpdate, WheelTicks
from robotd.odometry.kinematics import DiffDriveParams, WheelOdometry


def format_tum_line(stamp_ns: int, x_m: float, y_m: float, yaw_rad: float) -> str:
    qx, qy, qz, qw = yaw_to_quaternion(yaw_rad)
    return (f"{stamp_ns / 1e9:.9f} {x_m:.6f} {y_m:.6f} 0.000000 "
            f"{qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}\n")


def write_tum(path: Path | str, stamps_ns: np.ndarray, poses: np.ndarray) -> None:
    """Write a whole trajectory as a TUM file, replacing ``path`` atomically (a full disk or
    an interruption leaves the previous file as it was; :class:`OutputError`)."""
    with replacing(Path(path), "w", encoding="ascii") as f:
        f.write("# timestamp x y z qx qy qz qw\n")
        for t, p in zip(stamps_ns, poses):
            f.write(format_tum_line(int(t), float(p[0]), float(p[1]), float(p[2])))


class TumWriter:
    """Appends poses to a TUM file as they come (the daemon's trajectories)."""

    def __init__(self, path: Path | str) -> None:
        self._f: TextIO = open(path, "w", encoding="ascii")
        self._f.write("# timestamp x y z qx qy qz qw\n")

    def write(self, stamp_ns: int, x_m: float, y_m: float, yaw_rad: float) -> None:
        self._f.write(format_tum_line(stamp_ns, x_m, y_m, yaw_rad))

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()


def read_tum(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file into ``(stamps_ns, poses (N, 3))`` (yaw from the quaternion)."""
    stamps, poses = [], []
    with open(path, encoding="ascii") as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            if len(parts) != 8:
                raise ValueError(f"{path}:{n}: expected 8 fields, got {len(parts)}")
            t, x, y, _z, qx, qy, qz, qw = map(float, parts)
            stamps.append(int(round(t * 1e9)))
            poses.append((x, y, quaternion_to_yaw(qx, qy, qz, qw)))
    return np.asarray(stamps, dtype=np.int64), np.asarray(poses, dtype=float).reshape(-1, 3)


class TumRecorder:
    """Pipeline observer: writes the fused and the wheel-only odometry to ``fused.tum`` and
    ``wheel.tum`` in ``folder`` as the updates come. With ``nominal_drive`` (the nominal wheel
    geometry, when the daemon runs a calibrated odometry model) it also integrates the wheel
    ticks with that geometry into ``wheel_nominal.tum``: the odometry before calibration."""

    name = "tum_recorder"

    def __init__(self, folder: Path, nominal_drive: DiffDriveParams | None = None) -> None:
        self.fused = TumWriter(folder / "fused.tum")
        self.wheel = TumWriter(folder / "wheel.tum")
        self.nominal = WheelOdometry(nominal_drive) if nominal_drive is not None else None
        self.wheel_nominal = TumWriter(folder / "wheel_nominal.tum") if nominal_drive is not None else None

    def subscriptions(self) -> dict[type, Callable[..., None]]:
        subs: dict[type, Callable[..., None]] = {OdometryUpdate: self.on_odometry}
        if self.nominal is not None:
            subs[WheelTicks] = self.on_ticks
        return subs

    def on_odometry(self, u: OdometryUpdate) -> None:
        self.fused.write(u.fused.stamp_ns, u.fused.x_m, u.fused.y_m, u.fused.yaw_rad)
        self.wheel.write(u.wheel.stamp_ns, u.wheel.x_m, u.wheel.y_m, u.wheel.yaw_rad)

    def on_ticks(self, msg: WheelTicks) -> None:
        assert self.nominal is not None and self.wheel_nominal is not None  # subscribed only then
        p = self.nominal.update(msg)
        self.wheel_nominal.write(p.stamp_ns, p.x_m, p.y_m, p.yaw_rad)

    def close(self) -> None:
        self.fused.close()
        self.wheel.close()
        if self.wheel_nominal is not None:
            self.wheel_nominal.close()
