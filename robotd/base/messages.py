"""Typed, timestamped samples that flow from the drivers down the pipeline.

Every message is a frozen dataclass with ``stamp_ns`` (host monotonic time base, or the
virtual robot's time) and SI units in its field names. Drivers produce these and import
nothing else from robotd except :mod:`robotd.base.errors` and :mod:`robotd.base.clock`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from enum import StrEnum
from typing import Any, Literal, TypeVar

import numpy as np


@dataclass(frozen=True, slots=True)
class WheelTicks:
    """Raw wheel encoder counters as the base reports them.

    ``left_ticks``/``right_ticks`` are the raw 16-bit counters (0..65535, wrapping);
    the odometry unwraps them. ``device_ms`` is the base's own 16-bit millisecond
    timestamp, kept for diagnostics.

    ``speed_var_m2ps2`` / ``yaw_rate_var_rad2ps2``: the variances of the forward speed
    and yaw rate these ticks measure, when the source states them (a ROS 2
    ``nav_msgs/Odometry``'s twist covariance); None (the filter's own noise model) from a
    base that does not.
    """

    stamp_ns: int
    left_ticks: int
    right_ticks: int
    device_ms: int = 0
    speed_var_m2ps2: float | None = None
    yaw_rate_var_rad2ps2: float | None = None


@dataclass(frozen=True, slots=True)
class YawRate:
    """Angular rate about the robot's z axis (REP-103: counter-clockwise positive), rad/s.

    ``yaw_rate_var_rad2ps2``: the reading's variance when the source states it (a ROS 2
    ``sensor_msgs/Imu``'s angular velocity covariance); None: the filter's noise model.
    """

    stamp_ns: int
    yaw_rate_radps: float
    source: str = "gyro"
    yaw_rate_var_rad2ps2: float | None = None


@dataclass(frozen=True, slots=True)
class BaseStatus:
    """The base driver's word on its own health, sent when it changes: ``degraded`` while
    a wheel (or the whole bus) has been silent too long, so the wheel odometry is not
    being updated; ``detail`` says which (``"left wheel stale"``, ``"bus silent"``)."""

    stamp_ns: int
    degraded: bool
    detail: str = ""


@dataclass(frozen=True, slots=True)
class WheelDrop:
    """The base's wheel-drop switches changed: ``lifted`` while either wheel hangs free
    (the robot is picked up, as the Kobuki reports in its basic sensor data), False again
    when both wheels are back on the floor. ``left``/``right``: each wheel's switch."""

    stamp_ns: int
    lifted: bool
    left: bool = False
    right: bool = False


@dataclass(frozen=True, slots=True, eq=False)
class Frame:
    """One camera image.

    ``image`` is ``(H, W) uint8`` (grey) or ``(H, W, 3) uint8`` (BGR); ``camera`` names
    the source (``"floor"`` or ``"forward"``); ``seq`` counts frames from the source.
    """

    stamp_ns: int
    camera: str
    image: np.ndarray
    seq: int = 0


@dataclass(frozen=True, slots=True, eq=False)
class PoseStamped:
    """A planar pose estimate with its 3x3 covariance over (x_m, y_m, yaw_rad)."""

    stamp_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


# --------------------------------------------------------------------------------------
# What the pipeline's stages hand each other (robotd.app.pipeline routes them by type).
# --------------------------------------------------------------------------------------

_K = TypeVar("_K", bound="Keyframe")


@dataclass(frozen=True, slots=True, eq=False)
class OdometryUpdate:
    """The filter's fused pose and the wheel-only pose after an accepted wheel reading."""

    fused: PoseStamped
    wheel: PoseStamped


