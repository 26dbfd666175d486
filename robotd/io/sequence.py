"""Image sequences on disk and their ground-truth loop matrices (``robotd eval forward``).

A sequence is a folder of image files taken in order; the order is the files' *natural*
name order (``2.jpg`` before ``10.jpg``, ``img9`` before ``img10``). The ground truth is an
``N x N`` matrix, non-zero where images i and j show the same place, stored as ``.npy``,
``.csv`` / ``.txt`` (comma- or whitespace-separated numbers), or an image (BMP, PNG, PGM,
TIFF, ...: one pixel per pair, non-zero = same place). Only one triangle may be filled
(a later image against earlier ones, or the reverse): the matrix is made symmetric.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from robotd.base.errors import SequenceError

__all__ = ["IMAGE_SUFFIXES", "list_images", "load_ground_truth", "natural_key", "read_image"]

#: File suffixes taken as images of a sequence (case-insensitive).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".pgm", ".ppm", ".tif", ".tiff", ".webp")

_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple[tuple[int, int | str, str], ...]:
    """Sort key ordering digit runs by value: ``2.jpg`` < ``10.jpg``, ``a9b`` < ``a10b``."""
    parts = _DIGITS.split(name)
    return tuple((0, int(p), p) if k % 2 else (1, p.lower(), p) for k, p in enumerate(parts))


def list_images(folder: Path, exclude: tuple[Path, ...] = ()) -> list[Path]:
    """The image files of ``folder`` in natural name order (``exclude``: files that are
    not part of the sequence, such as a ground-truth image kept alongside)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SequenceError(f"image folder {folder} does not exist or is not a folder")
    skip = {p.resolve() for p in exclude}
    files = [p for p in folder.iterdir()
             if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and p.resolve() not in skip]
    if not files:
        raise SequenceError(f"image folder {folder} holds no images ({', '.join(IMAGE_SUFFIXES)})")
    return sorted(files, key=lambda p: natural_key(p.name))


def read_image(path: Path) -> np.ndarray:
    """One image as ``(H, W, 3)`` BGR uint8 (OpenCV's order); a clear error if unreadable."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise SequenceError(f"cannot read image {path} (missing, truncated or not an image)")
    return img


def load_ground_truth(path: Path, n_images: int | None = None) -> np.ndarray:
    """The symmetric ``(N, N) bool`` same-place matrix from ``path`` (diagonal cleared).

    ``n_images``: when given, the matrix must be that size. Raises
    :class:`~robotd.base.errors.SequenceError` with the reason otherwise.
    """
    path = Path(path)
    if not path.is_file():
        what = "is a folder, not a file" if path.is_dir() else "does not exist"
        raise SequenceError(f"ground-truth file {path} {what}")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            m = np.load(path, allow_pickle=False)
        elif suffix in (".csv", ".txt"):
            text = path.read_text()
            delim = "," if "," in text else None
            m = np.loadtxt(path, delimiter=delim, ndmin=2)
        elif suffix == ".mat":
            m = _matlab_matrix(path)
        elif suffix in IMAGE_SUFFIXES:
            import cv2

            m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if m is None:
                raise SequenceError(f"cannot read ground-truth image {path}")
        else:
            raise SequenceError(f"ground-truth file {path}: unknown format {suffix!r} "
                                "(use .npy, .csv, .txt, .mat or an image such as .bmp/.png)")
    except SequenceError:
        raise
    except (OSError, ValueError, NotImplementedError) as exc:
        raise SequenceError(f"cannot read ground-truth file {path}: {exc}") from None
    m = np.asarray(m)
    if m.ndim != 2 or m.shape[0] != m.shape[1]:
        raise SequenceError(f"ground truth {path} is {'x'.join(map(str, m.shape))}, not a square matrix")
    if n_images is not None and m.shape[0] != n_images:
        raise SequenceError(f"ground truth {path} is {m.shape[0]}x{m.shape[1]} but the sequence "
                            f"has {n_images} images")
    if m.dtype.kind not in "biuf":
        raise SequenceError(f"ground truth {path} is not numeric (dtype {m.dtype})")
    if m.dtype.kind == "f" and not np.isfinite(m).all():
        bad = np.argwhere(~np.isfinite(m))[0]
        raise SequenceError(f"ground truth {path} holds {int((~np.isfinite(m)).sum())} values that "
                            f"are not numbers (NaN or infinite), the first at row {bad[0]}, column "
                            f"{bad[1]}: every pair must be 0 (different places) or 1 (same place)")
    truth = m != 0
    truth = truth | truth.T
    np.fill_diagonal(truth, False)
    return truth


def _matlab_matrix(path: Path) -> np.ndarray:
    """The ground-truth matrix of a MATLAB ``.mat`` file, as the public loop-closure
    datasets publish it (Lip6, NewCollege, CityCentre: a variable such as ``truth`` or
    ``GroundTruth``, N x N, possibly sparse): the largest square numeric 2-D variable.
    MATLAB v7.3 files (HDF5) are not read (scipy cannot)."""
    from scipy import io as sio
    from scipy import sparse

    try:
        data = sio.loadmat(str(path))
    except Exception as exc:  # noqa: BLE001 - scipy raises IndexError, ValueError, ... on damage
        raise SequenceError(f"cannot read ground-truth file {path}: not a readable MATLAB file "
                            f"({type(exc).__name__}: {exc or 'truncated'})") from None
    best = None
    for key, value in data.items():
        if key.startswith("__"):
            continue
        if sparse.issparse(value):
            value = value.toarray()
        a = np.asarray(value)
        if a.ndim == 2 and a.shape[0] == a.shape[1] and a.dtype.kind in "biuf":
            if best is None or a.shape[0] > best.shape[0]:
                best = a
    if best is None:
        names = ", ".join(k for k in data if not k.startswith("__")) or "none"
        raise SequenceError(f"ground-truth file {path}: no square numeric matrix among its variables ({names})")
    return best
