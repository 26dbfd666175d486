"""Reading recordings: a damage-tolerant MCAP reader that gives robotd messages back.
"""

from __future__ import annotations

import heapq
import io
import logging
import os
import struct
import threading
import zlib
from collections.abc import Callable, Collection, Container, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, Header, Message, Metadata, Schema
from mcap import stream_reader as _mcap_stream
from mcap.stream_reader import breakup_chunk

from drivers.recording.schemas import (
    _CAMERA_TOPIC,
    _MCAP_MAGIC,
    _RECORD_HEAD,
)
from robotd.base import ros2msg
from robotd.base.errors import DriverError, RobotdError
from robotd.base.messages import Frame, PoseStamped, WheelTicks, YawRate

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


@dataclass
class RecordingDamage:
    """What could not be read from a recording (all zero/False for a sound file)."""

    no_summary: bool = False
    """The file has no valid summary (recording interrupted, or file cut); it was scanned."""
    unread_tail_bytes: int = 0
    """Bytes at the end that do not form a complete record (a cut inside a record)."""
    damaged_chunks: int = 0
    """Chunks skipped: incomplete, failing their CRC, or not decompressible."""
    undecodable_messages: int = 0
    """Messages skipped because their CDR data or their image did not decode."""

    @property
    def any(self) -> bool:
        """True when anything was lost or had to be recovered."""
        return bool(self.no_summary or self.unread_tail_bytes or self.damaged_chunks
                    or self.undecodable_messages)

    def as_dict(self) -> dict[str, int | bool]:
        return {"no_summary": self.no_summary, "unread_tail_bytes": self.unread_tail_bytes,
                "damaged_chunks": self.damaged_chunks,
                "undecodable_messages": self.undecodable_messages}


@dataclass(frozen=True)
class _ChunkRef:
    """Where a chunk (or a message written outside any chunk) starts, and its time span."""

    offset: int
    start_ns: int
    end_ns: int


RobotdMessage = WheelTicks | YawRate | Frame | PoseStamped


_stamp_ns = ros2msg.stamp_ns_of
_yaw_from_quaternion = ros2msg.yaw_of_quaternion


