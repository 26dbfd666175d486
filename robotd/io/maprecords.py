"""The rows of the map store as records, and how their values are encoded in the file.

:class:`~robotd.io.store.MapStore` returns these frozen records; matrices are stored as 9
little-endian float64 (row-major), and every pose and matrix is checked finite before it
is written.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from robotd.base.messages import LoopFate

__all__ = ["KeyframeRecord", "LinkRecord", "LoopCandidateRecord", "RunRecord", "blob_to_matrix",
           "candidate_record", "check_descriptor", "finite_triple", "matrix_to_blob"]

_MATRIX_DTYPE = np.dtype("<f8")

UNCLEAN_END_NOTE = "did not end cleanly"
"""Begins the note :meth:`MapStore.mark_unfinished_runs` adds to a run that never ended."""


@dataclass(frozen=True, slots=True)
class RunRecord:
    """One daemon run as stored in ``runs``; ``ended_ns`` is None while running, or for a
    run that never ended (killed, power cut) until the next start marks it (see
    :meth:`MapStore.mark_unfinished_runs` and :attr:`ended_cleanly`)."""

    id: int
    started_ns: int
    ended_ns: int | None
    config: str
    robotd_version: str
    notes: str
    epoch_unix_ns: int | None = None

    @property
    def ended_cleanly(self) -> bool:
        """True when the run recorded its own end."""
        return self.ended_ns is not None and UNCLEAN_END_NOTE not in self.notes


@dataclass(frozen=True, slots=True, eq=False)
class KeyframeRecord:
    """A keyframe without its image (fetch that with :meth:`MapStore.keyframe_image`).

    ``covariance`` is ``(3, 3) float64`` over ``(x_m, y_m, yaw_rad)``, read-only.
    ``image_width``/``image_height`` are pixels, None when no image was stored.
    """

    id: int
    run_id: int
    stamp_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    covariance: np.ndarray
    image_width: int | None
    image_height: int | None
    descriptor: bytes | None
    descriptor_mode: int | None


@dataclass(frozen=True, slots=True, eq=False)
class LinkRecord:
    """A pose-graph edge: the pose of ``to_id`` in the frame of ``from_id``.

    ``information`` is ``(3, 3) float64`` over ``(dx_m, dy_m, dyaw_rad)``, read-only.
    """

    id: int
    kind: str
    from_id: int
    to_id: int
    dx_m: float
    dy_m: float
    dyaw_rad: float
    information: np.ndarray


@dataclass(frozen=True, slots=True)
class LoopCandidateRecord:
    """A loop-closure candidate: keyframe ``candidate_id`` proposed for ``query_id`` with
    the local ``score`` (unitless), its ``fate`` and free-form ``detail``."""

    id: int
    query_id: int
    candidate_id: int
    score: float
    fate: LoopFate
    detail: str


def candidate_record(row: tuple[int, int, int, float, str, str]) -> LoopCandidateRecord:
    """A ``loop_candidates`` row ``(id, query_id, candidate_id, score, fate, detail)``."""
    i, query_id, candidate_id, score, fate, detail = row
    return LoopCandidateRecord(i, query_id, candidate_id, score, LoopFate(fate), detail)


def matrix_to_blob(matrix: np.ndarray | Sequence[Sequence[float]], what: str) -> bytes:
    array = np.asarray(matrix, dtype=np.float64)
    if array.shape != (3, 3):
        raise ValueError(f"{what} must have shape (3, 3), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} must be finite")
    return array.astype(_MATRIX_DTYPE).tobytes()


def blob_to_matrix(blob: bytes) -> np.ndarray:
    array = np.frombuffer(blob, dtype=_MATRIX_DTYPE).astype(np.float64).reshape(3, 3)
    array.setflags(write=False)
    return array


def finite_triple(values: Sequence[float] | np.ndarray, what: str) -> tuple[float, float, float]:
    if len(values) != 3:
        raise ValueError(f"{what} must have 3 elements, got {len(values)}")
    triple = (float(values[0]), float(values[1]), float(values[2]))
    if not all(math.isfinite(v) for v in triple):
        raise ValueError(f"{what} must be finite, got {triple}")
    return triple


def check_descriptor(descriptor: bytes | None, mode: int | None) -> None:
    if (descriptor is None) != (mode is None):
        raise ValueError("descriptor and descriptor_mode must be given together")
    if descriptor is not None and not isinstance(descriptor, bytes | bytearray | memoryview):
        raise TypeError(f"descriptor must be bytes, got {type(descriptor).__name__}")
