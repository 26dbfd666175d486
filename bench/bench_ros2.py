"""ROS 2 output: latency from a loop closure to the /tf update, and what publishing costs
(issue 25, item 5). One process runs the demo daemon on the virtual robot with [ros2]
on; a second process subscribes to /tf, as Nav2's tf listener would.

Per keyframe whose floor query closed a loop (the pose graph accepted it), three times:

- ``graph+publish``: from the floor detector's query result (candidates scored; before the
  pose graph gates the candidate and updates iSAM2) to the moment the changed
  ``map -> odom`` has been handed to DDS, in the daemon's process;
- ``publish``: from the accepted loop edge (the graph already updated) to the same moment:
  what the output stage adds;
- ``delivered``: from the query result to the moment the subscriber process has taken
  that ``/tf`` sample (both on the host's Unix clock; same machine).

Before that, the CDR encoding of a few message types, robotd's codec against
mcap-ros2-support's (the MCAP writer's before), bytes checked equal. And, from the same
run, the CPU time of the output stage (building, encoding and sending
every message: ``outputs_cpu_us``) against the daemon's own main-thread CPU time (the
pipeline, outputs included), and the main-thread CPU of the same drive without outputs
(the baseline) as a ratio.

All DDS traffic stays on the loopback interface (``CYCLONEDDS_URI`` pinned to ``lo``,
multicast off) on a domain id of its own.

Usage: ``python bench/bench_ros2.py [--route square] [--duration S] [--full]
[--out bench/results/ros2.json] [--doc docs/benchmarks/ros2.md]``; Default: the square route (16 m, 57 s of robot time, about 160 loop closures), twice
(baseline and ROS 2), about 10 minutes on a loaded 2-core machine; ``--full``: the
office route, whole (about 110 m).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

try:
    from bench.common import machine_info, print_table, write_json
except ImportError:  # run as a script: bench/ is on sys.path
    from common import machine_info, print_table, write_json  # type: ignore[no-redef]

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO_ROOT / "bench" / "results" / "ros2.json"


def subscriber(domain: int, out: Path, stop: Path) -> None:
    """The second process: every map -> odom on /tf with its receive time, until ``stop``
    exists."""
    from drivers.ros2 import dds
    from robotd.base import ros2msg

    rows = []
    with dds.Participant(domain) as p:
        tf = p.reader("/tf", "tf2_msgs/msg/TFMessage", dds.QOS_TF)
        ws = dds.WaitSet(p, [tf])
        ready = out.with_suffix(".ready")
        ready.write_text("ok")
        while not stop.exists():
            ws.wait(0.1)
            for data in tf.take(256):
                now = time.time_ns()
                for t in ros2msg.decode("tf2_msgs/msg/TFMessage", data)["transforms"]:
                    if t["header"]["frame_id"] == "map":
                        tr = t["transform"]
                        rows.append([ros2msg.stamp_ns_of(t["header"]), tr["translation"]["x"],
                                     tr["translation"]["y"], ros2msg.yaw_of_quaternion(tr["rotation"]), now])
    out.write_text(json.dumps(rows))


class Probe:
    """A pipeline observer: times the loop closures and the daemon's main-thread CPU."""

    name = "ros2_probe"

    def __init__(self) -> None:
        self.pipeline: Any = None
        self.outputs: Any = None
        self.query_perf_ns: int | None = None
        self.query_unix_ns: int | None = None
        self.loop_perf_ns: int | None = None
        self.loops: list[dict[str, Any]] = []
        self.cpu0: int | None = None
        self.cpu_ns = 0

    def attach(self, pipeline: Any) -> None:
        self.pipeline = pipeline

    def subscriptions(self) -> dict[type, Any]:
        from robotd.base.messages import Link, OdometryUpdate
        from robotd.floor.detector import KeyframeQuery

        return {KeyframeQuery: self.on_query, Link: self.on_link, OdometryUpdate: self.on_odometry}

    def on_odometry(self, _u: Any) -> None:
        if self.cpu0 is None:
            self.cpu0 = time.thread_time_ns()
        if self.outputs is None:
            try:
                self.outputs = self.pipeline.stage("outputs")
                self.outputs.on_tf_update = self.on_tf
            except KeyError:
                self.outputs = False

    def on_query(self, _q: Any) -> None:
        self.query_perf_ns, self.query_unix_ns = time.perf_counter_ns(), time.time_ns()
        self.loop_perf_ns = None

    def on_link(self, link: Any) -> None:
        if link.kind == "loop" and self.loop_perf_ns is None:
            self.loop_perf_ns = time.perf_counter_ns()

    def on_tf(self, stamp_ns: int) -> None:
        if self.loop_perf_ns is None or self.query_perf_ns is None:
            return  # a keyframe's own update, not a loop's
        now = time.perf_counter_ns()
        m = self.outputs.map_odom
        self.loops.append({"stamp_ns": stamp_ns, "value": [float(v) for v in m],
                           "graph_publish_us": (now - self.query_perf_ns) / 1e3,
                           "publish_us": (now - self.loop_perf_ns) / 1e3, "query_unix_ns": self.query_unix_ns})
        self.loop_perf_ns = self.query_perf_ns = None

    def finish(self) -> int:
        if self.cpu0 is not None:
            self.cpu_ns = time.thread_time_ns() - self.cpu0
        return 0


