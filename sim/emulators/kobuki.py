"""The Kobuki base emulator: SI sensor streams in, the base's serial bytes out.

:func:`encode` turns :class:`~sim.sensors.BaseSensorStreams` into what a Kobuki reports
in its 50 Hz feedback packets (sub-payloads 1, 4 and 13 of
:mod:`drivers.kobuki.protocol`), doing what the base itself does:

- Encoders: ``ticks = angle / 2 pi * ticks_per_rev`` counted in whole ticks (2578.33
  per turn, 85 um of rim each) in a 16-bit counter that wraps, starting at a random value
  with the wheel at a random phase within a tick.
- Clock: ``timestamp_ms`` is the device clock in whole milliseconds on a 16-bit counter
  that starts at a random boot value and wraps.
- Raw gyro (sub-payload 13): each sample in digits of 0.00875 deg/s, in the gyro's own
  axes (the chip is mounted turned 90 deg about z: gyro x = robot y, gyro y = -robot x,
  gyro z = robot z); a packet carries the samples taken since the previous packet (2 or
  3 at 108 Hz).
- Inertial (sub-payload 4), the firmware's: it subtracts the bias it measured at power-on
  (the true turn-on bias plus an error of ``firmware_bias_cal_sigma_degps``, 0.02 deg/s;
  it does not follow the random walk) from the raw yaw digits, integrates them at the
  gyro's nominal rate into a heading in 0.01 deg that starts at a random value and wraps
  at +-180 deg (an s16 of 0.01 deg cannot hold a full turn), and reports the mean
  compensated rate of the packet's samples in 0.01 deg/s (held when a packet has none).

The power-on state (:class:`KobukiState`) is drawn by :meth:`KobukiState.draw`;
:func:`simulate_kobuki` draws it between the sensors' errors and their streams, so a seed
gives the same bytes as the single model this was split from.

:class:`KobukiEmulator` plays the packets onto the master side of a pseudo-terminal, so a
driver opens the slave by its path as it would the real serial port; it decodes the
commands sent back, counts them, and answers RequestExtra with version and UDID packets
as the firmware does. :func:`driver_messages` reads the packets through the real
:class:`~drivers.kobuki.driver.KobukiDriver`, for tests and benchmarks that want the
daemon's messages without running the daemon.
"""

from __future__ import annotations

import dataclasses

import math
import os
import select
import threading
import tty
from dataclasses import dataclass

import numpy as np

from drivers.base import Message
from drivers.kobuki import protocol
from robotd.base.clock import ManualClock
from robotd.base.messages import WheelTicks, YawRate
from sim.route import Motion
from sim.sensors import (BaseErrors, BaseSensorParams, BaseSensorStreams, draw_errors,
                         simulate_sensors)

__all__ = ["KobukiEmulator", "KobukiFeedback", "KobukiParams", "KobukiState", "driver_messages",
           "encode", "simulate_kobuki"]

#: Inertial sub-payload units.
ANGLE_UNIT_DEG = 0.01
RATE_UNIT_DEGPS = 0.01
_U16 = 1 << 16
_READS_PER_PACKET = 100


@dataclass(frozen=True, slots=True)
class KobukiParams:
    """What the emulated base reports besides its sensors.

    ``firmware_bias_cal_sigma_degps``: error (1 sigma) of the gyro bias the firmware
    measures at power-on, deg/s. ``battery_decivolts``: the battery voltage reported,
    0.1 V. ``hardware_version`` / ``firmware_version``: ``(major, minor, patch)``
    answered to RequestExtra; ``udid``: the three 32-bit words of the unique device id.
    """

    firmware_bias_cal_sigma_degps: float = 0.02
    battery_decivolts: int = 165
    hardware_version: tuple[int, int, int] = (1, 0, 4)
    firmware_version: tuple[int, int, int] = (1, 2, 0)
    udid: tuple[int, int, int] = (0x524F424F, 0x54440000, 0x00000001)

    @classmethod
    def ideal(cls) -> KobukiParams:
        """A firmware that knows the gyro's turn-on bias exactly."""
        return cls(firmware_bias_cal_sigma_degps=0.0)