@dataclass(frozen=True, slots=True, eq=False)
class Keyframe:
    """A floor frame chosen as a keyframe, with the wheel + gyro pose at its stamp (the
    keyframe stage's output).

    Each later stage publishes a new message with what it adds, never changing this one
    (:mod:`robotd.app.pipeline`): :class:`DescribedKeyframe` (the floor descriptor),
    :class:`MeasuredKeyframe` (the visual odometry step), :class:`StoredKeyframe` (the map's
    id). Each extends the previous one's fields, so a later stage reads all of them.
    """

    frame: Frame
    pose: PoseStamped
    odometry_edge: tuple[np.ndarray, np.ndarray] | None = None
    """``(delta (3,), covariance (3, 3))`` from the previous keyframe: the wheel + gyro
    filter's increment, or in a :class:`MeasuredKeyframe` what visual odometry made of it;
    None at the first keyframe or when the filter had none. The map writer links the
    keyframes with it."""
    odometry_bias: tuple[Any, ...] | None = None
    """What ``odometry_edge`` shares with the gyro bias (the fields of
    :class:`robotd.odometry.history.EdgeBiasTerms`), when the pose graph keeps the bias
    (``[pose_graph] odometry_model``); None otherwise or when the edge has none."""
    carried: bool = False
    """The robot was lifted (a wheel drop) since the previous keyframe: no odometry edge may
    join the two (the wheels did not see the motion)."""

    @property
    def stamp_ns(self) -> int:
        return self.frame.stamp_ns

    @property
    def pose_xyyaw(self) -> np.ndarray:
        """``(3,)`` x_m, y_m, yaw_rad."""
        return np.array([self.pose.x_m, self.pose.y_m, self.pose.yaw_rad])


@dataclass(frozen=True, slots=True, eq=False, kw_only=True)
class DescribedKeyframe(Keyframe):
    """A :class:`Keyframe` with its floor descriptor ``(mode, bytes)`` (the floor detector
    stage's output), which the map stores in the keyframe's row."""

    descriptor: tuple[int, bytes] | None = None
    keypoints_px: np.ndarray | None = None
    """``(N, 2) float32`` the descriptor's keypoints where the detector found them (sub-pixel,
    in the coded order; :func:`robotd.floor.descriptor.extract_with_positions`), for floor
    visual odometry; the map stores the descriptor alone."""


@dataclass(frozen=True, slots=True, eq=False, kw_only=True)
class MeasuredKeyframe(DescribedKeyframe):
    """A keyframe with its odometry edge as floor visual odometry left it (the visual
    odometry stage's output): ``odometry_edge`` is the wheel + gyro edge combined with the
    visual step (fused mode) or the step alone (vision only)."""

    visual_pose: np.ndarray | None = None
    """``(3,)`` floor visual odometry alone, dead-reckoned from the run's first keyframe
    (which it starts at, in the odometry frame): each step chained, a failed one replaced by
    the wheel + gyro edge. For comparison (the demo's "VO only" column); nothing else uses
    it."""


@dataclass(frozen=True, slots=True, eq=False, kw_only=True)
class StoredKeyframe(MeasuredKeyframe):
    """A keyframe the map writer stored: ``keyframe_id`` and ``run_id`` are the map's."""

    keyframe_id: int
    run_id: int


def keyframe_as(cls: type[_K], kf: Keyframe, **added: object) -> _K:
    """``kf``'s fields (whichever keyframe message it is) in a new message of type ``cls``
    with ``added``: how a stage publishes its output without changing its input."""
    values = {f.name: getattr(kf, f.name) for f in fields(kf)}
    values.update(added)
    return cls(**values)


@dataclass(frozen=True, slots=True, eq=False)
class TransientKeyframe:
    """A keyframe over mapped ground while the robot is localised (``[pose_graph]
    localise_mapped``), which the map writer did not store: it is queried against the map
    and never stored."""

    keyframe: Keyframe


@dataclass(frozen=True, slots=True, eq=False)
class VisualOdometryStep:
    """Floor visual odometry's motion between the keyframes at ``prev_stamp_ns`` and
    ``stamp_ns`` (paper 003 Sec. IV-D), for the odometry filter to fuse: ``delta_xyyaw``
    ``(3,)`` the later pose in the earlier one's frame and its ``covariance`` ``(3, 3)``,
    both None when the step failed (the filter then only moves its clone)."""

    stamp_ns: int
    prev_stamp_ns: int | None
    delta_xyyaw: np.ndarray | None
    covariance: np.ndarray | None


@dataclass(frozen=True, slots=True)
class MapMatch:
    """A transient keyframe matched stored keyframe ``from_id`` at or above the trained
    threshold: the transient's pose in ``from_id``'s frame (``delta_xyyaw``) and its
    ``information`` (3, 3). The pose graph gates it to re-localise the robot."""

    from_id: int
    score: float
    delta_xyyaw: np.ndarray
    information: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class KeyframeStored:
    """A keyframe is in the map."""

    keyframe: StoredKeyframe