def run(route: str, duration_s: float | None, ros2: bool, out: Path) -> tuple[dict[str, Any], Probe]:
    from robotd.app.demo import run_demo, shipped_calibration
    from robotd.base.config import Config, replace

    cfg = replace(Config(), "calibration", path=str(shipped_calibration()))  # as `robotd demo` does
    if ros2:
        cfg = replace(cfg, "ros2", enabled=True)
    probe = Probe()
    summary = run_demo(cfg, out=out, route=route, duration_s=duration_s, plot=False, observers=(probe,))
    return summary, probe


def codec_times(repeats: int = 7, n: int = 2000) -> dict[str, Any]:
    """Encoding time per message, robotd's CDR codec against mcap-ros2-support's encoder
    (what the MCAP writer used before), on the same dicts; the bytes are checked equal."""
    from mcap_ros2._dynamic import serialize_dynamic

    from robotd.base import ros2msg as r

    msgs = {
        "nav_msgs/msg/Odometry": r.odometry_msg(123_456_789, 1.0, 2.0, 0.3, np.eye(3) * 0.01, "odom",
                                                "base_footprint"),
        "sensor_msgs/msg/Imu": r.imu_yaw_rate_msg(123_456_789, "gyro_link", 0.1),
        "tf2_msgs/msg/TFMessage": r.tf_message([r.planar_transform_msg(5, "map", "odom", (1.0, 2.0, 0.1)),
                                                r.planar_transform_msg(5, "odom", "base_footprint", (3.0, 1.0, 0.2))]),
        "nav_msgs/msg/Path": r.path_msg(5, "map", list(range(500)), np.random.default_rng(0).normal(size=(500, 3))),
    }
    out: dict[str, Any] = {}
    for name, msg in msgs.items():
        theirs = serialize_dynamic(name, r.schema_text(name))[name]
        if bytes(theirs(msg)) != r.encode(name, msg):
            raise SystemExit(f"{name}: the two encoders disagree")
        row = {}
        for label, fn in (("robotd", lambda: r.encode(name, msg)), ("mcap_ros2", lambda: theirs(msg))):
            runs = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                for _ in range(n):
                    fn()
                runs.append((time.perf_counter() - t0) / n * 1e6)
            row[f"{label}_us"] = float(np.median(runs))
        row["speedup"] = row["mcap_ros2_us"] / row["robotd_us"]
        out[name] = row
    return out


def stats_us(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, float)
    if not len(a):
        return {"n": 0}
    return {"n": int(len(a)), "median_us": float(np.median(a)), "p99_us": float(np.percentile(a, 99)),
            "max_us": float(a.max())}