def _normalise_type(name: str) -> str:
    """``sensor_msgs/Imu`` and ``sensor_msgs/msg/Imu`` name the same type."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[-1]}" if len(parts) in (2, 3) else name


class RecordingReader:
    """Reads a recording back as robotd messages; a context manager.

    Opening reads the header and the summary (or, when there is none, scans the file):
    :attr:`metadata`, :attr:`topics` and :attr:`damage` are known from then on, and
    :attr:`damage` grows while :meth:`messages` runs into damaged chunks or messages.
    Raises :class:`~robotd.base.errors.DriverError` naming the path when the file cannot be
    opened or is not an MCAP file (see the module doc for the damage policy).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.damage = RecordingDamage()
        self.skipped: dict[str, int] = {}
        """Messages of topics or types robotd does not read, per topic (not damage)."""
        self.unwanted: dict[str, int] = {}
        """Messages of robotd's types left undecoded (``messages(only=...)``), per topic."""
        self.metadata: dict[str, dict[str, str]] = {}
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunks: list[_ChunkRef] = []
        self._summary_failed = False
        self._lock = threading.Lock()
        try:
            self._f = open(self.path, "rb")
        except OSError as exc:
            raise DriverError(f"{self.path}: cannot open the recording: {exc.strerror}") from exc
        try:
            self._size = os.fstat(self._f.fileno()).st_size
            self._read_header()
            if not self._read_summary():
                self._scan()
        except RobotdError:
            self._f.close()
            raise
        except OSError as exc:
            self._f.close()
            raise DriverError(f"{self.path}: cannot read the recording: {exc.strerror}") from exc
        if self.damage.any:
            log.warning("%s: damaged recording, reading what is intact (%s)", self.path,
                        ", ".join(f"{k} {v}" for k, v in self.damage.as_dict().items() if v))

    # -- opening -----------------------------------------------------------------------

    def _read_header(self) -> None:
        self._f.seek(0)
        magic = self._f.read(len(_MCAP_MAGIC))
        if magic != _MCAP_MAGIC:
            what = "is empty" if not magic else ("is cut before its header" if _MCAP_MAGIC.startswith(magic)
                                                 else "is not an MCAP file")
            raise DriverError(f"{self.path}: not a readable recording: the file {what}")
        head = self._f.read(_RECORD_HEAD.size)
        if len(head) == _RECORD_HEAD.size:
            opcode, length = _RECORD_HEAD.unpack(head)
            body = self._f.read(length) if length <= self._size else b""
            if opcode == Opcode.HEADER and len(body) == length:
                try:
                    Header.read(ReadDataStream(io.BytesIO(body)))
                    return
                except Exception:  # noqa: BLE001 - a malformed header is reported below
                    pass
        raise DriverError(f"{self.path}: not a readable recording: the file is cut or damaged "
                          "inside its header")

    def _read_summary(self) -> bool:
        """Use the file's summary; False when it has none that can be trusted."""
        self._f.seek(0)
        try:
            reader = SeekingReader(self._f)
            summary = reader.get_summary()
            if summary is None:
                return False
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except Exception:  # noqa: BLE001 - mcap raises many kinds on a cut file; we scan instead
            log.debug("%s: no usable summary", self.path, exc_info=True)
            self._summary_failed = True
            return False
        self._schemas = dict(summary.schemas)
        self._channels = dict(summary.channels)
        stats = summary.statistics
        if not summary.chunk_indexes and (stats is None or stats.message_count > 0):
            return False  # messages outside chunks (an unchunked file): only a scan finds them
        self._chunks = [_ChunkRef(ci.chunk_start_offset, ci.message_start_time, ci.message_end_time)
                        for ci in summary.chunk_indexes]
        self.metadata = metadata
        return True

    def _scan(self) -> None:
        """Walk the records from the start, keeping every complete, sound chunk (and any
        message written outside a chunk)."""
        self._f.seek(-len(_MCAP_MAGIC), os.SEEK_END)
        self.damage.no_summary = self._f.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC or self._summary_failed
        pos = len(_MCAP_MAGIC)
        self._f.seek(pos)
        while True:
            head = self._f.read(_RECORD_HEAD.size)
            if len(head) < _RECORD_HEAD.size:
                self.damage.unread_tail_bytes = self._size - pos
                return
            opcode, length = _RECORD_HEAD.unpack(head)
            end = pos + _RECORD_HEAD.size + length
            if end > self._size or opcode == 0:
                self.damage.unread_tail_bytes = self._size - pos
                return
            if opcode in (Opcode.DATA_END, Opcode.FOOTER):
                return  # the data section is complete; only the summary was bad
            if opcode in (Opcode.CHUNK, Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA):
                body = self._f.read(length)
                self._scan_record(opcode, body, pos)
            else:
                self._f.seek(end)
            pos = end

    def _scan_record(self, opcode: int, body: bytes, offset: int) -> None:
        stream = ReadDataStream(io.BytesIO(body))
        try:
            if opcode == Opcode.CHUNK:
                chunk = Chunk.read(stream)
                records = breakup_chunk(chunk, validate_crc=True)
                for rec in records:
                    self._remember(rec)
                if any(isinstance(r, Message) for r in records):
                    self._chunks.append(_ChunkRef(offset, chunk.message_start_time, chunk.message_end_time))
            elif opcode == Opcode.MESSAGE:
                m = Message.read(stream, len(body))
                self._chunks.append(_ChunkRef(offset, m.log_time, m.log_time))
            elif opcode == Opcode.SCHEMA:
                self._remember(Schema.read(stream))
            elif opcode == Opcode.CHANNEL:
                self._remember(Channel.read(stream))
            elif opcode == Opcode.METADATA:
                m = Metadata.read(stream)
                self.metadata[m.name] = dict(m.metadata)
        except Exception:  # noqa: BLE001 - damaged bytes: mcap, zstd or struct errors
            log.debug("%s: damaged record at offset %d", self.path, offset, exc_info=True)
            if opcode in (Opcode.CHUNK, Opcode.MESSAGE):
                self.damage.damaged_chunks += 1

    def _remember(self, rec: Any) -> None:
        if isinstance(rec, Schema):
            self._schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            self._channels[rec.id] = rec

    # -- what is inside ----------------------------------------------------------------

    @property
    def schemas(self) -> dict[int, Schema]:
        """The file's MCAP schema records by id."""
        return dict(self._schemas)

    @property
    def channels(self) -> dict[int, Channel]:
        """The file's MCAP channel records by id."""
        return dict(self._channels)

    @property
    def topics(self) -> dict[str, str]:
        """Topic -> schema name of every channel in the recording."""
        out = {}
        for ch in self._channels.values():
            schema = self._schemas.get(ch.schema_id)
            out[ch.topic] = schema.name if schema is not None else ""
        return out

    @property
    def time_range_ns(self) -> tuple[int, int] | None:
        """``(first, last)`` log time of the intact messages (from the chunks' time
        ranges), or None when there are none; e.g. ``ManualClock(reader.time_range_ns[0])``
        starts a replay's clock at the recording's start."""
        if not self._chunks:
            return None
        return min(c.start_ns for c in self._chunks), max(c.end_ns for c in self._chunks)

    @property
    def yaw_source(self) -> str:
        """``YawRate.source`` of the recorded yaw rates (``"gyro"`` when not recorded)."""
        return self.metadata.get("robotd.imu", {}).get("yaw_source", "gyro")

    # -- messages ----------------------------------------------------------------------

    def _load_chunk(self, ref: _ChunkRef, keep: Container[int], others: dict[int, int]) -> list[Message]:
        """The message records at ``ref`` of the channels ``keep``, in file order; those of
        other channels counted per channel id in ``others``. A damaged chunk is counted
        and gives none."""
        try:
            with self._lock:
                self._f.seek(ref.offset)
                head = self._f.read(_RECORD_HEAD.size)
                opcode, length = _RECORD_HEAD.unpack(head) if len(head) == _RECORD_HEAD.size else (0, 0)
                end = ref.offset + _RECORD_HEAD.size + length
                ok = opcode in (Opcode.CHUNK, Opcode.MESSAGE) and end <= self._size
                body = self._f.read(length) if ok else b""
        except OSError as exc:
            raise DriverError(f"{self.path}: cannot read the recording: {exc.strerror}") from exc
        try:
            if not body:
                raise ValueError("no complete chunk at this offset")
            stream = ReadDataStream(io.BytesIO(body))
            if opcode == Opcode.MESSAGE:
                records = [Message.read(stream, len(body))]
                if records[0].channel_id not in keep:
                    others[records[0].channel_id] = others.get(records[0].channel_id, 0) + 1
                    return []
                return records
            return _chunk_messages(Chunk.read(stream), keep, others)
        except Exception as exc:  # noqa: BLE001 - damaged bytes: mcap, zstd or struct errors
            self.damage.damaged_chunks += 1
            log.warning("%s: skipping the damaged chunk at offset %d (%s)", self.path, ref.offset, exc)
            return []

    def raw_messages(self) -> Iterator[tuple[Channel, Message]]:
        """Every intact MCAP message in log-time order (ties: file order)."""
        channels = self._channels
        for msg in self._merged(None, lambda _others: None):
            yield channels[msg.channel_id], msg

    def _merged(self, keep: Collection[int] | None,
                on_others: Callable[[dict[int, int]], None]) -> Iterator[Message]:
        """The message records of the channels ``keep`` (None: every channel the file
        defines) in log-time order (ties: file order). The records of other channels are
        only counted as their chunk is read, and ``on_others`` gets those counts per channel
        id after each chunk (no record object, no place in the merge: a replay wants fewer
        than half of a virtual robot's messages); a record of a channel the file does not
        define counts as undecodable (:attr:`damage`), as it always did."""
        refs = sorted(self._chunks, key=lambda r: (r.start_ns, r.offset))
        heap: list[tuple[int, int, int, Message]] = []
        channels = self._channels
        kept = channels if keep is None else keep
        for ref in refs:
            # Later chunks start no earlier than this one, so anything before its start
            # is final.
            while heap and heap[0][:3] < (ref.start_ns, ref.offset, 0):
                yield heapq.heappop(heap)[3]
            others: dict[int, int] = {}
            for i, rec in enumerate(self._load_chunk(ref, kept, others)):
                heapq.heappush(heap, (rec.log_time, ref.offset, i, rec))
            if others:
                for cid in [c for c in others if c not in channels]:
                    self.damage.undecodable_messages += others.pop(cid)
                on_others(others)
        while heap:
            yield heapq.heappop(heap)[3]

    def messages(self, only: Collection[type] | None = None, *,
                 lazy_images: bool = False) -> Iterator[tuple[str, RobotdMessage]]:
        """``(topic, message)`` in log-time order, as robotd types.

        :class:`WheelTicks`, :class:`YawRate`, :class:`Frame` (image decoded) and
        :class:`PoseStamped` (every ``nav_msgs/msg/Odometry`` topic). Other types are
        skipped and counted in :attr:`skipped`; damage is counted in :attr:`damage`.
        ``only``: the robotd types wanted; messages of the others are not decoded (a
        replay has no use for ``/odom`` and ``/ground_truth``, about half the messages of
        a virtual robot's recording) and are counted per topic in :attr:`unwanted`.
        ``lazy_images``: a JPEG frame's pixels are decoded when first read
        (:class:`EncodedFrame`); a replay hands out 30 frames a second, of which a few
        become keyframes, and decoding was most of its reading time. Each is checked here
        by a decode at 1/8 scale, which runs the whole entropy decoding (where damage
        shows), so a frame that does not decode is still counted and skipped here.
        """
        yaw_source = self.yaw_source
        wanted = None if only is None else {k for k, t in _PRODUCES.items() if t in only}
        # What becomes of each channel's messages, settled once per channel (not per
        # message): counted in ``skipped`` or ``unwanted`` by topic (never decoded), or
        # decoded (the decoder compiled at the channel's first message) and converted.
        counted: dict[int, tuple[dict[str, int], str]] = {}
        kinds: dict[int, str] = {}
        for cid, channel in self._channels.items():
            schema = self._schemas.get(channel.schema_id)
            kind = _normalise_type(schema.name) if schema is not None else ""
            if schema is None or kind not in _CONVERTERS or channel.message_encoding != "cdr":
                counted[cid] = (self.skipped, channel.topic)
            elif wanted is not None and kind not in wanted:
                counted[cid] = (self.unwanted, channel.topic)
            else:
                kinds[cid] = kind

        def count(others: dict[int, int]) -> None:
            for cid, n in others.items():
                into, topic = counted[cid]
                into[topic] = into.get(topic, 0) + n

        decoders: dict[int, tuple[Callable[[bytes], Any], Callable[..., RobotdMessage]] | None] = {}
        for msg in self._merged(kinds, count):
            cid = msg.channel_id
            channel = self._channels[cid]
            if cid not in decoders:
                kind = kinds[cid]
                try:
                    # Decoded with the file's own definitions (a file from another
                    # version of robotd, or from ros2 bag), by robotd's one CDR codec.
                    decoders[cid] = (ros2msg.Codec(kind, ros2msg.parse_schema_text(
                        kind, self._schemas[channel.schema_id].data.decode())).decode,
                        _to_frame_lazy if lazy_images and kind == _IMAGE else _CONVERTERS[kind])
                except Exception:  # noqa: BLE001 - a broken schema text in the file
                    log.warning("%s: cannot parse the schema of %s", self.path, channel.topic)
                    decoders[cid] = None
            plan = decoders[cid]
            try:
                if plan is None:
                    raise ValueError("no decoder")
                out = plan[1](channel.topic, plan[0](msg.data), msg, yaw_source)
            except Exception as exc:  # noqa: BLE001 - CDR or image bytes that do not decode
                self.damage.undecodable_messages += 1
                log.debug("%s: undecodable %s message at %d: %s", self.path, channel.topic,
                          msg.log_time, exc)
                continue
            yield channel.topic, out

    def close(self) -> None:
        """Close the file; safe to call twice."""
        self._f.close()

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log and publish time


