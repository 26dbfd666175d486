"""Trajectories: TUM text files (so ``evo`` can read them) and planar error metrics.

A trajectory is ``stamps_ns (N,) int64`` with ``poses (N, 3) float64`` as
``(x_m, y_m, yaw_rad)``. TUM lines are ``t x y z qx qy qz qw`` with ``t`` in seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from robotd.base.files import replacing
from robotd.base.geometry import between, compose, inverse, quaternion_to_yaw, wrap_angle, yaw_to_quaternion


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


@dataclass(frozen=True)
class TrajectoryErrors:
    """How far an estimated trajectory is from ground truth (same stamps)."""

    distance_m: float
    end_position_error_m: float
    end_heading_error_deg: float
    max_position_error_m: float
    rmse_position_m: float

    @property
    def end_drift_per_100m(self) -> float:
        return 100.0 * self.end_position_error_m / self.distance_m if self.distance_m > 0 else math.nan

    @property
    def max_drift_per_100m(self) -> float:
        return 100.0 * self.max_position_error_m / self.distance_m if self.distance_m > 0 else math.nan

    def as_dict(self) -> dict[str, float]:
        return {
            "distance_m": self.distance_m,
            "end_position_error_m": self.end_position_error_m,
            "end_heading_error_deg": self.end_heading_error_deg,
            "max_position_error_m": self.max_position_error_m,
            "rmse_position_m": self.rmse_position_m,
            "end_drift_per_100m_m": self.end_drift_per_100m,
            "max_drift_per_100m_m": self.max_drift_per_100m,
        }


def anchor_to(first_truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """Express an odometry trajectory (which starts at its own origin) in the truth's frame.

    Odometry starts at identity at its first sample; ground truth starts wherever the
    route starts. This is the only alignment done: no fitting, so drift is not hidden.
    """
    return compose(compose(first_truth, inverse(estimate[0])), estimate)


def trajectory_errors(truth: np.ndarray, estimate: np.ndarray) -> TrajectoryErrors:
    """Errors of ``estimate`` against ``truth``, both ``(N, 3)`` at the same stamps."""
    if truth.shape != estimate.shape or truth.ndim != 2 or len(truth) == 0:
        raise ValueError("truth and estimate must be (N, 3) arrays of the same length")
    est = anchor_to(truth[0], estimate)
    err = np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1])
    distance = float(np.sum(np.hypot(np.diff(truth[:, 0]), np.diff(truth[:, 1]))))
    return TrajectoryErrors(
        distance_m=distance,
        end_position_error_m=float(err[-1]),
        end_heading_error_deg=float(math.degrees(abs(wrap_angle(float(est[-1, 2] - truth[-1, 2]))))),
        max_position_error_m=float(err.max()),
        rmse_position_m=float(np.sqrt(np.mean(err ** 2))),
    )


def relative_pose_error(truth: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """RPE between consecutive poses: RMS of the translation error (m) and of the heading
    error (rad) of each step ``between(p[i], p[i+1])``, both ``(N, 3)`` at the same stamps."""
    if truth.shape != estimate.shape or len(truth) < 2:
        raise ValueError("truth and estimate must be (N, 3) arrays of the same length, N >= 2")
    dt = between(truth[:-1], truth[1:])
    de = between(estimate[:-1], estimate[1:])
    trans = np.hypot(de[:, 0] - dt[:, 0], de[:, 1] - dt[:, 1])
    rot = wrap_angle(de[:, 2] - dt[:, 2])
    return float(np.sqrt(np.mean(trans ** 2))), float(np.sqrt(np.mean(np.asarray(rot) ** 2)))