@dataclass(frozen=True, slots=True)
class KobukiState:
    """The base's state at power-on: the bias its firmware measured (deg/s), the encoder
    counters and the wheels' phase within a tick, the millisecond counter, the firmware
    heading (deg)."""

    firmware_bias_degps: float
    left_ticks0: int
    right_ticks0: int
    tick_phase: tuple[float, float]
    device_ms0: int
    angle0_deg: float

    @classmethod
    def draw(cls, errors: BaseErrors, params: KobukiParams, rng: np.random.Generator) -> KobukiState:
        """Draw the power-on state (eight numbers from ``rng``, always in this order)."""
        fw_bias = (math.degrees(errors.gyro_bias0_radps)
                   + params.firmware_bias_cal_sigma_degps * rng.standard_normal())
        ticks0 = rng.integers(0, _U16, 2)
        tick_phase = rng.random(2)
        device_ms0 = int(rng.integers(0, _U16))
        angle0 = rng.uniform(-180.0, 180.0)
        return cls(float(fw_bias), int(ticks0[0]), int(ticks0[1]),
                   (float(tick_phase[0]), float(tick_phase[1])), device_ms0, float(angle0))


@dataclass(frozen=True, eq=False)
class KobukiFeedback:
    """The feedback packets of one run, as arrays in protocol units (``N`` packets).

    ``t_s`` ``(N,) float64`` simulation time, s; ``stamp_ns`` ``(N,) int64`` the same in
    ns; ``device_ms`` ``(N,) uint16``; ``left_ticks``/``right_ticks`` ``(N,) uint16``;
    ``angle_cdeg`` ``(N,) int16`` firmware heading, 0.01 deg, in [-18000, 18000);
    ``angle_rate_cdegps`` ``(N,) int16`` firmware yaw rate, 0.01 deg/s; ``gyro_count``
    ``(N,) int64`` raw gyro samples in each packet; ``gyro_digits`` ``(N, K, 3) int16``
    raw x, y, z digits in the gyro's axes, zero past ``gyro_count``; ``gyro_t_s`` ``(N, K)
    float64`` the samples' true times (NaN padding); ``true_pose`` ``(N, 3) float64``.
    ``sensors`` are the SI streams it encodes, ``state`` the power-on state.
    """

    t_s: np.ndarray
    stamp_ns: np.ndarray
    device_ms: np.ndarray
    left_ticks: np.ndarray
    right_ticks: np.ndarray
    angle_cdeg: np.ndarray
    angle_rate_cdegps: np.ndarray
    gyro_count: np.ndarray
    gyro_digits: np.ndarray
    gyro_t_s: np.ndarray
    true_pose: np.ndarray
    sensors: BaseSensorStreams
    state: KobukiState
    params: KobukiParams
    wheel_drop: np.ndarray | None = None
    """``(N,) uint8`` the wheel-drop bits of each packet (0x01 right, 0x02 left: both while
    the robot is carried); None: the wheels never leave the floor."""

    @property
    def raw_gyro_z(self) -> list[np.ndarray]:
        """Per packet, the raw yaw-axis digits it carries, ``int16``."""
        return [row[:n] for row, n in zip(self.gyro_digits[:, :, 2], self.gyro_count)]

    def packet(self, i: int) -> bytes:
        """Packet ``i`` framed as the base sends it."""
        basic = protocol.BasicSensorData(
            timestamp_ms=int(self.device_ms[i]), bumper=0,
            wheel_drop=0 if self.wheel_drop is None else int(self.wheel_drop[i]), cliff=0,
            left_encoder=int(self.left_ticks[i]), right_encoder=int(self.right_ticks[i]),
            left_pwm=0, right_pwm=0, buttons=0, charger=0,
            battery_decivolts=self.params.battery_decivolts, overcurrent=0,
        )
        inertial = protocol.InertialData(angle_centideg=int(self.angle_cdeg[i]),
                                         angle_rate_centidegps=int(self.angle_rate_cdegps[i]))
        gyro = protocol.RawGyroData(
            frame_id=i & 0xFF,
            samples=tuple((int(x), int(y), int(z))
                          for x, y, z in self.gyro_digits[i, : self.gyro_count[i]]),
        )
        return protocol.encode_feedback(basic, inertial, gyro)

    def messages(self, yaw_source: str = "raw_gyro") -> list[Message]:
        """What the daemon gets from these packets; see :func:`driver_messages`."""
        return driver_messages(self, yaw_source)