def markdown(r: dict[str, Any]) -> str:
    """``docs/benchmarks/ros2.md`` from a result of this benchmark."""
    m, lt, c = r["machine"], r["loop_to_tf"], r["cpu"]
    full = " --full" if r["route"] == "office" and not r["duration_s"] else ""
    span = f", {r['robot_time_s']:.0f} s of robot time, {r['distance_m']:.0f} m"

    def row(name: str, what: str) -> str:
        s = lt[name]
        if not s.get("n"):
            return f"| {name} | {what} | 0 | | | |"
        return (f"| {name} | {what} | {s['n']} | {s['median_us'] / 1e3:.2f} | {s['p99_us'] / 1e3:.2f} | "
                f"{s['max_us'] / 1e3:.2f} |")

    return "\n".join([
        "# ROS 2 output: loop closure to /tf, and the cost of publishing",
        "",
        f"Generated by `python bench/bench_ros2.py{full}` "
        f"from its JSON: the demo daemon on the virtual robot, route `{r['route']}`{span}, "
        f"{r['keyframes']} keyframes; a subscriber in a second process on the loopback interface. "
        f"Machine: {m['machine']}, {m['cpu_count']} CPUs, Python {m['python']} (shared with other jobs: "
        "timings are noisy, read the ratios).",
        "",
        "Latency per loop closure (ms), from the same run:",
        "",
        "| interval | from -> to | loops | median | p99 | max |",
        "|---|---|---|---|---|---|",
        row("graph_publish", "floor query result -> map -> odom handed to DDS (gate, iSAM2 update, output)"),
        row("publish", "accepted loop edge -> map -> odom handed to DDS (the output stage alone)"),
        row("delivered", "floor query result -> /tf sample taken by the subscriber process"),
        "",
        "CPU (thread CPU time of the daemon's main thread, which runs the pipeline and the outputs):",
        "",
        "| | seconds | |",
        "|---|---|---|",
        f"| output stage: build, encode, send | {c['outputs_s']:.3f} | {100 * (c['outputs_share'] or 0):.2f} % of the main thread |",
        f"| main thread, with ROS 2 output | {c['daemon_main_thread_s']:.2f} | |",
        f"| main thread, same drive without output (baseline) | {c['baseline_main_thread_s']:.2f} | "
        f"with / without: {c['main_thread_ratio_to_baseline'] or 0:.3f} |",
        "",
        f"Messages published: {', '.join(f'{k} {v}' for k, v in sorted(r['published'].items()))}; "
        f"/tf samples with map -> odom taken by the subscriber: {r['tf_received']}.",
        "",
        "Encoding one message (µs, median of 7 runs; identical bytes), robotd's CDR codec against "
        "mcap-ros2-support's encoder, which the MCAP writer used before:",
        "",
        "| type | robotd | mcap-ros2-support | x faster |",
        "|---|---|---|---|",
        *[f"| `{k}` | {v['robotd_us']:.1f} | {v['mcap_ros2_us']:.1f} | {v['speedup']:.1f} |"
          for k, v in r.get("codec", {}).items()],
        "",
    ])


