"""ROS 2 output: latency from a loop closure to the /tf update, and what publishing costs.
One process runs the demo daemon on the virtual robot with [ros2]
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

Also, in the same run: the golden-byte table (every type robotd speaks, encoded by its
model, against ``rosbags``' ``serialize_cdr`` in the Humble, Jazzy and Kilted type
stores); the two-process results (what the subscriber process received: ``map -> odom``,
odometry and its rate, ``robotd/pose`` with the graph's covariance, ``ros_discovery_info``;
and a second subscriber process that joins late and must still get ``/tf_static``); the
cost of the pose graph's marginal covariance behind ``robotd/pose`` (per call in the run,
and against iSAM2's own update per keyframe on chains of growing length); and a Foxglove
client log (``tools/foxglove_listen.py``, a plain ``websockets`` client, against
``robotd demo --foxglove --realtime`` for 30 s).

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
import threading
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
GOLDEN_DISTROS = ("humble", "jazzy", "kilted")


def two_process(got: dict[str, Any], late: dict[str, Any], late_delay_s: float | None, probe: Any) -> dict[str, Any]:
    """What the subscriber processes received (see the module notes)."""
    stamps = np.array(sorted(set(got["odometry_stamps"])), dtype=np.int64)
    rate = float((len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9)) if len(stamps) > 1 else 0.0
    pose = np.array(got["pose_cov"], dtype=float).reshape(-1, 4)
    pose = pose[np.argsort(pose[:, 0], kind="stable")]
    sig = np.sqrt(pose[:, 1:3].max(axis=1))  # the larger of the x and y standard deviations, m
    published = dict(probe.outputs.published) if probe.outputs else {}
    return {
        "map_odom_received": len(got["tf"]), "map_odom_distinct": len({tuple(r[1:4]) for r in got["tf"]}),
        "odometry_received": int(len(got["odometry_stamps"])), "odometry_published": published.get("odometry", 0),
        "odometry_rate_hz": rate,
        "pose_received": int(len(pose)),
        "pose_sigma_xy_m": {"median": float(np.median(sig)) if len(sig) else None,
                            "max": float(sig.max()) if len(sig) else None,
                            "last": float(sig[-1]) if len(sig) else None},
        "pose_sigma_drops": int(np.sum(np.diff(sig) < -0.1 * sig[:-1])) if len(sig) > 1 else 0,
        "nodes": got["nodes"], "static_first_subscriber": len(got["static"]),
        "late_joined_after_s": late_delay_s,
        "late_static": late.get("static", [])[:1],
    }


def subscriber(domain: int, out: Path, stop: Path) -> None:
    """The second process: every map -> odom on /tf with its receive time, until ``stop``
    exists."""
    from drivers.ros2 import dds
    from robotd.base import ros2msg

    rows = []
    extra: dict[str, Any] = {"odometry_stamps": [], "pose_cov": [], "nodes": [], "static": []}
    late = out.name.startswith("late")
    with dds.Participant(domain) as p:
        tf = p.reader("/tf", "tf2_msgs/msg/TFMessage", dds.QOS_TF)
        odom = p.reader("robotd/odometry", "nav_msgs/msg/Odometry")
        pose = p.reader("robotd/pose", "geometry_msgs/msg/PoseWithCovarianceStamped")
        static = p.reader("/tf_static", "tf2_msgs/msg/TFMessage", dds.QOS_TF_STATIC)
        discovery = p.discovery_reader(dds.ros_distro())
        ws = dds.WaitSet(p, [tf, odom, pose, static, discovery])
        t_join = time.time_ns()
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
            for m in odom.take_decoded(256):
                extra["odometry_stamps"].append(ros2msg.stamp_ns_of(m["header"]))
            for m in pose.take_decoded(256):
                c = ros2msg.covariance3(m["pose"]["covariance"])
                extra["pose_cov"].append([ros2msg.stamp_ns_of(m["header"]), float(c[0, 0]), float(c[1, 1]),
                                          float(c[2, 2])])
            for m in static.take_decoded():
                extra["static"].append({"after_join_ms": (time.time_ns() - t_join) / 1e6,
                                        "children": [t["child_frame_id"] for t in m["transforms"]]})
            for data in discovery.take():
                m = dds.discovery_codec(dds.ros_distro()).decode(data)
                extra["nodes"] = [[n["node_namespace"], n["node_name"], len(n["writer_gid_seq"]),
                                   len(n["reader_gid_seq"])] for n in m["node_entities_info_seq"]]
            if late and extra["static"]:
                break
    out.write_text(json.dumps({"tf": rows, **extra}))


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
        n_msg = max(20, n // 10) if name == "nav_msgs/msg/Path" else n  # a path of 500 poses takes ms
        for label, fn in (("robotd", lambda: r.encode(name, msg)), ("mcap_ros2", lambda: theirs(msg))):
            runs = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                for _ in range(n_msg):
                    fn()
                runs.append((time.perf_counter() - t0) / n_msg * 1e6)
            row[f"{label}_us"] = float(np.median(runs))
        row["speedup"] = row["mcap_ros2_us"] / row["robotd_us"]
        out[name] = row
    return out


def golden_table() -> dict[str, dict[str, Any]]:
    """Per type and distribution: robotd's bytes equal to ``rosbags``' ``serialize_cdr`` of
    the same message, and ``rosbags`` reading robotd's bytes back to it (the samples and
    the dict -> rosbags conversion of ``tests/base/test_ros2msg.py``)."""
    from robotd.base import ros2msg as r
    from tests.base.test_ros2msg import DISTROS, from_rosbags, samples, store, to_rosbags

    table: dict[str, dict[str, Any]] = {}
    for distro in DISTROS:
        ts = store(distro)
        for typename, msg in samples(distro).items():
            codec = r.Codec(typename, r.definitions(distro))
            ours = codec.encode(msg)
            complete = codec.decode(ours)
            theirs = bytes(ts.serialize_cdr(to_rosbags(ts, typename, complete), typename))
            back = from_rosbags(ts.deserialize_cdr(ours, typename)) == complete
            table.setdefault(typename, {})[distro] = {"equal": ours == theirs and back, "bytes": len(ours)}
    return table


def marginal_scaling(sizes: tuple[int, ...], loop_every: int = 50) -> list[dict[str, Any]]:
    """The keyframe marginal behind ``robotd/pose`` against iSAM2's own update per keyframe
    (the baseline), on square-ish chains of ``n`` keyframes with a loop back every
    ``loop_every``: median µs of each over the last 50 keyframes."""
    from robotd.graph import IncrementalGraph
    from robotd.graph.covariance import tangent_to_world

    info = np.diag([1e4, 1e4, 4e4])
    out = []
    for n in sizes:
        g = IncrementalGraph()
        g.add_first(0)
        add_us, marg_us = [], []
        for k in range(1, n):
            t0 = time.perf_counter_ns()
            g.add_keyframe(k, k - 1, (0.1, 0.0, 2 * np.pi / 100), info)
            t1 = time.perf_counter_ns()
            if k % loop_every == 0 and k >= 100:
                g.add_loop(k - 100, k, (0.0, 0.0, 0.0), info)
            t2 = time.perf_counter_ns()
            tangent_to_world(g.pose(k), g.marginal_covariance(k))
            t3 = time.perf_counter_ns()
            if k >= n - 50:
                add_us.append((t1 - t0) / 1e3)
                marg_us.append((t3 - t2) / 1e3)
        a, m = float(np.median(add_us)), float(np.median(marg_us))
        out.append({"keyframes": n, "isam2_update_us": a, "marginal_us": m, "ratio": m / a})
        print(f"  {n} keyframes: iSAM2 update {a:.0f} us, marginal {m:.0f} us", flush=True)
    return out


def foxglove_log(seconds: float, tmp: Path) -> dict[str, Any]:
    """``robotd demo --foxglove --realtime`` in one process, ``tools/foxglove_listen.py``
    (a plain ``websockets`` client) in another for ``seconds``: its log."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    demo = subprocess.Popen([sys.executable, "-m", "robotd.app.cli", "demo", "--foxglove", "--foxglove-port",
                             str(port), "--realtime", "--route", "square", "--duration", str(seconds + 30),
                             "--no-plot", "--out", str(tmp / "foxglove-demo")], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120 and demo.poll() is None:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                time.sleep(0.2)
        listen = subprocess.run([sys.executable, str(REPO_ROOT / "tools" / "foxglove_listen.py"),
                                 f"ws://127.0.0.1:{port}", "--seconds", str(seconds), "--lines", "12"],
                                env=env, capture_output=True, text=True, timeout=seconds + 60)
    finally:
        demo.terminate()
        try:
            demo.wait(timeout=30)
        except subprocess.TimeoutExpired:
            demo.kill()
    return {"seconds": seconds, "returncode": listen.returncode, "log": listen.stdout.splitlines(),
            "stderr_tail": listen.stderr.splitlines()[-5:]}


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
        *extra_sections(r),
    ])