def _gyro_frame(rates_robot: np.ndarray) -> np.ndarray:
    """``(M, 3)`` rates about the robot's x, y, z -> about the gyro chip's axes (turned
    90 deg counter-clockwise about z: robot x = -gyro y, robot y = gyro x)."""
    x, y, z = rates_robot[:, 0], rates_robot[:, 1], rates_robot[:, 2]
    return np.column_stack([y, -x, z])


def _per_packet(t_pk: np.ndarray, t_g: np.ndarray, digits: np.ndarray, comp_degps: np.ndarray,
                angle_deg: np.ndarray, angle0_deg: float) -> dict[str, np.ndarray]:
    """Group gyro samples into packets: samples in ``(t_pk[j-1], t_pk[j]]`` belong to
    packet ``j`` (those after the last packet are not sent). Returns the padded sample
    arrays and the firmware's heading (after the packet's last sample, ``angle0_deg``
    before any) and mean compensated rate (held when a packet has no sample)."""
    n_pk = len(t_pk)
    owner = np.searchsorted(t_pk, t_g, side="left")
    keep = owner < n_pk
    owner, t_g, digits = owner[keep], t_g[keep], digits[keep]
    comp_degps, angle_deg = comp_degps[keep], angle_deg[keep]
    count = np.bincount(owner, minlength=n_pk)
    k_max = max(1, int(count.max()))
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    slot = np.arange(len(owner)) - first[owner]
    g_digits = np.zeros((n_pk, k_max, 3), dtype=np.int16)
    g_digits[owner, slot] = digits
    g_t = np.full((n_pk, k_max), np.nan)
    g_t[owner, slot] = t_g
    last = first + count - 1
    filled = np.maximum.accumulate(np.where(count > 0, np.arange(n_pk), -1))
    valid = filled >= 0
    angle_pk = np.full(n_pk, angle0_deg)
    angle_pk[valid] = angle_deg[last[filled[valid]]]
    rate_sum = np.bincount(owner, weights=comp_degps, minlength=n_pk)
    rate_pk = np.zeros(n_pk)
    rate_pk[valid] = (rate_sum / np.maximum(count, 1))[filled[valid]]
    return {"count": count, "digits": g_digits, "t": g_t, "angle_deg": angle_pk,
            "rate_degps": rate_pk}


def encode(sensors: BaseSensorStreams, state: KobukiState,
           params: KobukiParams | None = None) -> KobukiFeedback:
    """The packets a Kobuki in ``state`` sends for ``sensors``; see the module doc."""
    params = params or KobukiParams()
    tpr = sensors.params.drive.ticks_per_rev
    ticks = sensors.wheel_angle_rad / (2.0 * math.pi) * tpr
    counters = (np.floor(ticks + np.asarray(state.tick_phase)).astype(np.int64)
                + np.array([state.left_ticks0, state.right_ticks0])) % _U16
    device_ms = (state.device_ms0
                 + np.round(sensors.device_clock_s * 1000.0).astype(np.int64)) % _U16
    digit = protocol.GYRO_DPS_PER_DIGIT
    rates_degps = np.rad2deg(_gyro_frame(sensors.gyro_radps))
    digits = np.clip(np.round(rates_degps / digit), -32768, 32767).astype(np.int16)
    comp = digits[:, 2].astype(float) * digit - state.firmware_bias_degps
    angle_fw = state.angle0_deg + np.cumsum(comp) / sensors.params.gyro_rate_hz
    g = _per_packet(sensors.t_s, sensors.gyro_t_s, digits, comp, angle_fw, state.angle0_deg)
    angle_wrapped = (g["angle_deg"] + 180.0) % 360.0 - 180.0
    angle_cdeg = np.round(angle_wrapped / ANGLE_UNIT_DEG).astype(np.int64)
    angle_cdeg = np.where(angle_cdeg >= 18000, angle_cdeg - 36000, angle_cdeg).astype(np.int16)
    rate_cdeg = np.clip(np.round(g["rate_degps"] / RATE_UNIT_DEGPS), -32768, 32767).astype(np.int16)
    return KobukiFeedback(
        t_s=sensors.t_s, stamp_ns=sensors.stamp_ns, device_ms=device_ms.astype(np.uint16),
        left_ticks=counters[:, 0].astype(np.uint16), right_ticks=counters[:, 1].astype(np.uint16),
        angle_cdeg=angle_cdeg, angle_rate_cdegps=rate_cdeg, gyro_count=g["count"].astype(np.int64),
        gyro_digits=g["digits"], gyro_t_s=g["t"], true_pose=sensors.true_pose,
        sensors=sensors, state=state, params=params,
    )