def _chunk_messages(chunk: Chunk, keep: Container[int], others: dict[int, int]) -> list[Message]:
    """The message records of a chunk (its CRC checked) on the channels ``keep``, as
    ``mcap``'s ``breakup_chunk`` gives them, other records skipped: the records are cut from
    the decompressed bytes with one ``struct`` call each instead of a read call per field
    (reading the 60 s drive spent a third of its time there). Messages of other channels
    are counted per channel id in ``others``, with no record made."""
    if chunk.compression == "zstd":
        zstandard = getattr(_mcap_stream, "zstandard", None)  # mcap's optional import
        if zstandard is None:
            raise ValueError("zstd chunk, and the zstandard module is missing")
        data: bytes = zstandard.decompress(chunk.data, chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        lz4 = getattr(_mcap_stream, "lz4", None)
        if lz4 is None:
            raise ValueError("lz4 chunk, and the lz4 module is missing")
        data = lz4.decompress(chunk.data)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"unknown chunk compression {chunk.compression!r}")
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC does not match its records")
    out: list[Message] = []
    skipped: dict[int, int] = {}  # into ``others`` once the whole chunk was read
    pos, end, head, message = 0, len(data), _MESSAGE_HEAD, int(Opcode.MESSAGE)
    while pos < end:
        if end - pos < 9:
            raise ValueError("chunk records end inside a record header")
        opcode, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], "little")
        stop = pos + 9 + length
        if stop > end:
            raise ValueError("chunk record runs past the chunk")
        if opcode == message:
            if length < 22:
                raise ValueError("message record too short")
            _op, _len, channel_id, sequence, log_time, publish_time = head.unpack_from(data, pos)
            if channel_id not in keep:
                skipped[channel_id] = skipped.get(channel_id, 0) + 1
                pos = stop
                continue
            out.append(Message(channel_id=channel_id, sequence=sequence, log_time=log_time,
                               publish_time=publish_time, data=data[pos + 31:stop]))
        pos = stop
    for channel_id, n in skipped.items():
        others[channel_id] = others.get(channel_id, 0) + n
    return out


