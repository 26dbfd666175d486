"""The floor descriptor's format constants, modes, extraction parameters and learned tables
(:mod:`robotd.floor.descriptor` describes the six steps they serve)."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = ["ANGLE_BITS", "HEADER", "MAGIC", "MODE_BYTES", "MODES", "N_ATTRIBUTES", "N_ELEMENTS",
           "POSITION_STEP_PX", "QUARTER", "VERSION", "FULL_RESOLUTION", "ExtractParams", "Learned", "ModeSpec",
           "load_learned", "shipped_learned"]

MODE_BYTES = {1: 512, 2: 1024, 3: 2048, 4: 4096, 5: 8192, 6: 16384}
MAGIC = b"FD"
VERSION = 1
HEADER = struct.Struct("<2sBBHHHHHBBI")  # 20 bytes
POSITION_STEP_PX = 2  # coordinate grid, pixels of the working image
ANGLE_BITS = 5
N_ELEMENTS = 128  # transformed elements per descriptor (16 cells x 8)
N_ATTRIBUTES = 4  # selection attributes: response, edge ratio, centre distance, orientation strength


class ModeSpec(NamedTuple):
    """Per mode: byte bound, trits kept per local descriptor, global descriptor bits."""

    bytes: int
    length: int
    global_bits: int


MODES = {1: ModeSpec(512, 24, 256), 2: ModeSpec(1024, 32, 256), 3: ModeSpec(2048, 48, 512),
         4: ModeSpec(4096, 64, 512), 5: ModeSpec(8192, 96, 1024), 6: ModeSpec(16384, 128, 1024)}


@dataclass(frozen=True)
class ExtractParams:
    """Extraction parameters (lengths in pixels of the half-resolution image).

    The shipped ``selection.npz`` was learned with the defaults; change them and retrain.

    Fields:
        max_side_px: inputs with a longer side are first downscaled (area averaging) to it.
        detect_sigma_px: inner Gaussian of the difference of Gaussians.
        dog_ratio: outer / inner sigma of the difference of Gaussians.
        min_contrast: smallest |DoG| kept, in units of the image's standard deviation.
        edge_ratio: Hessian ratio above which an extremum is an edge and dropped (Lowe: 10).
        orientation_sigma_px: smoothing of the image whose gradient gives the orientation.
        pool_sigma_px: Gaussian pooling of the gradient orientation maps (cell support).
        pool_step: the pooled maps are kept at every ``pool_step``-th pixel (1 or 2): they
            are smooth at ``pool_sigma_px``. With 2 (the default) the orientation channels
            are split from the gradients at every pixel and halved (area averaging)
            before pooling, a quarter of the pixels pooled and sampled; with
            ``exact_maps`` the channels come from the gradients of the image halved
            instead (cheaper, coarser: the raw descriptors of the same keypoints lie a
            median 0.11 from those at every pixel against 0.03, and the demo's visual
            odometry lost accuracy with it).
        orientation_step: likewise for the gradient that gives the keypoints' orientation
            (smooth at ``orientation_sigma_px``; 2 takes it from the image halved, a median
            1.1 degrees off).
        detect_step: 2 finds the candidates on the half-resolution image halved again (a
            quarter of its pixels; the difference of Gaussians at the same scale, so at
            half the sigmas in its pixels), positions back in half-resolution pixels, the
            orientation (and with ``exact_maps`` the pooled maps) from its Gaussian image:
            :data:`QUARTER`. About 0.75 of the default's time, but the extrema of a
            difference of Gaussians at 0.9 px are sampled too coarsely to repeat across
            copies of one print, so the repeat check misses copies and the printed plank
            floor aliases (the view a lattice step away scores 0.76-1.2 of the true
            overlap in modes 2, 3 and 5 against 0.23-0.36; selection tables re-learned on
            such candidates do not change that), and the visual odometry's error
            per step grows by about a fifth: not the default.
        detect_prefilter: with ``detect_step`` 2, the image the candidates are found on is
            the half-resolution image smoothed at ``detect_sigma_px`` and halved (2 x 2 area
            averages), instead of the working image averaged over 4 x 4 blocks and smoothed:
            the box average folds fine texture back into the detection's band, which moves
            the extrema between copies of one print. On the printed plank floor's alias test
            the view a lattice step away scores 0.45-0.66 of the true overlap in modes 2, 3
            and 5 (without it 0.76-1.17; the default detection 0.23-0.36), at the same time
            as ``QUARTER``: still not under the test's half, so not the default.
        orientation_from_maps: the keypoints' orientation read from the pooled orientation
            maps (their 8 directions summed as vectors, smoothed by what
            ``orientation_sigma_px`` lacks, sampled at the keypoint) instead of the gradient
            of the image smoothed at ``orientation_sigma_px`` at every pixel: on office
            frames a median 0.6 degrees from it (90th percentile 2.1; ``orientation_step``
            2: 1.1 and 4.0), its strength 0.96 of it at the median (the selection tables
            not re-learned), at about half the orientation's time (0.87-0.95 of the
            extraction's). Only with ``detect_step`` 1 and the table-split maps. The ROC
            AUC on the benchmark floors and the printed planks within -0.0015..+0.0024 of
            the default's, the plank alias test held; but in the demo (office, seeds 0 and 1)
            the visual odometry's APE 0.057 and 0.104 against 0.049 and 0.086 m (the loops
            all true, none refused): not the default.
        exact_maps: True splits each gradient between the orientation channels exactly
            (per-pixel arithmetic and scatters); False (the default) looks the split up in a
            table of 256 angles, within 1/64 of the gradient's magnitude of the exact split:
            about half the time of building the channels.
            :data:`FULL_RESOLUTION` (``pool_step`` 1, ``exact_maps``) gives the bytes of
            the extraction before these defaults, exactly (docs/performance.md compares
            the two).
        cell_px: distance between the centres of neighbouring descriptor cells.
        max_candidates: cap on the candidates ranked (strongest responses first).
        repeat_distance: a keypoint whose own image holds another keypoint (beyond the
            descriptor's patch, ``4 cell_px``) with a raw descriptor nearer than this (L2 of
            the unit-norm 128-D descriptors) is a repeat and is not coded. 0.3 is about the
            90th percentile of the distance between two views of one floor point (measured
            on the virtual robot's floors; unrelated keypoints are 0.7-1.0 apart): the copy
            is as alike as a re-observation. 0 keeps every keypoint.
        repeat_pool: how many of the most relevant candidates are checked for repeats
            (the pairwise distances cost ``repeat_pool**2 x 128`` multiply-adds); candidates
            after them are kept unchecked. Enough for the largest mode's budget.
        repeat_pool_ratio: when > 0, the pool is at most this many times what the mode's
            budget codes with no repeat dropped (at least ``global_min_features``), plus
            one: cheaper (2 checks about 550 candidates in mode 4 instead of 1000), but a
            copy ranked below the pool is not found, and on the printed plank floor the
            view a lattice step away then scores 0.6-0.95 of the true overlap instead of
            0.23-0.36 (modes 2, 3, 5): not the default. 0: always ``repeat_pool``.
        global_min_features: the global descriptor aggregates at least this many of the
            best keypoints, even when fewer are coded (low modes).
        learned: learned tables; None = the shipped ``selection.npz``.
    """

    max_side_px: int = 1280
    detect_sigma_px: float = 1.8
    dog_ratio: float = 1.6
    min_contrast: float = 0.03
    edge_ratio: float = 10.0
    orientation_sigma_px: float = 4.0
    pool_sigma_px: float = 2.5
    pool_step: int = 2
    orientation_step: int = 1
    detect_step: int = 1
    detect_prefilter: bool = False
    orientation_from_maps: bool = False
    exact_maps: bool = False
    cell_px: float = 6.0
    max_candidates: int = 4000
    repeat_distance: float = 0.3
    repeat_pool: int = 1000
    repeat_pool_ratio: float = 0.0
    global_min_features: int = 200
    learned: Learned | None = None

    def __post_init__(self) -> None:
        if not (self.max_side_px >= 32 and self.detect_sigma_px > 0 and self.dog_ratio > 1
                and self.edge_ratio > 1 and self.orientation_sigma_px > 0 and self.pool_sigma_px > 0
                and self.pool_step in (1, 2) and self.orientation_step in (1, 2) and self.detect_step in (1, 2)
                and self.cell_px > 0 and self.max_candidates >= 1 and self.global_min_features >= 0
                and self.repeat_distance >= 0 and self.repeat_pool >= 0 and self.repeat_pool_ratio >= 0
                and not (self.orientation_from_maps and (self.detect_step != 1 or self.exact_maps))):
            raise ValueError(f"extraction parameters out of range: {self}")


FULL_RESOLUTION = ExtractParams(pool_step=1, exact_maps=True)
"""The maps at every pixel of the detection image with the exact channel split, and the
full repeat pool: the bytes the extraction gave before the faster defaults (selectable,
slower; the benchmarks time it beside the default)."""


QUARTER = ExtractParams(detect_step=2, exact_maps=True)
"""The candidates, their orientation and the pooled maps from the image halved again (a
quarter of the half-resolution pixels; ``detect_step``): the cheapest extraction, which
fails the printed plank floor's alias suppression (selectable, not the default; the
benchmarks time it beside the default)."""


@dataclass(frozen=True, eq=False)
class Learned:
    """The learned tables (``selection.npz``, made by ``tools/train_selection.py``).

    ``rel_edges (4, B-1)`` bin edges and ``rel_logp (4, B)`` log P(match | bin) of the
    selection attributes; ``tern_lo``, ``tern_hi (128,)`` ternary thresholds of the
    transformed elements; ``order (128,)`` element priority; ``pca_mean (128,)``,
    ``pca_basis (128, 32)``, ``centroids (32, 32)`` and ``signs (1024,)`` (+-1) of the
    global descriptor.
    """

    rel_edges: np.ndarray
    rel_logp: np.ndarray
    tern_lo: np.ndarray
    tern_hi: np.ndarray
    order: np.ndarray
    pca_mean: np.ndarray
    pca_basis: np.ndarray
    centroids: np.ndarray
    signs: np.ndarray


def load_learned(path: str | Path | None = None) -> Learned:
    """Read learned tables from ``path`` (default: the ``selection.npz`` shipped here)."""
    if path is None:
        return shipped_learned()
    with np.load(path) as z:
        return Learned(**{k: np.array(z[k]) for k in Learned.__dataclass_fields__})


@lru_cache(maxsize=1)
def shipped_learned() -> Learned:
    """The learned tables shipped with robotd (read once)."""
    with resources.as_file(resources.files("robotd.floor") / "selection.npz") as p:
        return load_learned(p)