def simulate_kobuki(motion: Motion, sensor_params: BaseSensorParams, rng: np.random.Generator,
                    params: KobukiParams | None = None, rate_hz: float = 50.0,
                    errors: BaseErrors | None = None, draws_of: Motion | None = None) -> KobukiFeedback:
    """A Kobuki's packets at ``rate_hz`` along ``motion``: draws the sensors' errors, the
    base's power-on state, then the sensor streams (in that order, see the module doc).
    ``errors``: the base's own errors instead of the drawn ones (the same robot on another
    drive: the draws are still made, so the rest of the run is the seed's as ever).
    ``draws_of``: a kidnapped drive's motion without the kidnapping, whose gyro draws it
    shares (:func:`sim.sensors.simulate_sensors`)."""
    params = params or KobukiParams()
    drawn = draw_errors(sensor_params, rng)
    if errors is None:
        errors = drawn
    else:  # the turn-on bias is the drive's own; the rest is the base's
        errors = dataclasses.replace(errors, gyro_bias0_radps=drawn.gyro_bias0_radps)
    state = KobukiState.draw(errors, params, rng)
    sensors = simulate_sensors(motion, sensor_params, errors, rng, rate_hz, draws_of=draws_of)
    feedback = encode(sensors, state, params)
    if motion.lifted is not None:  # carried: both wheels hang free
        drop = np.where(np.asarray(motion.lifted_at(feedback.t_s)), 0x03, 0x00).astype(np.uint8)
        feedback = dataclasses.replace(feedback, wheel_drop=drop)
    return feedback


def driver_messages(feedback: KobukiFeedback,
                    yaw_source: str = "raw_gyro") -> list[Message]:
    """The messages :class:`~drivers.kobuki.driver.KobukiDriver` makes of ``feedback``.

    A :class:`KobukiEmulator` plays the packets one at a time and the real driver reads
    each one's bytes with a :class:`~robotd.base.clock.ManualClock` at the packet's time,
    so every stamp is its packet's time (a batch read could stamp by a packet the pty has
    not passed on yet). A packet holding the header bytes inside waits in the driver's
    parser for the next one, as on the robot; should that be the last packet, its
    messages are not returned. ``yaw_source`` is the driver's (``"raw_gyro"``, ``"inertial"``), or
    ``"raw_gyro_samples"``: the driver's wheel messages with one yaw rate per raw gyro
    sample at the sample's true time instead of the driver's per-packet mean.
    """
    from drivers.kobuki.driver import KobukiDriver

    if yaw_source not in ("raw_gyro", "inertial", "raw_gyro_samples"):
        raise ValueError("yaw_source must be 'raw_gyro', 'raw_gyro_samples' or 'inertial', "
                         f"got {yaw_source!r}")
    clock = ManualClock()
    out: list[Message] = []
    driver_source = "inertial" if yaw_source == "inertial" else "raw_gyro"
    with KobukiEmulator(feedback) as emulator, KobukiDriver(
            emulator.port, clock, yaw_source=driver_source) as driver:
        for i, stamp_ns in enumerate(feedback.stamp_ns):
            clock.set_ns(int(stamp_ns))
            emulator.emit(i)
            for _ in range(_READS_PER_PACKET):  # a read may see part of the packet
                if int(driver.stats()["bytes_in"]) >= emulator.bytes_written:
                    break
                out += driver.read(1.0)
            else:
                raise RuntimeError(f"the driver did not read packet {i}")
    if yaw_source != "raw_gyro_samples":
        return out
    return _with_sample_rates([m for m in out if isinstance(m, WheelTicks)], feedback)