def _to_wheel_ticks(topic: str, m: Any, rec: Message, yaw_source: str) -> WheelTicks:
    return WheelTicks(_stamp_ns(m["header"]), int(m["left_ticks"]), int(m["right_ticks"]), int(m["device_ms"]))


def _to_yaw_rate(topic: str, m: Any, rec: Message, yaw_source: str) -> YawRate:
    stated = ros2msg.stated_variances(m["angular_velocity_covariance"], (8,))
    return YawRate(_stamp_ns(m["header"]), float(m["angular_velocity"]["z"]), yaw_source,
                   None if stated is None else stated[0])


def _to_frame(topic: str, m: Any, rec: Message, yaw_source: str) -> Frame:
    image = cv2.imdecode(np.frombuffer(m["data"], np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"image data ({m['format']!r}) does not decode")
    match = _CAMERA_TOPIC.match(topic)
    camera = match.group(1) if match else topic.strip("/")
    return Frame(_stamp_ns(m["header"]), camera, image, int(rec.sequence))


class EncodedFrame(Frame):
    """A :class:`~robotd.base.messages.Frame` that keeps its JPEG bytes and decodes them
    the first time :attr:`image` is read (then keeps the pixels). The pipeline routes it as
    a ``Frame``; pickled or copied, it becomes a plain ``Frame``. It takes a ``Frame``'s
    fields too (``image``: the pixels, already decoded), so ``dataclasses.replace`` works on
    it as on any frame (the copy holds the pixels)."""

    __slots__ = ("_encoded", "_decoded")
    _encoded: np.ndarray | None
    _decoded: np.ndarray | None

    def __init__(self, stamp_ns: int, camera: str, image: np.ndarray | None = None, seq: int = 0, *,
                 encoded: np.ndarray | None = None) -> None:
        if (image is None) == (encoded is None):
            raise TypeError("EncodedFrame takes either image (decoded pixels) or encoded (JPEG bytes)")
        object.__setattr__(self, "stamp_ns", stamp_ns)
        object.__setattr__(self, "camera", camera)
        object.__setattr__(self, "seq", seq)
        object.__setattr__(self, "_encoded", encoded)
        object.__setattr__(self, "_decoded", image)

    @property
    def image(self) -> np.ndarray:
        """The pixels, as :func:`cv2.imdecode` gives them (``IMREAD_UNCHANGED``)."""
        image = self._decoded
        if image is None:
            image = cv2.imdecode(self._encoded, cv2.IMREAD_UNCHANGED)  # type: ignore[arg-type]
            if image is None:  # the 1/8-scale check passed: not seen in practice
                raise ValueError(f"{self.camera} frame {self.seq}: image data does not decode")
            object.__setattr__(self, "_decoded", image)
            object.__setattr__(self, "_encoded", None)
        return image

    def restamped(self, stamp_ns: int) -> EncodedFrame:
        """The same frame at another stamp, decoded only if this one was (a recording
        replayed in a loop: ``bench/bench_daemon.py --memory``)."""
        if self._decoded is not None:
            return EncodedFrame(stamp_ns, self.camera, self._decoded, self.seq)
        return EncodedFrame(stamp_ns, self.camera, seq=self.seq, encoded=self._encoded)

    def __reduce__(self) -> tuple[Any, ...]:
        return Frame, (self.stamp_ns, self.camera, self.image, self.seq)


def _to_frame_lazy(topic: str, m: Any, rec: Message, yaw_source: str) -> Frame:
    """:func:`_to_frame` with the decoding of a JPEG deferred (:class:`EncodedFrame`);
    other formats are decoded at once."""
    data = np.frombuffer(m["data"], np.uint8)
    if data[:2].tobytes() != b"\xff\xd8":  # not JPEG (its start-of-image marker)
        return _to_frame(topic, m, rec, yaw_source)
    if cv2.imdecode(data, cv2.IMREAD_REDUCED_GRAYSCALE_8) is None:
        raise ValueError(f"image data ({m['format']!r}) does not decode")
    match = _CAMERA_TOPIC.match(topic)
    camera = match.group(1) if match else topic.strip("/")
    return EncodedFrame(_stamp_ns(m["header"]), camera, seq=int(rec.sequence), encoded=data)


def _to_pose(topic: str, m: Any, rec: Message, yaw_source: str) -> PoseStamped:
    p = m["pose"]["pose"]
    return PoseStamped(_stamp_ns(m["header"]), float(p["position"]["x"]), float(p["position"]["y"]),
                       _yaw_from_quaternion(p["orientation"]), ros2msg.covariance3(m["pose"]["covariance"]))


_IMAGE = "sensor_msgs/msg/CompressedImage"

_PRODUCES: dict[str, type] = {
    "robotd_msgs/msg/WheelTicks": WheelTicks,
    "sensor_msgs/msg/Imu": YawRate,
    "sensor_msgs/msg/CompressedImage": Frame,
    "nav_msgs/msg/Odometry": PoseStamped,
}
"""The robotd type each readable ROS 2 type becomes (:data:`_CONVERTERS`)."""

_CONVERTERS: dict[str, Callable[[str, Any, Message, str], RobotdMessage]] = {
    "robotd_msgs/msg/WheelTicks": _to_wheel_ticks,
    "sensor_msgs/msg/Imu": _to_yaw_rate,
    "sensor_msgs/msg/CompressedImage": _to_frame,
    "nav_msgs/msg/Odometry": _to_pose,
}


def read_recording(path: str | os.PathLike[str]) -> Iterator[tuple[str, RobotdMessage]]:
    """``(topic, message)`` of a recording in log-time order (see :meth:`RecordingReader.messages`).

    Raises :class:`~robotd.base.errors.DriverError` when the file is unreadable; damage that
    leaves a partly readable file is logged (one warning naming the path, with counts)
    and what is intact is yielded. Use :class:`RecordingReader` to see the counts.
    """
    with RecordingReader(path) as reader:
        yield from reader.messages()
        if reader.damage.undecodable_messages or reader.damage.damaged_chunks:
            log.warning("%s: %d damaged chunks and %d undecodable messages skipped", reader.path,
                        reader.damage.damaged_chunks, reader.damage.undecodable_messages)


