"""ROS 2 topics as robotd's sources: a base (``[base] driver = "ros2"``) and cameras
(``source = "ros2"``), behind the same :class:`~drivers.base.Driver` as the others.

On a ROS 2 robot the base driver (``kobuki_node``, ``turtlebot3_node``, a
``diff_drive_controller``) owns the serial port and publishes ``nav_msgs/Odometry`` and
``sensor_msgs/Imu``; the cameras publish ``sensor_msgs/Image`` or ``CompressedImage``.
These drivers subscribe to them over DDS (:mod:`drivers.ros2.dds`, no ROS install) and
hand the daemon what its own drivers would:

- :class:`Ros2Base`: each ``nav_msgs/Odometry`` becomes :class:`~robotd.base.messages.WheelTicks`
  (the filter's wheel input). The planar motion between consecutive messages (distance
  along the mean heading, heading change) is turned into left and right wheel travel with
  ``[robot]``'s wheel base, and into encoder ticks with its wheel radius and ticks per turn,
  accumulated and wrapped at 16 bits as a Kobuki's counters are. Each ``sensor_msgs/Imu``
  becomes a :class:`~robotd.base.messages.YawRate` (``angular_velocity.z``, source
  ``"ros2"``). The variances the messages state go with them to the filter, which uses
  them instead of its own noise model (``[odometry]``): the odometry's twist covariance
  (``twist.covariance[0]``, forward speed, and ``[35]``, yaw rate) on the
  ``WheelTicks``, the IMU's ``angular_velocity_covariance[8]`` (yaw rate) on the
  ``YawRate``. A covariance counts as stated when its diagonal entry is finite and
  positive and the matrix is not flagged unknown: ROS marks "no estimate" with ``-1`` in
  element 0 and "unknown" with all zeros, and a zero variance would claim an exact
  measurement. Otherwise that message falls back to the noise model: counted per stream
  (``odometry_cov_fallbacks``, ``imu_cov_fallbacks``; ``*_cov_used`` for the others) and
  logged once per stream. ``stats()`` also shows the latest stated values.
- :class:`Ros2Camera`: each image becomes a grey :class:`~robotd.base.messages.Frame`
  (``mono8``, ``mono16``, ``bgr8``, ``rgb8``, ``bgra8``/``rgba8``; or any JPEG/PNG
  ``CompressedImage`` when the topic ends in ``/compressed``), read best effort (ROS 2's
  sensor-data QoS), as a camera node publishes.

Stamps come from the message headers (ROS time, the Unix clock), moved onto robotd's time
base by the offset between the two clocks measured when the driver opens. Messages whose
stamp goes back are dropped and counted (``out_of_order``); undecodable ones too
(``undecodable``). The odometry topic (the base) or the image topic (a camera) silent for
``[ros2] input_timeout_s`` after data flowed begins a *gap* (the base class counts and logs
it, and STATUS shows it), which ends with that topic's next message; the gyro flowing on
does not end a gap of the wheels.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import cv2
import numpy as np

from drivers.base import Driver, Message, StatValue
from drivers.ros2 import dds
from robotd.base import ros2msg
from robotd.base.clock import Clock
from robotd.base.errors import DriverError
from robotd.base.geometry import wrap_angle
from robotd.base.messages import Frame, WheelTicks, YawRate

log = logging.getLogger(__name__)

_U16 = 1 << 16


class _Ros2Source(Driver):
    """What both drivers share: the participant, the readers, the clock offset and the
    gap detection. Subclasses set up ``self._topics`` (ROS topic -> (type, QoS, handler))."""

    def __init__(self, name: str, clock: Clock, topics: dict[str, tuple[str, dds.QosSpec, Any]], *,
                 domain_id: int, namespace: str = "", timeout_s: float = 0.5,
                 dds_config: str | None = None) -> None:
        super().__init__(name, clock=clock)
        dds.require_cyclonedds()
        self._topics = topics
        self._domain_id = domain_id
        self._namespace = namespace
        self._timeout_ns = int(timeout_s * 1e9)
        self._dds_config = dds_config
        self._participant: dds.Participant | None = None
        self._readers: list[tuple[dds.RawReader, Any]] = []
        self._waitset: dds.WaitSet | None = None
        self._offset_ns = time.time_ns() - clock.now_ns()
        self._last_data_ns: int | None = None
        self._n: dict[str, int] = {"out_of_order": 0, "undecodable": 0, "before_start": 0}
        self._start()

    def _open_internal(self) -> None:
        try:
            self._participant = dds.Participant(self._domain_id, config=self._dds_config)
            self._readers = [(self._participant.reader(topic, type_name, qos, namespace=self._namespace), handler)
                             for topic, (type_name, qos, handler) in self._topics.items()]
            self._waitset = dds.WaitSet(self._participant, [r for r, _ in self._readers])
        except DriverError:
            self._release_internal()
            raise
        except Exception as exc:  # noqa: BLE001 - cyclonedds raises its own errors
            self._release_internal()
            raise DriverError(f"ROS 2 topics {', '.join(self._topics)}: {exc}") from exc

    def _release_internal(self) -> None:
        if self._participant is not None:
            self._participant.close()
        self._participant, self._readers, self._waitset = None, [], None

    def _close_internal(self) -> None:
        self._release_internal()

    def _local_ns(self, header: dict[str, Any]) -> int | None:
        """The header's stamp on robotd's time base, or None (counted) before it began."""
        t = ros2msg.stamp_ns_of(header) - self._offset_ns
        if t < 0:
            self._n["before_start"] += 1
            return None
        return t

    def _read_internal(self, timeout_s: float) -> list[Message]:
        assert self._waitset is not None
        self._waitset.wait(timeout_s)
        out: list[Message] = []
        for reader, handler in self._readers:
            for data in reader.take():
                try:
                    msg = handler(ros2msg.decode(reader.full_name, data))
                except (ValueError, KeyError, cv2.error) as exc:
                    self._n["undecodable"] += 1
                    log.debug("%s: undecodable message on %s: %s", self, reader.dds_topic, exc)
                    continue
                if msg is not None:
                    out.append(msg)
        now = self._clock.now_ns()
        if any(self._essential(m) for m in out):
            self._last_data_ns = now
        elif self._last_data_ns is not None and now - self._last_data_ns > self._timeout_ns:
            self._device_away(f"no message on {self._main_topic} for "
                              f"{(now - self._last_data_ns) / 1e9:.2f} s")
        out.sort(key=lambda m: m.stamp_ns)
        return out

    @property
    def _main_topic(self) -> str:
        return next(iter(self._topics))

    def _essential(self, msg: Message) -> bool:
        """Whether ``msg`` is of the stream whose silence is a gap (the first topic's)."""
        return True

    def _gap_ends_with(self, got: Message | list[Message]) -> bool:
        return any(self._essential(m) for m in (got if isinstance(got, list) else [got]))

    def _stats_internal(self) -> dict[str, StatValue]:
        out: dict[str, StatValue] = dict(self._n)
        out["dds_invalid_samples"] = sum(r.invalid for r, _ in self._readers)
        out["publishers_matched"] = sum(r.matched() for r, _ in self._readers)
        return out


class Ros2Base(_Ros2Source):
    """The wheel + gyro input from ROS 2 topics (see the module notes).

    ``wheel_radius_m``, ``wheel_base_m``, ``ticks_per_rev``: ``[robot]``'s geometry, which
    the odometry filter turns the ticks back into motion with. ``imu_topic`` may be ``""``.
    """

    def __init__(self, clock: Clock, *, odometry_topic: str, imu_topic: str, wheel_radius_m: float,
                 wheel_base_m: float, ticks_per_rev: float, domain_id: int, namespace: str = "",
                 timeout_s: float = 0.5, dds_config: str | None = None) -> None:
        self._ticks_per_m = ticks_per_rev / (2.0 * math.pi * wheel_radius_m)
        self._half_base_m = 0.5 * wheel_base_m
        self._prev: tuple[int, float, float, float] | None = None  # stamp, x, y, yaw
        self._ticks = [0.0, 0.0]  # accumulated left, right
        self._counts = {"odometry_msgs": 0, "imu_msgs": 0, "odometry_cov_used": 0, "odometry_cov_fallbacks": 0,
                        "imu_cov_used": 0, "imu_cov_fallbacks": 0}
        self._variances: dict[str, float] = {}
        topics: dict[str, tuple[str, dds.QosSpec, Any]] = {
            odometry_topic: ("nav_msgs/msg/Odometry", dds.QOS_DEFAULT, self._on_odometry)}
        if imu_topic:
            topics[imu_topic] = ("sensor_msgs/msg/Imu", dds.QOS_SENSOR, self._on_imu)
        super().__init__("base", clock, topics, domain_id=domain_id, namespace=namespace,
                         timeout_s=timeout_s, dds_config=dds_config)

    def _essential(self, msg: Message) -> bool:
        return isinstance(msg, WheelTicks)  # the gyro alone cannot drive the filter

    def _on_odometry(self, m: dict[str, Any]) -> WheelTicks | None:
        stamp = self._local_ns(m["header"])
        if stamp is None:
            return None
        p = m["pose"]["pose"]
        x, y = float(p["position"]["x"]), float(p["position"]["y"])
        yaw = ros2msg.yaw_of_quaternion(p["orientation"])
        prev = self._prev
        if prev is not None and stamp <= prev[0]:
            self._n["out_of_order"] += 1
            return None
        self._counts["odometry_msgs"] += 1
        cov = ros2msg.covariance3(m["pose"]["covariance"])
        self._variances.update(odometry_var_x_m2=float(cov[0, 0]), odometry_var_yaw_rad2=float(cov[2, 2]))
        twist_cov = m["twist"]["covariance"]
        var_v, var_w = self._stated("odometry", twist_cov, (0, 35))
        if var_v is not None and var_w is not None:
            self._variances.update(odometry_speed_var_m2ps2=var_v, odometry_yaw_rate_var_rad2ps2=var_w)
        self._prev = (stamp, x, y, yaw)
        if prev is not None:
            dyaw = float(wrap_angle(yaw - prev[3]))
            mid = prev[3] + 0.5 * dyaw
            ds = (x - prev[1]) * math.cos(mid) + (y - prev[2]) * math.sin(mid)
            self._ticks[0] += (ds - dyaw * self._half_base_m) * self._ticks_per_m
            self._ticks[1] += (ds + dyaw * self._half_base_m) * self._ticks_per_m
        return WheelTicks(stamp, int(round(self._ticks[0])) % _U16, int(round(self._ticks[1])) % _U16,
                          speed_var_m2ps2=var_v, yaw_rate_var_rad2ps2=var_w)

    def _on_imu(self, m: dict[str, Any]) -> YawRate | None:
        stamp = self._local_ns(m["header"])
        if stamp is None:
            return None
        self._counts["imu_msgs"] += 1
        (var,) = self._stated("imu", m["angular_velocity_covariance"], (8,))
        if var is not None:
            self._variances["imu_yaw_rate_var_rad2ps2"] = var
        return YawRate(stamp, float(m["angular_velocity"]["z"]), "ros2", yaw_rate_var_rad2ps2=var)

    def _stated(self, stream: str, cov: list[float], diagonal: tuple[int, ...]) -> tuple[float | None, ...]:
        """The variances at ``diagonal`` (indices into the row-major ``cov``) when the
        message states them (see the module notes), else Nones, counted and logged once."""
        values = ros2msg.stated_variances(cov, diagonal)
        if values is not None:
            self._counts[f"{stream}_cov_used"] += 1
            return values
        self._counts[f"{stream}_cov_fallbacks"] += 1
        if self._counts[f"{stream}_cov_fallbacks"] == 1:
            log.info("%s: the %s messages state no usable covariance (%s); the filter uses its own "
                     "noise model for them ([odometry])", self, stream, ros2msg.covariance_problem(cov, diagonal))
        return (None,) * len(diagonal)

    def _stats_internal(self) -> dict[str, StatValue]:
        return {**super()._stats_internal(), **self._counts, **self._variances}

    def __str__(self) -> str:
        return f"ROS 2 base ({', '.join(self._topics)})"


_ENCODINGS = {"mono8": None, "8UC1": None, "bgr8": cv2.COLOR_BGR2GRAY, "8UC3": cv2.COLOR_BGR2GRAY,
              "rgb8": cv2.COLOR_RGB2GRAY, "bgra8": cv2.COLOR_BGRA2GRAY, "rgba8": cv2.COLOR_RGBA2GRAY}


def image_to_grey(m: dict[str, Any]) -> np.ndarray:
    """A ``sensor_msgs/Image`` dict as a ``(H, W) uint8`` grey image (``ValueError`` for an
    encoding robotd does not read or data of the wrong size)."""
    h, w, step, enc = int(m["height"]), int(m["width"]), int(m["step"]), m["encoding"]
    data = np.frombuffer(m["data"], np.uint8)
    if enc in ("mono16", "16UC1"):
        if len(data) < h * step or step < 2 * w:
            raise ValueError(f"{enc} image {w}x{h}: {len(data)} bytes")
        img16 = data[:h * step].reshape(h, step)[:, :2 * w].copy().view(">u2" if m["is_bigendian"] else "<u2")
        return (img16 >> 8).astype(np.uint8)
    if enc not in _ENCODINGS:
        raise ValueError(f"image encoding {enc!r} is not read (mono8, mono16, bgr8, rgb8, bgra8, rgba8)")
    channels = {None: 1}.get(_ENCODINGS[enc], 4 if enc in ("bgra8", "rgba8") else 3)
    if len(data) < h * step or step < channels * w:
        raise ValueError(f"{enc} image {w}x{h} (step {step}): {len(data)} bytes")
    img = data[:h * step].reshape(h, step)[:, :channels * w]
    if channels == 1:
        return img.copy()
    return cv2.cvtColor(img.reshape(h, w, channels), _ENCODINGS[enc])


class Ros2Camera(_Ros2Source):
    """One camera from a ROS 2 image topic (see the module notes). ``camera``:
    ``"floor"`` or ``"forward"``; a ``topic`` ending in ``/compressed`` is read as
    ``sensor_msgs/CompressedImage``, any other as ``sensor_msgs/Image``."""

    def __init__(self, clock: Clock, *, camera: str, topic: str, domain_id: int, namespace: str = "",
                 timeout_s: float = 0.5, dds_config: str | None = None) -> None:
        self.camera = camera
        self._seq = 0
        self._last_stamp: int | None = None
        compressed = topic.rstrip("/").endswith("/compressed")
        type_name = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
        handler = self._on_compressed if compressed else self._on_image
        super().__init__(camera, clock, {topic: (type_name, dds.QOS_SENSOR, handler)}, domain_id=domain_id,
                         namespace=namespace, timeout_s=timeout_s, dds_config=dds_config)

    def _frame(self, header: dict[str, Any], image: np.ndarray) -> Frame | None:
        stamp = self._local_ns(header)
        if stamp is None:
            return None
        if self._last_stamp is not None and stamp <= self._last_stamp:
            self._n["out_of_order"] += 1
            return None
        self._last_stamp = stamp
        self._seq += 1
        return Frame(stamp, self.camera, image, self._seq)

    def _on_image(self, m: dict[str, Any]) -> Frame | None:
        return self._frame(m["header"], image_to_grey(m))

    def _on_compressed(self, m: dict[str, Any]) -> Frame | None:
        img = cv2.imdecode(np.frombuffer(m["data"], np.uint8), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"compressed image ({m['format']!r}) does not decode")
        return self._frame(m["header"], img)

    def _stats_internal(self) -> dict[str, StatValue]:
        return {**super()._stats_internal(), "frames": self._seq}

    def __str__(self) -> str:
        return f"ROS 2 {self.camera} camera ({', '.join(self._topics)})"


def open_ros2_base(cfg: Any, clock: Clock) -> Ros2Base:
    """``[base] driver = "ros2"`` (the registry's factory; ``cfg``: the whole config)."""
    r = cfg.ros2
    return Ros2Base(clock, odometry_topic=r.input_odometry_topic, imu_topic=r.input_imu_topic,
                    wheel_radius_m=cfg.robot.wheel_radius_m, wheel_base_m=cfg.robot.wheel_base_m,
                    ticks_per_rev=cfg.robot.ticks_per_rev, domain_id=dds.domain_id_from(r.domain_id),
                    namespace=r.namespace, timeout_s=r.input_timeout_s)


def open_ros2_floor(cfg: Any, clock: Clock) -> Ros2Camera:
    """``[floor_camera] source = "ros2"`` (``cfg``: the whole config)."""
    r = cfg.ros2
    return Ros2Camera(clock, camera="floor", topic=r.floor_camera_topic, domain_id=dds.domain_id_from(r.domain_id),
                      namespace=r.namespace, timeout_s=r.input_timeout_s)


def open_ros2_forward(cfg: Any, clock: Clock) -> Ros2Camera:
    """``[forward_camera] source = "ros2"`` (``cfg``: the whole config)."""
    r = cfg.ros2
    return Ros2Camera(clock, camera="forward", topic=r.forward_camera_topic,
                      domain_id=dds.domain_id_from(r.domain_id), namespace=r.namespace,
                      timeout_s=r.input_timeout_s)