def _with_sample_rates(wheels: list[WheelTicks],
                       feedback: KobukiFeedback) -> list[Message]:
    """``wheels`` merged with one yaw rate per raw gyro sample at its true time (wheels
    first on equal stamps, as the driver emits a packet's messages)."""
    mask = np.arange(feedback.gyro_digits.shape[1])[None, :] < feedback.gyro_count[:, None]
    stamps = np.round(feedback.gyro_t_s[mask] * 1e9).astype(np.int64)
    rates = np.deg2rad(feedback.gyro_digits[:, :, 2][mask].astype(float)
                       * protocol.GYRO_DPS_PER_DIGIT)
    keyed: list[tuple[int, int, int, WheelTicks | YawRate]] = [
        (m.stamp_ns, 0, i, m) for i, m in enumerate(wheels)]
    keyed += [(int(s), 1, i, YawRate(int(s), float(w), "raw_gyro"))
              for i, (s, w) in enumerate(zip(stamps, rates))]
    keyed.sort(key=lambda k: (k[0], k[1], k[2]))
    return [k[3] for k in keyed]


class KobukiEmulator:
    """The base on a pseudo-terminal: ``emit(i)`` writes packet ``i`` of ``feedback`` and
    handles the commands that came back. ``port`` is the path a driver opens.

    Writing waits while the pty is full (the reader is late), until ``stop`` is set.
    """

    def __init__(self, feedback: KobukiFeedback, stop: threading.Event | None = None) -> None:
        self.feedback = feedback
        self._stop = stop if stop is not None else threading.Event()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._parser = protocol.PacketParser()
        self.commands_received: dict[str, int] = {}
        self.packets_emitted = 0
        self.bytes_written = 0

    @property
    def event_times_s(self) -> np.ndarray:
        """``(N,) float64`` the packets' simulation times, s."""
        return self.feedback.t_s

    @property
    def stamp_ns(self) -> np.ndarray:
        """``(N,) int64`` the packets' simulation times, ns (ground-truth stamps)."""
        return self.feedback.stamp_ns

    @property
    def true_pose(self) -> np.ndarray:
        """``(N, 3) float64`` the true ``(x_m, y_m, yaw_rad)`` at each packet."""
        return self.feedback.true_pose

    def emit(self, i: int) -> None:
        """Write packet ``i``, then read and answer the commands waiting."""
        self._write(self.feedback.packet(i))
        self.packets_emitted += 1
        self.poll_commands()

    def close(self) -> None:
        """Close both ends of the pty; safe to call more than once."""
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._master = self._slave = -1

    def __enter__(self) -> KobukiEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view and not self._stop.is_set():
            try:
                n = os.write(self._master, view)
                view = view[n:]
                self.bytes_written += n
            except BlockingIOError:
                select.select([], [self._master], [], 0.1)

    def poll_commands(self, timeout_s: float = 0.0) -> int:
        """Read the command bytes waiting (waiting up to ``timeout_s`` for some), count the
        commands they complete and answer RequestExtra; returns the bytes read."""
        if timeout_s > 0.0:
            select.select([self._master], [], [], timeout_s)
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return 0
        for payload in self._parser.feed(data):
            for cmd in protocol.decode_commands(payload):
                name = type(cmd).__name__
                self.commands_received[name] = self.commands_received.get(name, 0) + 1
                if isinstance(cmd, protocol.RequestExtra):
                    self._write(self.extra_reply(cmd))
        return len(data)

    def extra_reply(self, cmd: protocol.RequestExtra) -> bytes:
        """The firmware's answer to ``cmd``: the asked-for version and UDID sub-payloads in
        one packet (no bytes when nothing known was asked)."""
        p = self.feedback.params
        parts: list[protocol.FeedbackSubPayload] = []
        if cmd.hardware_version:
            parts.append(protocol.HardwareVersion(*p.hardware_version))
        if cmd.firmware_version:
            parts.append(protocol.FirmwareVersion(*p.firmware_version))
        if cmd.udid:
            parts.append(protocol.UniqueDeviceId(*p.udid))
        return protocol.encode_feedback(*parts) if parts else b""
