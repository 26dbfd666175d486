"""Camera intrinsics from chessboard photos (Zhang's method, through OpenCV).

The procedure is the one of OpenCV's own calibration sample (``samples/cpp/calibration.cpp``),
which produced the published result for the sample photos
(``../shared/data/calibration/opencv_left/left_intrinsics.yml``: ``flags: 2`` =
``CALIB_FIX_ASPECT_RATIO``, ``aspectRatio: 1``), so that a user gets the numbers they
would get from OpenCV:

* corners: ``cv2.findChessboardCorners`` with adaptive threshold, fast check and image
  normalisation, refined by ``cv2.cornerSubPix`` with an 11x11 half-window (a 23x23 px
  search window), no dead zone, 30 iterations or 1e-4 px;
* board points ``(col * square, row * square, 0)``;
* ``cv2.calibrateCamera`` with the 5-coefficient model (k1 k2 p1 p2 k3); with
  ``fix_aspect_ratio`` the ratio fx/fy is held at 1 (``CALIB_FIX_ASPECT_RATIO`` with an
  identity initial matrix);
* errors as the sample reports them: per image the RMS distance between detected and
  reprojected corners, overall the RMS over all corners (``avg_reprojection_error``,
  equal to the value ``calibrateCamera`` returns).

Images that cannot be used are not errors but results: each rejected image carries
the reason (unreadable, wrong size, corners not found).
"""

from __future__ import annotations

import argparse
import enum
import logging
import math
import os
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence, TextIO

import cv2
import numpy as np

from robotd.base.camera import CameraIntrinsics
from robotd.io.calibfile import CalibrationFile, update_calibration
from robotd.base.errors import CalibrationError

logger = logging.getLogger(__name__)

__all__ = [
    "IntrinsicsResult",
    "ProgressBar",
    "RejectReason",
    "RejectedImage",
    "add_intrinsics_arguments",
    "board_object_points",
    "calibrate_intrinsics",
    "find_board_corners",
    "format_intrinsics_report",
    "parse_board",
    "run_intrinsics",
]

#: findChessboardCorners flags of OpenCV's calibration sample.
CHESSBOARD_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK | cv2.CALIB_CB_NORMALIZE_IMAGE
#: cornerSubPix half-window, pixels (the usual 11x11 of OpenCV's sample).
SUBPIX_WINDOW = (11, 11)
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 1e-4)
#: Fewest usable views for a calibration worth having.
MIN_IMAGES = 3

ProgressFn = Callable[[int, int, str], None]


class RejectReason(str, enum.Enum):
    """Why an image was left out of the calibration."""

    UNREADABLE = "unreadable"
    WRONG_SIZE = "wrong size"
    CORNERS_NOT_FOUND = "corners not found"


@dataclass(frozen=True)
class RejectedImage:
    """An image left out, why (``reason``) and the particulars (``detail``)."""

    path: str
    reason: RejectReason
    detail: str


@dataclass(frozen=True, eq=False)
class IntrinsicsResult:
    """The outcome of :func:`calibrate_intrinsics`.

    Fields:
        intrinsics: the calibrated camera matrix, distortion ``(k1, k2, p1, p2, k3)`` and
            image size.
        rms_error_px: RMS reprojection error over all corners of all used images, pixels
            (what OpenCV's sample writes as ``avg_reprojection_error``).
        mean_error_px: mean Euclidean reprojection error per corner, pixels (<= RMS).
        per_image_error_px: RMS reprojection error of each used image, pixels, in the
            order of ``used_images``.
        std_dev_px: standard deviations of ``(fx, fy, cx, cy)`` estimated by OpenCV from the
            residuals (assumes independent corner errors), pixels.
        used_images: paths of the images that entered the calibration, input order.
        rejected: images left out, input order, each with its reason.
        board_inner_corners: ``(columns, rows)`` of inner corners.
        square_size_m: side of a board square, metres.
        flags: the ``cv2.calibrateCamera`` flags used.
    """

    intrinsics: CameraIntrinsics
    rms_error_px: float
    mean_error_px: float
    per_image_error_px: tuple[float, ...]
    std_dev_px: tuple[float, float, float, float]
    used_images: tuple[str, ...]
    rejected: tuple[RejectedImage, ...]
    board_inner_corners: tuple[int, int]
    square_size_m: float
    flags: int

    def calibration_file(self) -> CalibrationFile:
        """The calibration-file part of this result: the intrinsics and their RMS error."""
        return CalibrationFile(intrinsics=self.intrinsics, reprojection_error_px=self.rms_error_px)