def main(argv: list[str] | None = None) -> int:
    from robotd.base.blas import one_blas_thread

    one_blas_thread()  # as robotd's command line runs the daemon
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--route", default="square")
    ap.add_argument("--duration", type=float, default=None, help="robot seconds (default: the whole route)")
    ap.add_argument("--full", action="store_true", help="the whole office route")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--doc", type=Path, default=None, metavar="MD",
                    help="also write the result as markdown (docs/benchmarks/ros2.md)")
    ap.add_argument("--from-json", type=Path, default=None, help="only write --doc from an earlier JSON")
    ap.add_argument("--subscriber", nargs=3, metavar=("DOMAIN", "OUT", "STOP"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.subscriber:
        subscriber(int(args.subscriber[0]), Path(args.subscriber[1]), Path(args.subscriber[2]))
        return 0
    if args.from_json:
        args.doc.parent.mkdir(parents=True, exist_ok=True)
        args.doc.write_text(markdown(json.loads(args.from_json.read_text())))
        return 0
    route, duration = ("office", None) if args.full else (args.route, args.duration)

    from drivers.ros2 import dds

    domain = 150 + os.getpid() % 60
    os.environ["CYCLONEDDS_URI"] = dds.loopback_config()  # this process and the subscriber: lo only
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    tmp = Path(tempfile.mkdtemp(prefix="bench-ros2-"))
    sub_out, stop = tmp / "sub.json", tmp / "stop"
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    sub = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--subscriber", str(domain),
                            str(sub_out), str(stop)], env=env)
    t0 = time.monotonic()
    while not sub_out.with_suffix(".ready").exists() and time.monotonic() - t0 < 30:
        time.sleep(0.05)

    codec = codec_times()
    print_table(["encode (us per message)", "robotd", "mcap_ros2", "x faster"],
                [[k, round(v["robotd_us"], 1), round(v["mcap_ros2_us"], 1), round(v["speedup"], 2)]
                 for k, v in codec.items()])
    print(f"baseline: the demo without outputs ({route}, {duration or 'whole'} s)", flush=True)
    w0 = time.perf_counter()
    base_summary, base_probe = run(route, duration, False, tmp / "base")
    base_wall = time.perf_counter() - w0
    print("with ROS 2 output", flush=True)
    w0 = time.perf_counter()
    summary, probe = run(route, duration, True, tmp / "ros2")
    wall = time.perf_counter() - w0
    stop.write_text("stop")
    sub.wait(timeout=60)
    received = json.loads(sub_out.read_text())

    outputs_cpu_us = probe.outputs.cpu_ns / 1e3 if probe.outputs else 0.0
    published = dict(probe.outputs.published) if probe.outputs else {}
    delivered = []
    for loop in probe.loops:
        for stamp, x, y, yaw, recv_ns in received:
            if stamp == loop["stamp_ns"] and np.allclose([x, y, yaw], loop["value"], atol=1e-12):
                delivered.append((recv_ns - loop["query_unix_ns"]) / 1e3)
                break
    result = {
        "machine": machine_info(), "route": route, "duration_s": duration,
        "loop_to_tf": {
            "graph_publish": stats_us([lp["graph_publish_us"] for lp in probe.loops]),
            "publish": stats_us([lp["publish_us"] for lp in probe.loops]),
            "delivered": stats_us(delivered),
            "loops_timed": len(probe.loops), "loops_received": len(delivered),
        },
        "cpu": {
            "outputs_s": outputs_cpu_us / 1e6, "daemon_main_thread_s": probe.cpu_ns / 1e9,
            "outputs_share": outputs_cpu_us * 1e3 / probe.cpu_ns if probe.cpu_ns else None,
            "baseline_main_thread_s": base_probe.cpu_ns / 1e9,
            "main_thread_ratio_to_baseline": probe.cpu_ns / base_probe.cpu_ns if base_probe.cpu_ns else None,
            "wall_s": wall, "baseline_wall_s": base_wall,
        },
        "published": published, "tf_received": len(received), "codec": codec,
        "keyframes": summary.get("keyframes"), "robot_time_s": summary.get("robot_time_s"),
        "distance_m": summary.get("distance_m"),
    }
    lt = result["loop_to_tf"]
    print_table(["loop -> /tf", "n", "median us", "p99 us", "max us"],
                [[k, lt[k]["n"], round(lt[k].get("median_us", 0), 1), round(lt[k].get("p99_us", 0), 1),
                  round(lt[k].get("max_us", 0), 1)] for k in ("graph_publish", "publish", "delivered")])
    c = result["cpu"]
    print()
    print_table(["CPU", "seconds", "share / ratio"], [
        ["outputs (build, encode, send)", round(c["outputs_s"], 3), round(c["outputs_share"] or 0, 4)],
        ["daemon main thread, with outputs", round(c["daemon_main_thread_s"], 2), ""],
        ["daemon main thread, baseline", round(c["baseline_main_thread_s"], 2),
         round(c["main_thread_ratio_to_baseline"] or 0, 3)],
    ])
    print(f"\npublished: {published}\n/tf samples with map -> odom received: {len(received)}")
    print(f"wrote {write_json(args.out, result)}")
    if args.doc:
        args.doc.parent.mkdir(parents=True, exist_ok=True)
        args.doc.write_text(markdown(result))
        print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
