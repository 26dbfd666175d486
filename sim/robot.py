"""The virtual robot: a Turtlebot 2 that speaks the real protocols.

It plans a route (:mod:`sim.route`), simulates the wheel encoders and gyro with
their errors (:mod:`sim.sensors`), and plays them out in time order:

* Kobuki feedback packets (basic sensor data, inertial, raw gyro) at 50 Hz are written to
  the master side of a pseudo-terminal, so the daemon opens the slave by its path with the
  same serial driver it uses on the robot; commands the daemon sends back are decoded and
  counted (RequestExtra is answered with version and UDID packets, as the firmware does).
* Floor camera frames at 30 Hz are rendered (:mod:`sim.cameras.floor`) at the true pose
  and handed over through :class:`VirtualCamera`, which has the same ``read``/``close``
  shape as the V4L2 camera.
* The injected :class:`~robotd.base.clock.ManualClock` is moved to each event's time before
  the event is emitted, so the daemon's clock is the virtual robot's.

Fast mode (default) emits as fast as the daemon consumes (lossless back-pressure);
real-time mode paces events on the wall clock and drops frames like a real camera when
the consumer falls behind.
"""

from __future__ import annotations

import logging
import os
import queue
import select
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.kobuki import protocol
from robotd.base.camera import FloorCameraModel
from robotd.base.clock import ManualClock
from robotd.base.messages import Frame
from sim.cameras.floor import FloorRenderer, RenderParams
from sim.route import ROUTES, MotionLimits, build_route, plan_motion
from sim.sensors import BaseSensorParams, simulate_base
from sim.world.floor import Floor

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VirtualRobotSettings:
    """What to simulate. Units in the names; ``duration_s=None`` runs the whole route."""

    route: str = "office"
    seed: int = 0
    duration_s: float | None = None
    realtime: bool = False
    floor_files: tuple[str, ...] = ()
    floor_metres_per_px: float = 0.001
    floor_pattern: str | None = None
    camera_fps: float = 30.0
    camera_queue_size: int = 4


def _default_print_photo() -> "np.ndarray":
    """The photo printed on pattern floors by default: scikit-image's gravel."""
    import skimage.data

    return skimage.data.gravel()


class VirtualCamera:
    """Frames rendered by the virtual robot, read like a real camera.

    ``read(timeout_s)`` returns a :class:`~robotd.base.messages.Frame` or ``None``; after the
    last frame, ``exhausted`` is set. Lossless mode makes the robot wait for the reader;
    otherwise a full buffer drops the new frame, as a camera whose reader is late does.
    """

    def __init__(self, capacity: int, lossless: bool) -> None:
        self._q: queue.Queue[Frame] = queue.Queue(maxsize=capacity)
        self.lossless = lossless
        self.dropped = 0
        self.exhausted = threading.Event()
        self.closed = False

    def read(self, timeout_s: float) -> Frame | None:
        try:
            return self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def close(self) -> None:
        self.closed = True

    def push(self, frame: Frame, stop: threading.Event) -> None:
        if not self.lossless:
            try:
                self._q.put_nowait(frame)
            except queue.Full:
                self.dropped += 1
            return
        while not stop.is_set():
            try:
                self._q.put(frame, timeout=0.1)
                return
            except queue.Full:
                continue