# --------------------------------------------------------------------- the board


def parse_board(text: str) -> tuple[int, int]:
    """``"9x6"`` -> ``(9, 6)``: inner corners along the board's two sides (both >= 2)."""
    parts = text.lower().replace("*", "x").split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"board must be COLSxROWS inner corners, e.g. 9x6; got {text!r}") from None
    if cols < 2 or rows < 2:
        raise argparse.ArgumentTypeError(f"a board needs at least 2x2 inner corners, got {text!r}")
    return cols, rows


def board_object_points(board_inner_corners: tuple[int, int], square_size_m: float) -> np.ndarray:
    """Inner corners in the board frame, ``(cols * rows, 3) float32`` metres.

    Row-major like OpenCV's corner order: point ``k = row * cols + col`` is at
    ``(col * square_size_m, row * square_size_m, 0)``.
    """
    cols, rows = board_inner_corners
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float64) * float(square_size_m)
    return np.column_stack([grid, np.zeros(len(grid))]).astype(np.float32)


def find_board_corners(gray: np.ndarray, board_inner_corners: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners of a chessboard, ``(cols * rows, 2) float32`` px, or None.

    ``gray`` is a ``(H, W) uint8`` image. Corners come in OpenCV's order (row by row).
    """
    found, corners = cv2.findChessboardCorners(gray, tuple(board_inner_corners), flags=CHESSBOARD_FLAGS)
    if not found or corners is None:
        return None
    corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2).astype(np.float32), SUBPIX_WINDOW, (-1, -1),
                               SUBPIX_CRITERIA)
    return corners.reshape(-1, 2)


def _load_gray(path: str) -> tuple[np.ndarray | None, str]:
    """``(image, "")`` or ``(None, why it cannot be read)``."""
    if not os.path.exists(path):
        return None, "no such file"
    if os.path.isdir(path):
        return None, "is a directory"
    # Colour, then grey through cvtColor, as OpenCV's sample does (JPEG decoders convert
    # colour to grey slightly differently when asked for grey directly).
    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        return None, "not an image OpenCV can decode"
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), ""


# ------------------------------------------------------------------- calibration


def _find_boards(paths: list[str], board: tuple[int, int], progress: ProgressFn | None,
                 ) -> tuple[tuple[int, int], dict[int, np.ndarray], tuple[RejectedImage, ...]]:
    """The common image size, the board corners per usable image index, and the rejected
    images with their reasons. One pass, one image in memory at a time."""
    cols, rows = board
    rejected: dict[int, RejectedImage] = {}
    found: dict[int, tuple[tuple[int, int], np.ndarray | None]] = {}  # size, corners
    for i, path in enumerate(paths):
        gray, why = _load_gray(path)
        if gray is None:
            rejected[i] = RejectedImage(path, RejectReason.UNREADABLE, why)
        else:
            found[i] = ((gray.shape[1], gray.shape[0]), find_board_corners(gray, (cols, rows)))
        if progress is not None:
            progress(i + 1, len(paths), path)
    sizes = Counter(s for s, _ in found.values())
    # most_common keeps first-seen order among equal counts.
    size = sizes.most_common(1)[0][0] if sizes else (0, 0)
    corners: dict[int, np.ndarray] = {}
    for i, (got, c) in found.items():
        if got != size:
            rejected[i] = RejectedImage(paths[i], RejectReason.WRONG_SIZE,
                                        f"{got[0]}x{got[1]}, the others are {size[0]}x{size[1]}")
        elif c is None:
            rejected[i] = RejectedImage(paths[i], RejectReason.CORNERS_NOT_FOUND, f"no {cols}x{rows} chessboard found")
        else:
            corners[i] = c
    rejected_list = tuple(rejected[i] for i in sorted(rejected))
    for r in rejected_list:
        logger.debug("rejected %s: %s (%s)", r.path, r.reason.value, r.detail)
    return size, corners, rejected_list


def calibrate_intrinsics(
    images: Sequence[str | os.PathLike[str]],
    board_inner_corners: tuple[int, int] = (9, 6),
    square_size_m: float = 0.025,
    fix_aspect_ratio: bool = False,
    progress: ProgressFn | None = None,
) -> IntrinsicsResult:
    """Calibrate a camera from photos of a chessboard.

    ``images``: image files (any format OpenCV reads); ``board_inner_corners``: inner
    corners ``(columns, rows)``; ``square_size_m``: square side, metres (scales only the
    board poses, not the intrinsics); ``fix_aspect_ratio``: hold fx = fy;
    ``progress(done, total, path)`` is called after each image.

    The image size is the most common size among the readable images; images of another
    size are rejected. Raises :class:`~robotd.base.errors.CalibrationError` when fewer than
    ``MIN_IMAGES`` images are usable (the message lists what was rejected and why) or
    when OpenCV cannot solve the calibration.
    """
    cols, rows = int(board_inner_corners[0]), int(board_inner_corners[1])
    if cols < 2 or rows < 2:
        raise CalibrationError(f"a board needs at least 2x2 inner corners, got {cols}x{rows}")
    if not (math.isfinite(square_size_m) and square_size_m > 0.0):
        raise CalibrationError(f"square size must be positive, got {square_size_m}")
    paths = [os.fspath(p) for p in images]
    total = len(paths)
    size, corners, rejected_list = _find_boards(paths, (cols, rows), progress)
    used = sorted(corners)
    if len(used) < MIN_IMAGES:
        listing = "; ".join(f"{os.path.basename(r.path)}: {r.reason.value}" for r in rejected_list[:10])
        more = f" (and {len(rejected_list) - 10} more)" if len(rejected_list) > 10 else ""
        raise CalibrationError(
            f"only {len(used)} of {total} images are usable, need at least {MIN_IMAGES}"
            + (f"; rejected: {listing}{more}" if listing else ""))

    obj = board_object_points((cols, rows), square_size_m)
    object_points = [obj] * len(used)
    image_points = [corners[i].reshape(-1, 1, 2) for i in used]
    flags = cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect_ratio else 0
    k0 = np.eye(3)  # with CALIB_FIX_ASPECT_RATIO only fx/fy = 1 is taken from it
    try:
        _, k, d, rvecs, tvecs, std_intr, _, _ = cv2.calibrateCameraExtended(
            object_points, image_points, size, k0, np.zeros(5), flags=flags)
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV could not calibrate from {len(used)} images: "
                               f"{str(exc).strip().splitlines()[-1]}") from None

    per_image = []
    sq_sum = 0.0
    dist_sum = 0.0
    n_pts = 0
    for j, i in enumerate(used):
        proj, _ = cv2.projectPoints(obj, rvecs[j], tvecs[j], k, d)
        r = proj.reshape(-1, 2).astype(np.float64) - corners[i].astype(np.float64)
        sq = np.sum(r * r, axis=1)
        per_image.append(float(math.sqrt(sq.mean())))
        sq_sum += float(sq.sum())
        dist_sum += float(np.sqrt(sq).sum())
        n_pts += len(sq)
    k = np.array(k, dtype=np.float64)
    dist5 = np.asarray(d, dtype=np.float64).ravel()[:5]
    std = np.asarray(std_intr, dtype=np.float64).ravel()[:4].copy()
    if fix_aspect_ratio:  # OpenCV reports 0 for fx, which follows fy at a fixed ratio
        std[0] = std[1] * k[0, 0] / k[1, 1]
    return IntrinsicsResult(
        intrinsics=CameraIntrinsics.from_camera_matrix(k, dist5, int(size[0]), int(size[1])),
        rms_error_px=math.sqrt(sq_sum / n_pts),
        mean_error_px=dist_sum / n_pts,
        per_image_error_px=tuple(per_image),
        std_dev_px=tuple(float(x) for x in std[:4]),  # type: ignore[arg-type]
        used_images=tuple(paths[i] for i in used),
        rejected=rejected_list,
        board_inner_corners=(cols, rows),
        square_size_m=float(square_size_m),
        flags=int(flags),
    )


# ---------------------------------------------------------------------------- CLI


class ProgressBar:
    """A progress bar on a text stream, usable as a ``progress(done, total, label)`` callback.

    On a terminal it redraws one line with ``\\r``; otherwise (a log, a pipe) it writes
    plain lines, at most about 20 per run, so logs stay readable.
    """

    def __init__(self, title: str, stream: TextIO | None = None, width: int = 30) -> None:
        self.title = title
        self.stream = stream if stream is not None else sys.stderr
        self.width = int(width)
        isatty = getattr(self.stream, "isatty", None)
        self.tty = bool(isatty()) if callable(isatty) else False
        self._last_plain = -1

    def __call__(self, done: int, total: int, label: str = "") -> None:
        total = max(int(total), 1)
        done = min(max(int(done), 0), total)
        filled = self.width * done // total
        bar = "#" * filled + "." * (self.width - filled)
        name = os.path.basename(label) if label else ""
        line = f"{self.title} [{bar}] {done}/{total}" + (f" {name}" if name else "")
        if self.tty:
            self.stream.write("\r\x1b[K" + line + ("\n" if done == total else ""))
        else:
            step = max(1, total // 20)
            if done == total or done // step != self._last_plain // step:
                self.stream.write(line + "\n")
                self._last_plain = done
        self.stream.flush()


def format_intrinsics_report(result: IntrinsicsResult) -> str:
    """The per-image error table, the rejected list and the calibrated values, as text."""
    names = [os.path.basename(p) for p in result.used_images]
    w = max([len("image")] + [len(n) for n in names])
    worst = max(result.per_image_error_px)
    lines = [f"{'image':<{w}}  reprojection error (RMS, px)", f"{'-' * w}  {'-' * 29}"]
    for n, e in zip(names, result.per_image_error_px):
        mark = "  <- worst" if e == worst and len(names) > 1 else ""
        lines.append(f"{n:<{w}}  {e:8.4f}{mark}")
    lines.append("")
    if result.rejected:
        lines.append(f"rejected {len(result.rejected)} image(s):")
        rw = max(len(os.path.basename(r.path)) for r in result.rejected)
        for r in result.rejected:
            lines.append(f"  {os.path.basename(r.path):<{rw}}  {r.reason.value}: {r.detail}")
    else:
        lines.append("rejected: none")
    lines.append("")
    ci = result.intrinsics
    d = ci.distortion
    fixed = " (aspect ratio fixed)" if result.flags & cv2.CALIB_FIX_ASPECT_RATIO else ""
    lines += [
        f"images used     {len(result.used_images)} of {len(result.used_images) + len(result.rejected)}, "
        f"{ci.width_px}x{ci.height_px} px, board {result.board_inner_corners[0]}x"
        f"{result.board_inner_corners[1]}, square {result.square_size_m * 1000:g} mm",
        f"fx, fy          {ci.fx_px:.4f}, {ci.fy_px:.4f} px{fixed}  "
        f"(+- {result.std_dev_px[0]:.2f}, {result.std_dev_px[1]:.2f})",
        f"cx, cy          {ci.cx_px:.4f}, {ci.cy_px:.4f} px  (+- {result.std_dev_px[2]:.2f}, {result.std_dev_px[3]:.2f})",
        f"k1 k2 p1 p2 k3  {d[0]:.5f} {d[1]:.5f} {d[2]:.5f} {d[3]:.5f} {d[4]:.5f}",
        f"RMS error       {result.rms_error_px:.4f} px (mean {result.mean_error_px:.4f} px per corner)",
    ]
    return "\n".join(lines)


def add_intrinsics_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``robotd calibrate intrinsics``."""
    parser.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="chessboard photos")
    parser.add_argument("--board", type=parse_board, default=(9, 6), metavar="COLSxROWS",
                        help="inner corners of the chessboard (default: 9x6)")
    parser.add_argument("--square", type=float, default=0.025, metavar="METRES",
                        help="side of one board square, metres (default: 0.025)")
    parser.add_argument("--fix-aspect-ratio", action="store_true",
                        help="hold fx = fy (OpenCV's CALIB_FIX_ASPECT_RATIO)")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE",
                        help="calibration file to write; an existing file keeps its other parts")


def run_intrinsics(args: argparse.Namespace) -> int:
    """``robotd calibrate intrinsics``: calibrate, print the report, write/merge the file."""
    bar = ProgressBar("corners", sys.stderr)
    result = calibrate_intrinsics(args.images, board_inner_corners=tuple(args.board),
                                  square_size_m=float(args.square), fix_aspect_ratio=bool(args.fix_aspect_ratio),
                                  progress=bar)
    print(format_intrinsics_report(result))
    merged = update_calibration(args.out, result.calibration_file())
    print(f"wrote {args.out}")
    if merged.mount is not None:
        print("note: the file's floor mount was kept; it was measured with the previous intrinsics, "
              "re-run 'robotd calibrate floor-mount' if the camera or lens changed")
    return 0