def extra_sections(r: dict[str, Any]) -> list[str]:
    """The golden bytes, the two-process results, the marginal's cost and the Foxglove log."""
    lines: list[str] = []
    golden = r.get("golden", {})
    if golden:
        lines += ["## Golden bytes", "",
                  "Every type robotd speaks, encoded by its model, against `rosbags`' `serialize_cdr` of the same "
                  "message in each distribution's type store (and `rosbags` reading robotd's bytes back to it); "
                  "bytes of the sample message:", "",
                  "| type | " + " | ".join(GOLDEN_DISTROS) + " |", "|---|" + "---|" * len(GOLDEN_DISTROS)]
        for k, v in golden.items():
            cells = [f"{'equal' if v[d]['equal'] else '**different**'} ({v[d]['bytes']})" for d in GOLDEN_DISTROS]
            lines.append(f"| `{k}` | " + " | ".join(cells) + " |")
        lines += ["", "`rmw_dds_common/msg/ParticipantEntitiesInfo` (`ros_discovery_info`) is longer in Humble: its "
                  "GID is 24 bytes there, 16 in Jazzy and Kilted.", ""]
    tp = r.get("two_process")
    if tp:
        late = tp["late_static"]
        late_txt = (f"got `/tf_static` ({', '.join(late[0]['children'])}) {late[0]['after_join_ms']:.0f} ms after "
                    "joining" if late else "got no `/tf_static`")
        nodes = ", ".join(f"`{ns.rstrip('/')}/{name}` ({w} writers, {rd} readers)" for ns, name, w, rd in tp["nodes"])
        sig = tp["pose_sigma_xy_m"]
        lines += ["## Two processes", "",
                  "The subscriber process (its own `CYCLONEDDS_URI` on `lo`, the run's own domain id) received:", "",
                  f"- `/tf` `map -> odom`: {tp['map_odom_received']} samples, {tp['map_odom_distinct']} distinct values;",
                  f"- `robotd/odometry`: {tp['odometry_received']} of {tp['odometry_published']} published, "
                  f"{tp['odometry_rate_hz']:.1f} Hz of odometry time;",
                  f"- `robotd/pose`: {tp['pose_received']} messages; the larger of the x and y standard deviations "
                  f"(the pose graph's marginal carried by the odometry): median {sig['median']:.4f} m, largest "
                  f"{sig['max']:.4f} m, last {sig['last']:.4f} m; it fell by more than 10 % from one message to the "
                  f"next {tp['pose_sigma_drops']} times (loop closures);"
                  if sig["median"] is not None else "- `robotd/pose`: none received;",
                  f"- `ros_discovery_info`: {nodes or 'nothing'};",
                  f"- a second subscriber process joining {tp['late_joined_after_s']:.0f} s into the run {late_txt}."
                  if tp["late_joined_after_s"] is not None else "- no late subscriber (the run was too short).",
                  ""]
    mg = r.get("marginal")
    if mg:
        run = mg["in_run"]
        per = run["total_s"] / run["calls"] * 1e6 if run["calls"] else 0.0
        lines += ["## The marginal covariance behind `robotd/pose`", "",
                  f"Computed once per keyframe entering the graph and per accepted loop, not per message: in the run "
                  f"{run['calls']} calls, {run['total_s']:.3f} s in all ({per:.0f} µs each; failures: "
                  f"{run['failures']}). Against iSAM2's own update per keyframe (the baseline), on chains of 0.1 m "
                  "steps turning 3.6 degrees, a loop back 100 keyframes every 50 (median of the last 50 keyframes):", "",
                  "| keyframes | iSAM2 update (µs) | marginal (µs) | marginal / update |", "|---|---|---|---|",
                  *[f"| {s['keyframes']} | {s['isam2_update_us']:.0f} | {s['marginal_us']:.0f} | {s['ratio']:.2f} |"
                    for s in mg["scaling"]], ""]
    fox = r.get("foxglove")
    if fox:
        lines += ["## Foxglove client log", "",
                  f"`tools/foxglove_listen.py` (a plain `websockets` client) against `robotd demo --foxglove "
                  f"--realtime` for {fox['seconds']:.0f} s (exit code {fox['returncode']}):", "", "```",
                  *fox["log"], "```", ""]
    return lines


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
    golden = golden_table()
    print_table(["golden bytes vs rosbags", *GOLDEN_DISTROS],
                [[k, *("equal" if v[d]["equal"] else "DIFFERENT" for d in GOLDEN_DISTROS)] for k, v in golden.items()])
    print("marginal covariance of the newest keyframe against iSAM2's update", flush=True)
    scaling = marginal_scaling((100, 1000, 3000, 10000) if args.full else (100, 1000, 3000))
    print(f"baseline: the demo without outputs ({route}, {duration or 'whole'} s)", flush=True)
    w0 = time.perf_counter()
    base_summary, base_probe = run(route, duration, False, tmp / "base")
    base_wall = time.perf_counter() - w0
    print("with ROS 2 output", flush=True)
    # a second subscriber joins while the daemon runs: /tf_static must still reach it
    late_out = tmp / "late.json"
    late_delay_s = 20.0
    late: dict[str, Any] = {}

    def start_late() -> None:
        late["joined_unix_ns"] = time.time_ns()
        late["proc"] = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--subscriber",
                                         str(domain), str(late_out), str(stop)], env=env)

    timer = threading.Timer(late_delay_s, start_late)
    timer.start()
    w0 = time.perf_counter()
    summary, probe = run(route, duration, True, tmp / "ros2")
    wall = time.perf_counter() - w0
    timer.cancel()
    stop.write_text("stop")
    sub.wait(timeout=60)
    got = json.loads(sub_out.read_text())
    received = got["tf"]
    late_got: dict[str, Any] = {}
    if "proc" in late:
        late["proc"].wait(timeout=60)
        late_got = json.loads(late_out.read_text()) if late_out.exists() else {}
    print("Foxglove: demo --foxglove --realtime and a websockets client, 30 s", flush=True)
    fox = foxglove_log(30.0, tmp)
    print("\n".join(fox["log"]), flush=True)

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
        "golden": golden, "marginal": {
            "in_run": {"calls": probe.outputs.marginals if probe.outputs else 0,
                       "total_s": probe.outputs.marginal_ns / 1e9 if probe.outputs else 0.0,
                       "failures": probe.outputs.marginal_failures if probe.outputs else 0},
            "scaling": scaling},
        "two_process": two_process(got, late_got, late_delay_s if late else None, probe),
        "foxglove": fox,
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