LinkKind = Literal["odometry", "loop"]
"""What a pose-graph edge is: chained odometry, or a loop (floor or forward camera)."""


@dataclass(frozen=True, slots=True, eq=False)
class Link:
    """A pose-graph edge to store: the pose of ``to_id`` in the frame of ``from_id``.

    ``kind``: ``"odometry"`` or ``"loop"``; ``delta_xyyaw`` ``(3,)`` metres and radians;
    ``information`` ``(3, 3)``, the inverse covariance of ``delta_xyyaw``; ``source``: what
    measured a loop (``"floor"`` or ``"forward"``).
    """

    kind: LinkKind
    from_id: int
    to_id: int
    delta_xyyaw: np.ndarray
    information: np.ndarray
    source: str = "floor"
    bias: tuple[Any, ...] | None = None
    """An odometry link's bias terms (:attr:`Keyframe.odometry_bias`), None without."""


@dataclass(frozen=True, slots=True, eq=False)
class LoopCandidate:
    """A candidate at or above the trained threshold, with the relative pose measured from
    its inlier floor points: keyframe ``to_id`` seen from ``from_id`` (``delta_xyyaw`` in
    ``from_id``'s frame, ``information`` (3, 3)). The pose graph decides whether it becomes
    a loop :class:`Link`."""

    from_id: int
    to_id: int
    score: float
    delta_xyyaw: np.ndarray
    information: np.ndarray


@dataclass(frozen=True, slots=True)
class ForwardLoop:
    """A loop the forward camera verified (paper 000): keyframe ``to_id`` sees the place of
    the older keyframe ``from_id``. Monocular geometry gives no distance: ``dyaw_rad`` is the
    camera's heading change and ``bearing_rad`` the direction of the new camera centre, both
    in the old camera's planar frame (:func:`robotd.forward.planar.planar_motion`); the pose
    graph takes the range from its own prediction, unless ``range_m`` (the distance between
    the camera centres, measured on the floor from the camera's known height,
    :func:`robotd.forward.verify.floor_range`) is given. ``probability``: the filter's
    posterior of the loop; ``inliers``: matches fitting the essential matrix;
    ``sigma_bearing_rad``: how well the inliers fix the bearing (1-sigma,
    :func:`robotd.forward.planar.refine_motion`), None when not known; ``sigma_yaw_rad``:
    how far the heading change is from fixed beyond the edge's own heading sigma (1-sigma,
    added in quadrature), None when the images fix it: the half-width of a heading-bearing
    ridge that no prior heading settled (:mod:`robotd.app.stages.forward_loops`)."""

    from_id: int
    to_id: int
    probability: float
    dyaw_rad: float
    bearing_rad: float
    inliers: int
    range_m: float | None = None
    sigma_bearing_rad: float | None = None
    sigma_yaw_rad: float | None = None


class LoopFate(StrEnum):
    """What became of a loop candidate. A :class:`~enum.StrEnum`: each member is its own
    value, the text stored in the map's ``loop_candidates.fate`` (whose CHECK lists them: a
    new member needs a schema migration, :mod:`robotd.io.mapfile`) and compared equal to it."""

    ACCEPTED = "accepted"
    """Became a loop edge of the pose graph."""
    BELOW_THRESHOLD = "below_threshold"
    """Its score was under the calibrated threshold."""
    FAILED_GATE = "failed_gate"
    """Refused by the graph's chi-square gate (or from an earlier run, outside its graph)."""
    NO_TRANSFORM = "no_transform"
    """No relative pose could be estimated between the two keyframes."""
    DOWN_WEIGHTED = "down_weighted"
    """Accepted, then down-weighted by the robust optimiser."""
    GROUPED = "grouped"
    """Entered the graph through its relocalising group's one edge (the group's fitted pose,
    :func:`robotd.graph.reloc.group_constraint`), not as a loop edge of its own; the gate
    never judged it. Since map schema 6; the migration to it relabels such rows of an older
    map, which said ``failed_gate``."""


@dataclass(frozen=True, slots=True)
class CandidateFate:
    """What became of one loop candidate (as DLoopDetector reports its detections):
    ``fate`` is a :class:`LoopFate`; ``detail`` says why in numbers (the chi-square, the
    weight)."""

    query_id: int
    candidate_id: int
    score: float
    fate: LoopFate
    detail: str = ""
