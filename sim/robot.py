"""The virtual robot: a Turtlebot 2 that speaks the real protocols.

It plans a route (:mod:`sim.route`) over a floor (:mod:`sim.world`), and composes parts
that each own a list of event times and an ``emit(i)``:

* emulators (:mod:`sim.emulators`): the Kobuki base, whose SI sensor streams
  (:mod:`sim.sensors`) are encoded into feedback packets at 50 Hz and written to the
  master side of a pseudo-terminal, so the daemon opens the slave by its path with the
  same serial driver it uses on the robot; it answers the daemon's commands. With
  ``base="can"`` the same streams go out instead as CAN frames on a python-can virtual
  bus (:mod:`sim.emulators.can`), which the daemon's CAN driver opens by channel name;
* cameras (:mod:`sim.cameras`): the downward floor camera, rendered at the true pose at
  30 Hz and read like a real camera; optionally (``forward_camera=True``) the forward
  camera in the route's textured world (:mod:`sim.world.rooms`), at ``forward_fps``.

One thread plays every part's events in time order (emulators before cameras on equal
times); the injected :class:`~robotd.base.clock.ManualClock` is moved to each event's time
before the event is emitted, so the daemon's clock is the virtual robot's.

Fast mode (default) emits as fast as the daemon consumes (lossless back-pressure);
real-time mode paces events on the wall clock and drops frames like a real camera when
the consumer falls behind.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from robotd.base.camera import FloorCameraModel
from robotd.base.clock import ManualClock
from sim.cameras.device import VirtualCamera
from sim.cameras.floor import FloorRenderer, RenderParams, floor_camera
from sim.emulators.kobuki import KobukiEmulator, KobukiParams, simulate_kobuki
from sim.route import ROUTES, Motion, MotionLimits, build_route, kidnapped, plan_motion
from sim.sensors import BaseSensorParams
from sim.world.floor import Floor, FloorSource

if TYPE_CHECKING:  # python-can and cantools are loaded only for a CAN base
    from sim.emulators.can import CanEmulator, CanFaults

__all__ = ["Part", "VirtualCamera", "VirtualRobot", "VirtualRobotSettings"]

log = logging.getLogger(__name__)


class Part(Protocol):
    """An emulator or a camera of the virtual robot."""

    @property
    def event_times_s(self) -> np.ndarray:
        """``(K,) float64`` increasing simulation times of the part's events, s."""
        ...

    def emit(self, i: int) -> None:
        """Emit event ``i`` (the clock is already at its time)."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class VirtualRobotSettings:
    """What to simulate. Units in the names; ``duration_s=None`` runs the whole route."""

    route: str = "office"
    seed: int = 0
    base_seed: int | None = None
    """The seed whose base errors (wheel radii, wheel base, gyro scale) this robot has;
    None: ``seed``'s. The same robot on another drive, as a calibration drive needs."""
    duration_s: float | None = None
    realtime: bool = False
    floor_files: tuple[str, ...] = ()
    floor_metres_per_px: float = 0.001
    floor_pattern: str | None = None
    camera_fps: float = 30.0
    camera_queue_size: int = 4
    forward_camera: bool = False
    forward_fps: float = 10.0
    base: str = "kobuki"
    """``"kobuki"`` (serial bytes on a pty) or ``"can"`` (frames on a python-can virtual bus)."""
    can_convention: str = "diff_drive"
    can_faults: CanFaults | None = None
    kidnap: tuple[float, float, float] | None = None
    """``(at_s, to_s, carry_s)``: at ``at_s`` of the route the robot is lifted (wheel drop,
    cameras covered), carried for ``carry_s`` and put down where the route is at ``to_s``
    (:func:`sim.route.kidnapped`); it drives on from there. Kobuki base only."""


def _default_print_photo() -> "np.ndarray":
    """The photo printed on pattern floors by default: scikit-image's gravel."""
    import skimage.data

    return skimage.data.gravel()