class VirtualRobot:
    """The simulated robot; ``start()`` plays it out in a thread, ``close()`` tears down."""

    def __init__(self, settings: VirtualRobotSettings, camera_model: FloorCameraModel,
                 clock: ManualClock, sensor_params: BaseSensorParams | None = None,
                 render_params: RenderParams | None = None) -> None:
        if settings.route not in ROUTES:
            from robotd.base.errors import ConfigError
            raise ConfigError(f"unknown route {settings.route!r} (known: {', '.join(ROUTES)})")
        self.settings = settings
        self.clock = clock
        rng = np.random.default_rng(settings.seed)
        self.motion = plan_motion(build_route(settings.route), MotionLimits())
        if settings.duration_s is not None:
            self.motion = self.motion.truncated(settings.duration_s)
        self.base = simulate_base(self.motion, sensor_params or BaseSensorParams(), rng)
        if settings.floor_pattern is not None:
            from sim.world.floor import load_floor_photo
            from sim.world.pattern import PatternFloor, PatternParams

            photo = (load_floor_photo(settings.floor_files[0]) if settings.floor_files
                     else _default_print_photo())
            params = (PatternParams(kind="tiles", width_m=0.3) if settings.floor_pattern == "tiles"
                      else PatternParams(kind="planks"))
            self.floor = PatternFloor(photo, params, settings.floor_metres_per_px, settings.seed)
        elif settings.floor_files:
            self.floor = Floor.from_photos(list(settings.floor_files),
                                           metres_per_px=settings.floor_metres_per_px,
                                           seed=settings.seed)
        else:
            self.floor = Floor.default(seed=settings.seed, metres_per_px=settings.floor_metres_per_px)
        self.camera_model = camera_model
        self.renderer = FloorRenderer(self.floor, camera_model, render_params or RenderParams(),
                                      np.random.default_rng(settings.seed + 1))
        self.camera = VirtualCamera(settings.camera_queue_size, lossless=not settings.realtime)
        self.frame_times_s = np.arange(0.0, float(self.motion.t_s[-1]), 1.0 / settings.camera_fps)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._parser = protocol.PacketParser()
        self.commands_received: dict[str, int] = {}
        self.packets_emitted = 0
        self.frames_emitted = 0
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="virtual-robot", daemon=True)
        self.error: BaseException | None = None

    # -- public ------------------------------------------------------------------------
    @property
    def duration_s(self) -> float:
        return float(self.motion.t_s[-1])

    @property
    def sim_time_s(self) -> float:
        return self.clock.now_ns() / 1e9

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)

    def close(self) -> None:
        self.stop()
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> "VirtualRobot":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write_ground_truth_tum(self, path: Path, rate_hz: float = 50.0) -> None:
        """Ground-truth poses as a TUM trajectory file (t x y z qx qy qz qw)."""
        from robotd.io.trajectory import write_tum

        t = np.arange(0.0, self.duration_s, 1.0 / rate_hz)
        poses = self.motion.pose_at(t)
        write_tum(path, (t * 1e9).astype(np.int64), poses)

    # -- the event loop ----------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._play()
        except BaseException as exc:  # reported to the caller, never silently lost
            self.error = exc
            log.exception("virtual robot failed")
        finally:
            self.camera.exhausted.set()
            self.finished.set()

    def _play(self) -> None:
        packet_t = self.base.t_s
        frame_t = self.frame_times_s
        i = j = 0
        wall0 = time.monotonic()
        while not self._stop.is_set() and (i < len(packet_t) or j < len(frame_t)):
            is_packet = j >= len(frame_t) or (i < len(packet_t) and packet_t[i] <= frame_t[j])
            t = float(packet_t[i] if is_packet else frame_t[j])
            if self.settings.realtime:
                delay = wall0 + t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
            self.clock.set_ns(max(self.clock.now_ns(), int(round(t * 1e9))))
            if is_packet:
                self._write(self._packet_bytes(i))
                self.packets_emitted += 1
                i += 1
                self._poll_commands()
            else:
                pose = self.motion.pose_at(t)
                v, w = self.motion.velocity_at(t)
                image = self.renderer.render(pose, v, w, t)
                self.camera.push(Frame(int(round(t * 1e9)), "floor", image, j), self._stop)
                self.frames_emitted += 1
                j += 1

    def _packet_bytes(self, i: int) -> bytes:
        b = self.base
        basic = protocol.BasicSensorData(
            timestamp_ms=int(b.device_ms[i]), bumper=0, wheel_drop=0, cliff=0,
            left_encoder=int(b.left_ticks[i]), right_encoder=int(b.right_ticks[i]),
            left_pwm=0, right_pwm=0, buttons=0, charger=0, battery_decivolts=165, overcurrent=0,
        )
        inertial = protocol.InertialData(angle_centideg=int(b.angle_cdeg[i]),
                                       angle_rate_centidegps=int(b.angle_rate_cdegps[i]))
        gyro = protocol.RawGyroData(
            frame_id=i & 0xFF,
            samples=tuple(tuple(int(a) for a in xyz) for xyz in b.gyro_digits[i, : b.gyro_count[i]]),
        )
        return protocol.encode_feedback(basic, inertial, gyro)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view and not self._stop.is_set():
            try:
                n = os.write(self._master, view)
                view = view[n:]
            except BlockingIOError:
                select.select([], [self._master], [], 0.1)

    def _poll_commands(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return
        for payload in self._parser.feed(data):
            for cmd in protocol.decode_commands(payload):
                name = type(cmd).__name__
                self.commands_received[name] = self.commands_received.get(name, 0) + 1
                if isinstance(cmd, protocol.RequestExtra):
                    self._write(self._extra_reply(cmd))

    @staticmethod
    def _extra_reply(cmd: "protocol.RequestExtra") -> bytes:
        parts = []
        if cmd.hardware_version:
            parts.append(protocol.HardwareVersion(major=1, minor=0, patch=4))
        if cmd.firmware_version:
            parts.append(protocol.FirmwareVersion(major=1, minor=2, patch=0))
        if cmd.udid:
            parts.append(protocol.UniqueDeviceId(udid0=0x524F424F, udid1=0x54440000, udid2=0x00000001))
        return protocol.encode_feedback(*parts) if parts else b""
