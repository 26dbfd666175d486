"""Re-encoding a recording's camera frames: the same drive, compact or lossless.

:func:`transcode` copies a recording message by message, keeping every topic, stamp, log
time, sequence number, channel (with its QoS metadata) and metadata record, and re-encodes
only the ``sensor_msgs/msg/CompressedImage`` frames (PNG to JPEG, or the other way). A
lossless PNG recording transcoded to JPEG at quality ``q`` holds the very bytes a JPEG
recording of the same run at quality ``q`` would have held, since both encode the same
decoded pixels; that is how the benchmark compares thresholds trained on the two forms of
one drive, and how an old PNG recording (1.5 GB for a 4-minute drive) is made compact.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from drivers.recording.reader import RecordingReader, _normalise_type
from drivers.recording.schemas import PARTIAL_SUFFIX
from drivers.recording.writer import image_encoding
from robotd.base import ros2msg
from robotd.base.errors import DriverError

log = logging.getLogger(__name__)

_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"


@dataclass(frozen=True)
class TranscodeResult:
    """What :func:`transcode` did: message and frame counts, bytes in and out."""

    messages: int
    frames: int
    undecodable_frames: int
    """Frames whose image did not decode: copied unchanged (and counted)."""
    bytes_in: int
    bytes_out: int


def transcode(src: str | os.PathLike[str], dst: str | os.PathLike[str], *, image_format: str,
              jpeg_quality: int = 20, png_compression: int = 1,
              chunk_size: int = 256 * 1024) -> TranscodeResult:
    """Copy recording ``src`` to ``dst`` with every camera frame re-encoded as
    ``image_format`` (``"jpeg"`` at ``jpeg_quality`` 0-100, or ``"png"`` at zlib level
    ``png_compression``); everything else is copied byte for byte.

    ``dst`` is written as ``dst.partial`` and renamed when complete; an existing ``dst``
    is an error. The ``robotd`` metadata record's ``image_format`` and ``image_quality``
    are updated, and a ``robotd.transcoded`` record names the source. Raises
    :class:`~robotd.base.errors.DriverError` naming the path when ``src`` is not a
    readable recording or ``dst`` cannot be written; a damaged ``src`` is copied as far
    as it is intact (the reader logs what it skipped).
    """
    if image_format not in ("png", "jpeg"):
        raise ValueError(f"image_format must be 'png' or 'jpeg', got {image_format!r}")
    if not 0 <= jpeg_quality <= 100 or not 0 <= png_compression <= 9:
        raise ValueError("jpeg_quality must be 0..100 and png_compression 0..9")
    dst = Path(dst)
    partial = dst.with_name(dst.name + PARTIAL_SUFFIX)
    if dst.exists():
        raise DriverError(f"{dst}: a recording already exists (choose another name)")
    ext, params = image_encoding(image_format, jpeg_quality, png_compression)
    quality = (f"jpeg_quality {jpeg_quality}" if image_format == "jpeg"
               else f"png_compression {png_compression}")
    messages = frames = bad = 0
    with RecordingReader(src) as reader:
        try:
            f = open(partial, "wb")
        except OSError as exc:
            raise DriverError(f"{partial}: cannot create the recording: {exc.strerror}") from exc
        try:
            with f:
                out = McapWriter(f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
                out.start(profile="ros2", library="robotd transcode")
                schema_ids: dict[int, int] = {}
                channel_ids: dict[int, int] = {}
                for sid, known in sorted(reader.schemas.items()):
                    schema_ids[sid] = out.register_schema(known.name, known.encoding, known.data)
                for cid, ch in sorted(reader.channels.items()):
                    channel_ids[cid] = out.register_channel(
                        ch.topic, ch.message_encoding, schema_ids.get(ch.schema_id, 0), dict(ch.metadata))
                for name, record in reader.metadata.items():
                    if name == "robotd":
                        record = {**record, "image_format": image_format, "image_quality": quality}
                    out.add_metadata(name, record)
                out.add_metadata("robotd.transcoded", {"source": str(Path(src).name),
                                                       "image_format": image_format,
                                                       "image_quality": quality})
                codecs: dict[int, ros2msg.Codec] = {}
                for channel, msg in reader.raw_messages():
                    data = msg.data
                    schema = reader.schemas.get(channel.schema_id)
                    if schema is not None and _normalise_type(schema.name) == _IMAGE_TYPE:
                        frames += 1
                        if schema.id not in codecs:  # the file's own definition, robotd's codec
                            codecs[schema.id] = ros2msg.Codec(_IMAGE_TYPE, ros2msg.parse_schema_text(
                                _IMAGE_TYPE, schema.data.decode()))
                        codec = codecs[schema.id]
                        new = _reencode(codec.decode(data), ext, params, image_format)
                        if new is None:
                            bad += 1
                        else:
                            data = codec.encode(new)
                    out.add_message(channel_ids[channel.id], log_time=msg.log_time, data=data,
                                    publish_time=msg.publish_time, sequence=msg.sequence)
                    messages += 1
                out.finish()
                f.flush()
                os.fsync(f.fileno())
            os.replace(partial, dst)
        except OSError as exc:
            raise DriverError(f"{partial}: cannot write the recording: {exc.strerror or exc}") from exc
    if bad:
        log.warning("%s: %d frames did not decode and were copied unchanged", src, bad)
    return TranscodeResult(messages, frames, bad, Path(src).stat().st_size, dst.stat().st_size)


def _reencode(ros: dict[str, Any], ext: str, params: list[int], image_format: str) -> dict[str, Any] | None:
    """The CompressedImage ``ros`` (a decoded dict) with its image re-encoded; None when
    the image does not decode."""
    image = cv2.imdecode(np.frombuffer(ros["data"], np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    ok, buf = cv2.imencode(ext, image, params)
    if not ok:
        return None
    return {"header": ros["header"], "format": image_format, "data": buf.tobytes()}
