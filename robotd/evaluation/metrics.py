"""Trajectory metrics against ground truth, with evo's names and options.

Every trajectory is ``(N, 3)`` poses ``(x_m, y_m, yaw_rad)`` at the same stamps as the
truth's. The metrics are those of evo (Grupp, https://github.com/MichaelGrupp/evo), planar:

- **APE, translation part** (evo ``ape --pose_relation trans_part``): the position error
  of each pose, as an RMS (and max, end) over the trajectory. It depends on how the
  estimate is first put into the truth's frame, which every name here says:

  - ``origin`` (evo ``--align_origin``): the estimate's first pose is moved onto the
    truth's first pose, nothing fitted. Odometry starts at its own origin; anchored this
    way its drift shows in full. robotd's demo, daemon and odometry figures use it.
  - ``aligned`` (evo ``--align``, Umeyama without scale): the rigid 2-D transform that
    fits the whole estimate onto the truth in least squares is applied first. It measures
    the shape of the trajectory, whatever its placement; the pose-graph benchmarks use it
    (their reference is an optimum in an arbitrary frame).

- **RPE per step** (evo ``rpe --delta 1 --delta_unit f``): the error of each
  pose-to-pose step ``between(p[i], p[i+1])``, translation (m) and rotation (rad), RMS.

Pure functions of arrays: no I/O (TUM files are :mod:`robotd.io.trajectory`'s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from robotd.base.geometry import between, compose, inverse, rigid_fit_2d, wrap_angle

__all__ = ["Alignment", "OdometryErrors", "align", "align_origin", "align_rigid", "ape_translation", "ape_translation_rmse",
           "odometry_errors", "rpe_per_step"]


class Alignment(StrEnum):
    """How an estimate is put into the truth's frame before its APE (evo's option)."""

    ORIGIN = "origin"
    """First pose onto the truth's first pose (evo ``--align_origin``); nothing fitted."""
    ALIGNED = "aligned"
    """Rigid 2-D least-squares fit of all positions (evo ``--align``, Umeyama, no scale)."""


def _check_pair(truth: np.ndarray, estimate: np.ndarray, minimum: int = 1) -> None:
    if truth.shape != estimate.shape or truth.ndim != 2 or truth.shape[1] != 3 or len(truth) < minimum:
        raise ValueError(f"truth and estimate must be (N, 3) arrays of the same length, N >= {minimum}")


def align_origin(first_truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """``estimate (N, 3)`` moved so that its first pose is ``first_truth (3,)`` (evo's
    ``--align_origin``): odometry, which starts at its own origin, in the truth's frame.
    No fitting, so drift is not hidden."""
    return compose(compose(first_truth, inverse(estimate[0])), estimate)


def align_rigid(truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """``estimate (N, 3)`` moved by the rigid 2-D transform whose positions best fit the
    truth's in least squares (evo's ``--align``: Umeyama without scale; N >= 2)."""
    fit = rigid_fit_2d(estimate[:, :2], truth[:, :2])
    return compose(fit, estimate)


def align(truth: np.ndarray, estimate: np.ndarray, alignment: Alignment) -> np.ndarray:
    """``estimate`` in the truth's frame by ``alignment``."""
    _check_pair(truth, estimate, 2 if alignment is Alignment.ALIGNED else 1)
    if alignment is Alignment.ALIGNED:
        return align_rigid(truth, estimate)
    return align_origin(truth[0], estimate)


def ape_translation(truth: np.ndarray, estimate: np.ndarray, alignment: Alignment) -> np.ndarray:
    """The translation part of the absolute pose error: ``(N,)`` position errors (m) of
    ``estimate`` against ``truth`` after ``alignment`` (evo ``ape --pose_relation
    trans_part``; the RMS of this is the figure called ATE in the literature)."""
    est = align(truth, estimate, alignment)
    return np.asarray(np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1]))


def ape_translation_rmse(truth: np.ndarray, estimate: np.ndarray, alignment: Alignment) -> float:
    """RMS of :func:`ape_translation`, metres."""
    err = ape_translation(truth, estimate, alignment)
    return float(np.sqrt(np.mean(err ** 2)))


def rpe_per_step(truth: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """RPE between consecutive poses (evo ``rpe --delta 1 --delta_unit f``): RMS of the
    translation error (m) and of the rotation error (rad) of each step ``between(p[i],
    p[i+1])``; both ``(N, 3)`` at the same stamps, N >= 2. No alignment is needed."""
    _check_pair(truth, estimate, 2)
    dt = between(truth[:-1], truth[1:])
    de = between(estimate[:-1], estimate[1:])
    trans = np.hypot(de[:, 0] - dt[:, 0], de[:, 1] - dt[:, 1])
    rot = np.asarray(wrap_angle(de[:, 2] - dt[:, 2]))
    return float(np.sqrt(np.mean(trans ** 2))), float(np.sqrt(np.mean(rot ** 2)))


@dataclass(frozen=True)
class OdometryErrors:
    """How far an odometry trajectory is from ground truth (same stamps), anchored at the
    origin (:attr:`Alignment.ORIGIN`): the drift as it accumulates."""

    distance_m: float
    """Length of the true path."""
    end_position_error_m: float
    end_heading_error_deg: float
    ape_origin_max_m: float
    """Largest position error."""
    ape_origin_rmse_m: float
    """RMS position error (APE, translation part, origin-anchored)."""

    @property
    def end_drift_per_100m(self) -> float:
        return 100.0 * self.end_position_error_m / self.distance_m if self.distance_m > 0 else math.nan

    @property
    def max_drift_per_100m(self) -> float:
        return 100.0 * self.ape_origin_max_m / self.distance_m if self.distance_m > 0 else math.nan

    def as_dict(self) -> dict[str, float]:
        return {
            "distance_m": self.distance_m,
            "end_position_error_m": self.end_position_error_m,
            "end_heading_error_deg": self.end_heading_error_deg,
            "ape_origin_max_m": self.ape_origin_max_m,
            "ape_origin_rmse_m": self.ape_origin_rmse_m,
            "end_drift_per_100m_m": self.end_drift_per_100m,
            "max_drift_per_100m_m": self.max_drift_per_100m,
        }


def odometry_errors(truth: np.ndarray, estimate: np.ndarray) -> OdometryErrors:
    """:class:`OdometryErrors` of ``estimate`` against ``truth``, both ``(N, 3)`` at the
    same stamps (N >= 1), the estimate anchored at the truth's first pose."""
    _check_pair(truth, estimate)
    est = align_origin(truth[0], estimate)
    err = np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1])
    distance = float(np.sum(np.hypot(np.diff(truth[:, 0]), np.diff(truth[:, 1]))))
    return OdometryErrors(
        distance_m=distance,
        end_position_error_m=float(err[-1]),
        end_heading_error_deg=math.degrees(abs(float(wrap_angle(float(est[-1, 2] - truth[-1, 2]))))),
        ape_origin_max_m=float(err.max()),
        ape_origin_rmse_m=float(np.sqrt(np.mean(err ** 2))),
    )
