"""Listen to a Foxglove live view with a plain WebSocket client and print what arrives.

Connects (subprotocol ``foxglove.sdk.v1``), subscribes to every advertised channel, and
decodes each binary message frame (``0x01``, subscription id u32, log time u64, CDR) with
the ``ros2msg`` schema the server advertised for it, through robotd's CDR codec. Prints
one line per message for the first ``--lines`` messages, then a count per topic.

Usage: ``python tools/foxglove_listen.py [ws://127.0.0.1:8765] [--seconds 20] [--lines 30]``.
"""

from __future__ import annotations

import argparse
import collections
import json
import struct
import sys
import time

from websockets.sync.client import connect

from robotd.base import ros2msg


def summary(type_name: str, m: dict) -> str:
    if type_name == "tf2_msgs/msg/TFMessage":
        return "; ".join(f"{t['header']['frame_id']}->{t['child_frame_id']} "
                         f"({t['transform']['translation']['x']:.3f}, {t['transform']['translation']['y']:.3f})"
                         for t in m["transforms"])
    if type_name == "nav_msgs/msg/Odometry":
        p = m["pose"]["pose"]["position"]
        return f"{m['header']['frame_id']} x {p['x']:.3f} y {p['y']:.3f}"
    if type_name == "geometry_msgs/msg/PoseWithCovarianceStamped":
        p = m["pose"]["pose"]["position"]
        return f"{m['header']['frame_id']} x {p['x']:.3f} y {p['y']:.3f}"
    if type_name == "nav_msgs/msg/Path":
        return f"{len(m['poses'])} poses"
    if type_name == "visualization_msgs/msg/MarkerArray":
        return ", ".join(f"{mk['ns']}: {len(mk['points']) // 2} edges" for mk in m["markers"])
    if type_name == "diagnostic_msgs/msg/DiagnosticArray":
        return ", ".join(f"{s['name']} [{s['level']}] {s['message']}" for s in m["status"])
    if type_name == "sensor_msgs/msg/CompressedImage":
        return f"{m['format']} {len(m['data'])} bytes"
    return ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("url", nargs="?", default="ws://127.0.0.1:8765")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--lines", type=int, default=30)
    args = ap.parse_args(argv)
    counts: collections.Counter[str] = collections.Counter()
    channels: dict[int, dict] = {}
    codecs: dict[int, ros2msg.Codec] = {}
    printed = 0
    with connect(args.url, subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        print(f"connected to {args.url} ({ws.subprotocol})")
        t_end = time.monotonic() + args.seconds
        while time.monotonic() < t_end:
            try:
                frame = ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "serverInfo":
                    print(f"serverInfo: {msg['name']}, capabilities {msg.get('capabilities')}")
                elif msg["op"] == "advertise":
                    subs = []
                    for ch in msg["channels"]:
                        sid = len(channels) + 1
                        channels[sid] = ch
                        codecs[sid] = ros2msg.Codec(ch["schemaName"], ros2msg.parse_schema_text(
                            ch["schemaName"], ch["schema"]))
                        subs.append({"id": sid, "channelId": ch["id"]})
                        print(f"advertise: {ch['topic']} {ch['schemaName']} ({ch['encoding']}/{ch['schemaEncoding']})")
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                continue
            if frame[0] != 0x01:
                continue
            sid, log_time = struct.unpack_from("<IQ", frame, 1)
            ch = channels[sid]
            counts[ch["topic"]] += 1
            if printed < args.lines:
                decoded = codecs[sid].decode(frame[13:])
                print(f"{log_time / 1e9:.3f} {ch['topic']}: {summary(ch['schemaName'], decoded)}")
                printed += 1
    print("received per topic:", dict(sorted(counts.items())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