class VirtualRobot:
    """The simulated robot; ``start()`` plays it out in a thread, ``close()`` tears down.

    ``emulators`` and ``cameras`` are its parts (today the Kobuki base, :attr:`base`, and
    the floor camera, :attr:`camera`; with ``settings.forward_camera`` also the forward
    camera, :attr:`forward`, else ``None``). ``sensor_params`` is the base's sensor error
    model, ``base_params`` what its firmware reports, ``render_params`` the floor
    camera's exposure and noise. The base's random draws come from ``settings.seed``, the
    floor camera's noise from ``settings.seed + 1``, the forward camera's from
    ``settings.seed + 2``. In fast (lossless) mode every camera must be read, or the robot
    waits for its reader: enable the forward camera only when something reads it.
    """

    def __init__(self, settings: VirtualRobotSettings, camera_model: FloorCameraModel,
                 clock: ManualClock, sensor_params: BaseSensorParams | None = None,
                 render_params: RenderParams | None = None,
                 base_params: KobukiParams | None = None) -> None:
        if settings.base not in ("kobuki", "can"):
            from robotd.base.errors import ConfigError
            raise ConfigError(f"unknown virtual base {settings.base!r} (known: kobuki, can)")
        if settings.route not in ROUTES:
            from robotd.base.errors import ConfigError
            raise ConfigError(f"unknown route {settings.route!r} (known: {', '.join(ROUTES)})")
        if settings.kidnap is not None and settings.base != "kobuki":
            from robotd.base.errors import ConfigError
            raise ConfigError("a kidnapping needs the Kobuki base (the wheel-drop bits of its sensor data)")
        self.settings = settings
        self.clock = clock
        rng = np.random.default_rng(settings.seed)
        self.motion = plan_motion(build_route(settings.route), MotionLimits())
        plain = self.motion  # a kidnapped drive's gyro draws are this drive's (simulate_sensors)
        if settings.kidnap is not None:
            from robotd.base.errors import ConfigError

            at_s, to_s, carry_s = settings.kidnap
            try:
                self.motion = kidnapped(self.motion, at_s, to_s, carry_s)
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
        if settings.duration_s is not None:
            self.motion = self.motion.truncated(settings.duration_s)
            plain = plain.truncated(settings.duration_s)
        sp = sensor_params or BaseSensorParams()
        own = None
        if settings.base_seed is not None and settings.base_seed != settings.seed:
            from sim.sensors import draw_errors

            own = draw_errors(sp, np.random.default_rng(settings.base_seed))
        feedback = simulate_kobuki(self.motion, sp, rng, base_params, errors=own,
                                   draws_of=plain if settings.kidnap is not None else None)
        self.floor = _make_floor(settings)
        self.camera_model = camera_model
        self.renderer = FloorRenderer(self.floor, camera_model, render_params or RenderParams(),
                                      np.random.default_rng(settings.seed + 1))
        self._stop = threading.Event()
        self.base: KobukiEmulator | CanEmulator
        if settings.base == "can":
            from sim.emulators.can import CanEmulator, encode_can

            # The same sensor streams (same seed, same drawn errors) as the Kobuki's, sent
            # as CAN frames instead: only the protocol and the driver differ.
            self.base = CanEmulator(
                encode_can(feedback.sensors, settings.can_convention,
                           np.random.default_rng(settings.seed + 3), settings.can_faults),
                feedback.sensors)
        else:
            self.base = KobukiEmulator(feedback, stop=self._stop)
        self.camera = floor_camera(self.renderer, self.motion, settings.camera_fps,
                                   capacity=settings.camera_queue_size,
                                   lossless=not settings.realtime, stop=self._stop)
        self.emulators: list[KobukiEmulator | CanEmulator] = [self.base]
        self.cameras: list[VirtualCamera] = [self.camera]
        self.forward: VirtualCamera | None = None
        if settings.forward_camera:
            self.forward = _make_forward_camera(settings, self.motion, self._stop)
            self.cameras.append(self.forward)
        self.port = self.base.port
        self.finished = threading.Event()
        self._thread = threading.Thread(target=self._run, name="virtual-robot", daemon=True)
        self.error: BaseException | None = None

    # -- public ------------------------------------------------------------------------
    @property
    def duration_s(self) -> float:
        return float(self.motion.t_s[-1])

    @property
    def sim_time_s(self) -> float:
        return self.clock.now_ns() / 1e9

    @property
    def packets_emitted(self) -> int:
        """Feedback packets written by all emulators."""
        return sum(e.packets_emitted for e in self.emulators)

    @property
    def frames_emitted(self) -> int:
        """Frames handed over (or dropped) by all cameras."""
        return sum(c.frames_emitted for c in self.cameras)

    @property
    def commands_received(self) -> dict[str, int]:
        """Commands the base received, by type name."""
        return self.base.commands_received

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)

    def close(self) -> None:
        self.stop()
        for part in (*self.emulators, *self.cameras):
            part.close()

    def __enter__(self) -> "VirtualRobot":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def ground_truth(self, rate_hz: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
        """The true trajectory every ``1 / rate_hz`` s over the run: ``stamp_ns`` ``(N,)
        int64`` and poses ``(N, 3) float64`` ``(x_m, y_m, yaw_rad)``."""
        t_s = np.arange(0.0, self.duration_s, 1.0 / rate_hz)
        return (t_s * 1e9).astype(np.int64), self.motion.pose_at(t_s)

    # -- the event loop ----------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._play()
        except BaseException as exc:  # reported to the caller, never silently lost
            self.error = exc
            log.exception("virtual robot failed")
        finally:
            for camera in self.cameras:
                camera.exhausted.set()
            self.finished.set()

    def _play(self) -> None:
        parts: list[Part] = [*self.emulators, *self.cameras]
        events = heapq.merge(*(_events(k, p.event_times_s) for k, p in enumerate(parts)))
        wall0 = time.monotonic()
        for t_s, k, i in events:
            if self._stop.is_set():
                return
            if self.settings.realtime:
                delay = wall0 + t_s - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
            self.clock.set_ns(max(self.clock.now_ns(), int(round(t_s * 1e9))))
            parts[k].emit(i)


def _events(k: int, times_s: np.ndarray) -> Iterator[tuple[float, int, int]]:
    """Part ``k``'s events as ``(t_s, k, i)``: merged, equal times go in part order."""
    for i, t_s in enumerate(times_s):
        yield float(t_s), k, i


def _make_forward_camera(settings: VirtualRobotSettings, motion: Motion,
                         stop: threading.Event) -> VirtualCamera:
    """The forward camera in the route's world (:func:`sim.world.rooms.world_for_route`)."""
    from sim.cameras.forward import ForwardCameraModel, ForwardRenderer, ForwardRenderParams, forward_camera
    from sim.world.rooms import world_for_route

    world = world_for_route(settings.route, settings.seed)
    renderer = ForwardRenderer(world, ForwardCameraModel(), ForwardRenderParams(),
                               np.random.default_rng(settings.seed + 2))
    return forward_camera(renderer, motion, settings.forward_fps, capacity=settings.camera_queue_size,
                          lossless=not settings.realtime, stop=stop)


def _make_floor(settings: VirtualRobotSettings) -> FloorSource:
    """The floor the settings ask for: a pattern printed with a photo, photos, or the
    default (scikit-image's textures)."""
    if settings.floor_pattern is not None:
        from sim.world.floor import load_floor_photo
        from sim.world.pattern import PatternFloor, PatternParams

        photo = (load_floor_photo(settings.floor_files[0]) if settings.floor_files
                 else _default_print_photo())
        params = (PatternParams(kind="tiles", width_m=0.3) if settings.floor_pattern == "tiles"
                  else PatternParams(kind="planks"))
        return PatternFloor(photo, params, settings.floor_metres_per_px, settings.seed)
    if settings.floor_files:
        return Floor.from_photos(list(settings.floor_files),
                                 metres_per_px=settings.floor_metres_per_px, seed=settings.seed)
    return Floor.default(seed=settings.seed, metres_per_px=settings.floor_metres_per_px)
