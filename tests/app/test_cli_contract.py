"""The operator's contract, checked on the real command: every failure ends with its exit
status and one line on stderr (no traceback), and every file that existed before the
command is byte-identical afterwards.

Each case runs ``robotd`` in a process of its own (``--log-level error``, so stderr holds
only what the command itself says). Cases of a new command go here too (docs/cli.md).
"""

from __future__ import annotations

import hashlib
import os
import re
import resource
import shutil
import signal
import sqlite3
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from robotd.io.maplock import lock_path
from robotd.io.store import MapStore

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
ROBOTD = [sys.executable, "-m", "robotd.app.cli", "--log-level", "error"]


# -- helpers ----------------------------------------------------------------------------

def run(*args: object, cwd: Path | None = None, timeout: float = 120.0,
        preexec: Callable[[], None] | None = None) -> subprocess.CompletedProcess:
    """``robotd ARGS`` to completion, stdin closed."""
    return subprocess.run([*ROBOTD, *map(os.fsdecode, args)], cwd=cwd, stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, errors="backslashreplace",
                          timeout=timeout, preexec_fn=preexec)


def start(*args: object, cwd: Path | None = None) -> subprocess.Popen:
    """``robotd ARGS`` in the background."""
    return subprocess.Popen([*ROBOTD, *map(os.fsdecode, args)], cwd=cwd, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            errors="backslashreplace")


def snapshot(*roots: Path) -> dict[str, str]:
    """Every file under ``roots`` (or the files themselves) -> sha256 of its bytes."""
    out = {}
    for root in roots:
        paths = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for p in paths:
            out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def assert_refused(r: subprocess.CompletedProcess, says: str, code: int = 2) -> None:
    """Exit ``code``, one line on stderr that contains ``says``, no traceback."""
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr[-3000:]
    assert r.returncode == code, (r.returncode, r.stderr)
    assert says in lines[0], lines[0]


def full_disk(limit_bytes: int = 4096) -> Callable[[], None]:
    """preexec: files of the command cannot grow past ``limit_bytes`` (EFBIG, as on a full
    disk; SIGXFSZ ignored so the write fails instead of killing the process)."""
    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return limit


def wait_for(condition: Callable[[], bool], proc: subprocess.Popen, what: str,
             timeout_s: float = 60.0) -> None:
    """Poll ``condition`` (the process must stay alive meanwhile)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if proc.poll() is not None:
            raise AssertionError(f"the process ended ({proc.returncode}) before {what}: "
                                 f"{proc.stderr.read()[-2000:] if proc.stderr else ''}")
        if time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def catches_sigterm(pid: int) -> bool:
    """True once the process has its own SIGTERM handler (robotd's start-up guard is in
    place: the command is past Python's start and into its own work)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = int(re.search(r"SigCgt:\s*([0-9a-f]+)", text).group(1), 16)
    return bool(caught & (1 << (signal.SIGTERM - 1)))


def has_run(m: Path) -> bool:
    """True once the map at ``m`` holds a run (read without disturbing its writer)."""
    try:
        conn = sqlite3.connect(m.as_uri() + "?mode=ro", uri=True)
        try:
            return conn.execute("SELECT count(*) FROM runs").fetchone()[0] > 0
        finally:
            conn.close()
    except sqlite3.Error:
        return False


def unprivileged() -> Callable[[], None] | None:
    """preexec: when running as root, give up root's power over files (a new user
    namespace: the process keeps uid 0 on disk but loses CAP_DAC_OVERRIDE there), so that
    permission bits apply to it as to an operator's account."""
    if os.geteuid() != 0:
        return None

    def drop() -> None:
        import ctypes

        clone_newuser = 0x10000000
        if ctypes.CDLL(None, use_errno=True).unshare(clone_newuser) != 0:
            raise OSError(ctypes.get_errno(), "unshare(CLONE_NEWUSER) failed")
    return drop


@pytest.fixture(scope="module")
def material() -> Iterator[Path]:
    """Made once for the module: a 3 s recording of the virtual robot and a 1 s demo's
    output folder. A world-readable folder, so that cases run as ``nobody`` can read it."""
    root = Path(tempfile.mkdtemp(prefix="robotd-contract-"))
    os.chmod(root, 0o755)
    r = run("record", root / "drive.mcap", "--virtual", "--route", "square", "--duration", "3",
            timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    r = run("demo", "--route", "square", "--duration", "1", "--no-plot", "--out", root / "demo",
            timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    for p in root.rglob("*"):
        os.chmod(p, 0o755 if p.is_dir() else 0o644)
    yield root
    shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def demo_out(material: Path, tmp_path: Path) -> Path:
    """A copy of an earlier demo's output folder."""
    out = tmp_path / "demo"
    shutil.copytree(material / "demo", out)
    return out


@pytest.fixture
def g2o(tmp_path: Path) -> Path:
    """A small valid g2o file (a square with one loop)."""
    p = tmp_path / "in.g2o"
    lines = [f"VERTEX_SE2 {i} {x} {y} 0\n" for i, (x, y) in enumerate([(0, 0), (1, 0), (1, 1), (0, 1)])]
    info = "100 0 0 100 0 400"
    lines += [f"EDGE_SE2 {i} {i + 1} 1 0 1.5707963 {info}\n" for i in range(3)]
    lines += [f"EDGE_SE2 3 0 1 0 1.5707963 {info}\n"]
    p.write_text("".join(lines))
    return p


# -- 1. one writer per map --------------------------------------------------------------

def test_a_second_replay_into_a_live_map_is_refused_and_readers_still_work(material: Path,
                                                                           tmp_path: Path):
    m = tmp_path / "m.sqlite"
    first = start("replay", material / "drive.mcap", "--map", m, "--speed", "0.25")  # 12 s: stopped below while it holds the lock
    wait_for(lambda: lock_path(m).exists() and b"pid" in lock_path(m).read_bytes()
             and m.exists() and has_run(m), first, "the first replay's run")
    # Held stopped (the lock stays held) while the others start: on a loaded machine their own
    # start-up could otherwise outlast the first replay, and the second would find no writer.
    first.send_signal(signal.SIGSTOP)
    try:
        second = run("replay", material / "drive.mcap", "--map", m)
        export = run("graph", "export", m, "--out", tmp_path / "export")  # a reader: no lock
    finally:
        first.send_signal(signal.SIGCONT)
    assert_refused(second, f"map {m} is being written by another process (pid {first.pid}")
    out, err = first.communicate(timeout=120)
    assert first.returncode == 0, err[-3000:]
    assert export.returncode == 0 or "has no keyframes" in export.stderr, export.stderr
    with MapStore.open(m, create=False, read_only=True) as store:
        (only,) = store.runs()  # the refused replay added no run, and changed the live one not
        assert only.ended_cleanly and only.notes == ""
    assert not lock_path(m).exists()  # let go when the first replay ended


def test_a_second_daemon_on_one_config_is_refused_before_it_opens_a_device(tmp_path: Path):
    m = tmp_path / "run.sqlite"
    cfg = tmp_path / "robotd.toml"
    cfg.write_text(f'[base]\nport = "loop://"\n[floor_camera]\nsource = "none"\n'
                   f'[map]\npath = "{m}"\n[calibration]\npath = "{tmp_path / "none.yml"}"\n')
    first = start("run", "--config", cfg)
    wait_for(lambda: m.exists() and lock_path(m).exists(), first, "the first daemon's map")
    second = run("run", "--config", cfg)
    assert_refused(second, f"pid {first.pid}")
    first.send_signal(signal.SIGTERM)
    _, err = first.communicate(timeout=60)
    assert first.returncode == 0, err[-2000:]
    with MapStore.open(m, create=False, read_only=True) as store:
        (only,) = store.runs()
        assert only.ended_cleanly


@pytest.mark.slow
def test_a_second_demo_into_a_running_demos_folder_is_refused(tmp_path: Path):
    out = tmp_path / "demo"
    first = start("demo", "--route", "square", "--duration", "60", "--no-plot", "--out", out)
    m = out / "map.sqlite"
    wait_for(lambda: (out / "fused.tum").exists() and m.exists(), first, "the first demo's run")
    second = run("demo", "--route", "square", "--duration", "1", "--no-plot", "--out", out)
    assert_refused(second, f"pid {first.pid}")
    first.send_signal(signal.SIGINT)  # and Ctrl-C mid-run ends the first one cleanly
    _, err = first.communicate(timeout=120)
    assert first.returncode == 130 and "Traceback" not in err, err[-2000:]
    for name in ("fused.tum", "wheel.tum", "groundtruth.tum"):
        assert b"\0" not in (out / name).read_bytes()
    with MapStore.open(m, create=False, read_only=True) as store:
        (only,) = store.runs()
        assert only.ended_cleanly
    assert not lock_path(m).exists()


def test_a_killed_writer_does_not_block_the_next(material: Path, tmp_path: Path):
    """SIGKILL leaves the lock file with a dead pid in it; the kernel dropped the lock."""
    m = tmp_path / "m.sqlite"
    first = start("replay", material / "drive.mcap", "--map", m, "--speed", "0.25")  # 12 s: killed while it runs, even on a loaded machine
    wait_for(lambda: m.exists() and has_run(m), first, "the replay's run")
    first.kill()
    first.communicate(timeout=30)
    assert lock_path(m).exists()
    again = run("replay", material / "drive.mcap", "--map", m)
    assert again.returncode == 0, again.stderr[-2000:]
    with MapStore.open(m, create=False, read_only=True) as store:
        killed, finished = store.runs()
        assert not killed.ended_cleanly and finished.ended_cleanly


# -- 2, 9, 10. graph optimize and export -------------------------------------------------

def test_optimize_refuses_its_input_as_output_even_with_force(g2o: Path):
    before = snapshot(g2o.parent)
    assert_refused(run("graph", "optimize", g2o, "--out", g2o, "--force"), "is the input")
    assert snapshot(g2o.parent) == before


def test_optimize_on_a_full_disk_keeps_the_previous_output(g2o: Path, tmp_path: Path):
    out = tmp_path / "out.g2o"
    out.write_text("previous output\n")
    before = snapshot(tmp_path)
    r = run("graph", "optimize", g2o, "--out", out, "--force", preexec=full_disk(64))
    assert_refused(r, f"cannot write {out}")
    assert snapshot(tmp_path) == before  # nor a temporary file left behind


def test_optimize_replaces_its_output_with_force(g2o: Path, tmp_path: Path):
    out = tmp_path / "out.g2o"
    out.write_text("previous output\n")
    r = run("graph", "optimize", g2o, "--out", out, "--force")
    assert r.returncode == 0, r.stderr
    assert out.read_text().startswith("VERTEX_SE2 0 ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.g2o", "out.g2o"]


@pytest.mark.parametrize("case", ["out_is_a_folder", "out_exists", "out_folder_missing",
                                  "input_missing", "input_is_a_folder", "huge_vertex_id",
                                  "truncated_line"])
def test_optimize_refusals(case: str, g2o: Path, tmp_path: Path):
    args: list[object] = ["graph", "optimize", g2o, "--out", tmp_path / "out.g2o"]
    says = {"out_is_a_folder": "is a folder", "out_exists": "exists (use --force",
            "out_folder_missing": "does not exist", "input_missing": "no such file",
            "input_is_a_folder": "is a folder, not a file", "huge_vertex_id": "above the largest",
            "truncated_line": ":8: EDGE_SE2 needs 11 values, got 8 (truncated)"}[case]
    if case == "out_is_a_folder":
        (tmp_path / "out.g2o").mkdir()
    elif case == "out_exists":
        (tmp_path / "out.g2o").write_text("mine\n")
    elif case == "out_folder_missing":
        args[-1] = tmp_path / "nowhere" / "out.g2o"
    elif case == "input_missing":
        args[2] = tmp_path / "missing.g2o"
    elif case == "input_is_a_folder":
        args[2] = tmp_path
    elif case == "huge_vertex_id":
        g2o.write_text(g2o.read_text().replace("VERTEX_SE2 3 ", f"VERTEX_SE2 {2**63} "))
    elif case == "truncated_line":
        g2o.write_text(g2o.read_text().rsplit(" ", 3)[0] + "\n")
    before = snapshot(tmp_path)
    assert_refused(run(*args), says)
    assert snapshot(tmp_path) == before


def test_export_refusals_leave_everything_as_it_was(material: Path, tmp_path: Path):
    m = material / "demo" / "map.sqlite"
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    existing = tmp_path / "exp"
    existing.mkdir()
    (existing / "odometry.tum").write_text("mine\n")
    before = snapshot(tmp_path, m)
    assert_refused(run("graph", "export", m, "--out", afile), "is a regular file; give a folder")
    assert_refused(run("graph", "export", m, "--out", existing), "exists (use --force")
    assert_refused(run("graph", "export", tmp_path / "nomap.sqlite", "--out", tmp_path / "x"),
                   "does not exist")
    os.chmod(existing, 0o555)  # as a read-only file system would be
    try:
        ro = run("graph", "export", m, "--out", existing, "--force", preexec=unprivileged())
    finally:
        os.chmod(existing, 0o755)
    assert_refused(ro, f"cannot write {existing / 'graph.g2o'}: folder {existing} is not writable")
    assert snapshot(tmp_path, m) == before


# -- 3, 5. kobuki decode -----------------------------------------------------------------

def test_decode_refuses_an_existing_output_and_its_own_capture(material: Path, tmp_path: Path):
    cap = tmp_path / "capture.bin"
    cap.write_bytes(bytes(range(256)) * 4)
    out = tmp_path / "out.jsonl"
    out.write_text("mine\n")
    before = snapshot(tmp_path)
    assert_refused(run("kobuki", "decode", cap, "--out", out), "exists (use --force")
    assert_refused(run("kobuki", "decode", cap, "--out", cap, "--force"), "is the input")
    assert_refused(run("kobuki", "decode", cap, "--out", out, "--force", preexec=full_disk(8)),
                   f"cannot write {out}")
    assert snapshot(tmp_path) == before
    r = run("kobuki", "decode", cap, "--out", out, "--force")
    assert r.returncode == 0 and out.read_text().startswith('{"summary": ')


@pytest.mark.parametrize("device", ["/dev/zero", "fifo", "folder"])
def test_decode_refuses_what_would_be_read_forever(device: str, tmp_path: Path):
    path = Path(device)
    if device == "fifo":
        path = tmp_path / "port"
        os.mkfifo(path)
    elif device == "folder":
        path = tmp_path
    r = run("kobuki", "decode", path, timeout=20)
    kind = {"/dev/zero": "a character device", "fifo": "a named pipe", "folder": "a folder"}[device]
    assert_refused(r, f"is {kind}, not a capture file")


# -- 4, 12, 16, 18, 19. the demo checks everything before touching its output ------------

DEMO_REFUSALS = {
    "record_exists": (["--record", "{material}/drive.mcap"], "exists: choose another name"),
    "record_folder_missing": (["--record", "{tmp}/nowhere/x.mcap"], "does not exist"),
    "floor_missing": (["--floor", "{tmp}/nofloor.png"], "cannot read floor image"),
    "kidnap_past_route": (["--kidnap", "500"], "does not fit a motion"),
    "kidnap_past_duration": (["--kidnap", "50", "--duration", "10"], "never be kidnapped"),
    "negative_seed": (["--seed", "-1"], "--seed must be a whole number"),
    "calibration_not_yaml": (["--calibration", "{material}/drive.mcap"], "drive.mcap"),
    "calibration_missing": (["--calibration", "{tmp}/none.yml"], "no such file"),
    "can_faults_without_can": (["--can-faults"], "--can-faults needs --base can"),
    "duration_zero": (["--duration", "0"], "--duration must be"),
    "unknown_route": (["--route", "moon"], "invalid choice"),
    "foxglove_port_alone": (["--foxglove-port", "9000"], "--foxglove-port needs --foxglove"),
    "foxglove_port_range": (["--foxglove", "--foxglove-port", "70000"], "above the maximum"),
}


@pytest.mark.parametrize("case", sorted(DEMO_REFUSALS))
def test_a_refused_demo_leaves_the_previous_demo_as_it_was(case: str, material: Path,
                                                           demo_out: Path, tmp_path: Path):
    args, says = DEMO_REFUSALS[case]
    args = [a.format(material=material, tmp=tmp_path) for a in args]
    before = snapshot(tmp_path)
    r = run("demo", "--no-plot", "--out", demo_out, *args)
    assert_refused(r, says)
    assert snapshot(tmp_path) == before
    assert not (tmp_path / "nowhere").exists()


def test_a_negative_base_seed_is_refused_before_anything_is_written(tmp_path: Path):
    assert_refused(run("record", tmp_path / "r.mcap", "--virtual", "--duration", "1",
                       "--base-seed", "-1"), "--base-seed must be a whole number")
    assert list(tmp_path.iterdir()) == []


def test_a_refused_record_makes_no_demo_folder(material: Path, tmp_path: Path):
    rec = tmp_path / "run.mcap"
    rec.write_bytes(b"mine")
    assert_refused(run("record", rec, "--virtual", "--duration", "1"), "exists: choose another name")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"] and rec.read_bytes() == b"mine"


def test_a_foreign_file_in_the_demo_folder_is_left_alone(demo_out: Path):
    (demo_out / "map.sqlite").write_text("my notes, not a map\n")
    before = snapshot(demo_out)
    assert_refused(run("demo", "--no-plot", "--duration", "1", "--out", demo_out),
                   "is in the way and is not a demo map")
    assert snapshot(demo_out) == before


# -- robotd calibrate odometry ---------------------------------------------------

@pytest.mark.parametrize("case", ["drive_too_short", "drive_missing", "calibration_missing",
                                  "drive_is_a_folder", "passes_zero", "plot_folder_missing",
                                  "json_is_the_calibration", "calibration_slip_events_partial"])
def test_calibrate_odometry_refusals_keep_the_calibration_file(case: str, material: Path,
                                                               tmp_path: Path):
    cal = tmp_path / "cal.yml"
    shutil.copy(Path(__file__).resolve().parents[2] / "robotd" / "app" / "data" / "demo_calibration.yml", cal)
    drive, says = material / "drive.mcap", {
        "drive_too_short": "the drive lacks", "drive_missing": "cannot open the recording",
        "calibration_missing": "no such calibration file",
        "drive_is_a_folder": "cannot open the recording: Is a directory",
        "passes_zero": "--passes must be at least 1", "plot_folder_missing": "folder",
        "json_is_the_calibration": "--json",
        "calibration_slip_events_partial": "need all of odometry_slip_event_rate_hz"}[case]
    extra: list[object] = {"passes_zero": ["--passes", "0"],
                           "plot_folder_missing": ["--plot", tmp_path / "nowhere" / "r.png"],
                           "json_is_the_calibration": ["--json", cal]}.get(case, [])
    if case == "drive_missing":
        drive = tmp_path / "absent.mcap"
    elif case == "calibration_missing":
        cal = tmp_path / "absent.yml"
    elif case == "drive_is_a_folder":
        drive = tmp_path
    elif case == "calibration_slip_events_partial":  # a damaged file: three of the four slip event keys
        kept = [line for line in cal.read_text().splitlines(keepends=True)
                if not line.startswith("odometry_slip_event_")]
        cal.write_text("".join(kept) + "odometry_slip_event_rate_hz: 0.2\nodometry_slip_event_duration_s: 0.19\n"
                       "odometry_slip_event_rate_sigma_hz: 0.05\n")
    before = snapshot(tmp_path)
    assert_refused(run("calibrate", "odometry", drive, "--calibration", cal, *extra), says)
    assert snapshot(tmp_path) == before


def test_graph_optimize_refuses_an_unknown_robust_kernel(g2o: Path, tmp_path: Path):
    before = snapshot(tmp_path)
    assert_refused(run("graph", "optimize", g2o, "--out", tmp_path / "o.g2o", "--robust", "bogus"),
                   "invalid choice: 'bogus'")
    assert snapshot(tmp_path) == before


# -- 6, 11. replay's arguments and 14: recordings with nothing to replay -----------------

@pytest.mark.parametrize("speed", ["1e-9", "inf", "nan", "0", "-1", "1e6"])
def test_replay_refuses_a_speed_it_cannot_keep(speed: str, material: Path, tmp_path: Path):
    r = run("replay", material / "drive.mcap", "--map", tmp_path / "m.sqlite", "--speed", speed)
    assert_refused(r, "--speed must be from 0.01 to 1000")
    assert list(tmp_path.iterdir()) == []


def test_replay_needs_a_map_named_on_its_command_line(material: Path, tmp_path: Path):
    """Without --map a replay wrote into [map] path: the live service's map, given the
    service's config."""
    r = run("replay", material / "drive.mcap", cwd=tmp_path)
    assert_refused(r, "the following arguments are required: --map")
    assert list(tmp_path.iterdir()) == []


def _write_mcap(path: Path, topic: str, schema_name: str, encoding: str, payload: bytes) -> None:
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(schema_name, encoding, b"string data\n" if encoding == "ros2msg" else b"{}")
        cid = w.register_channel(topic, "cdr" if encoding == "ros2msg" else "json", sid)
        for i in range(20):
            w.add_message(cid, log_time=i * 10**8, publish_time=i * 10**8, data=payload)
        w.finish()


@pytest.mark.parametrize("kind", ["foreign_topics", "undecodable_payloads"])
def test_replay_refuses_a_recording_with_nothing_to_replay_before_opening_the_map(
        kind: str, tmp_path: Path):
    rec = tmp_path / "other.mcap"
    if kind == "foreign_topics":
        _write_mcap(rec, "/chatter", "std_msgs/msg/String", "ros2msg", b"\0\1\0\0\4\0\0\0abc\0")
        says = "/chatter [std_msgs/msg/String]"
    else:
        _write_mcap(rec, "/odom/wheel_ticks", "robotd_msgs/msg/WheelTicks", "ros2msg", b"\xff" * 3)
        says = "20 messages of robotd's types did not decode"
    m = tmp_path / "m.sqlite"
    r = run("replay", rec, "--map", m)
    assert_refused(r, says)
    assert "no message robotd replays" in r.stderr
    assert not m.exists()


def test_replay_of_a_file_that_is_not_mcap(tmp_path: Path):
    rec = tmp_path / "notes.mcap"
    rec.write_text("not a recording\n")
    before = snapshot(tmp_path)
    assert_refused(run("replay", rec, "--map", tmp_path / "m.sqlite"), str(rec))
    assert snapshot(tmp_path) == before


def test_a_damaged_map_is_refused_and_left_as_it_was(material: Path, tmp_path: Path):
    m = tmp_path / "m.sqlite"
    shutil.copy(material / "demo" / "map.sqlite", m)
    with open(m, "r+b") as f:  # a stretch of the file overwritten, as a bad sector might
        f.seek(4096)
        f.write(b"\xa5" * 4096)
    before = snapshot(tmp_path)
    assert_refused(run("replay", material / "drive.mcap", "--map", m), str(m))
    assert snapshot(tmp_path) == before


_ROBOTD_OF_SCHEMA_5 = (
    "import sys\n"
    "from robotd.io import mapconnection\n"
    "mapconnection.MIGRATIONS = {v: mapconnection.MIGRATIONS[v] for v in range(1, 6)}\n"
    "from robotd.app.cli import main\n"
    "sys.exit(main(sys.argv[1:]))\n"
)
"""``robotd`` as a release of map schema 5 is: this code with its migrations ending at 5."""


def test_a_robotd_of_schema_5_refuses_a_map_of_schema_6_and_leaves_it_as_it_was(material: Path, tmp_path: Path):
    """A map this robotd wrote (schema 6) opened by a robotd that knows schema 5 only, to
    export it (read-only) and to replay into it (for writing): refused, one line naming
    both versions, the map byte-identical."""
    m = tmp_path / "m.sqlite"
    shutil.copy(material / "demo" / "map.sqlite", m)
    with sqlite3.connect(m) as raw:
        assert raw.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone() == ("6",)
    raw.close()
    before = snapshot(tmp_path)
    for args in (["graph", "export", m, "--out", tmp_path / "exp"],
                 ["replay", material / "drive.mcap", "--map", m]):
        r = subprocess.run([sys.executable, "-c", _ROBOTD_OF_SCHEMA_5, "--log-level", "error",
                            *map(os.fsdecode, args)], stdin=subprocess.DEVNULL, capture_output=True, text=True,
                           timeout=120)
        assert_refused(r, f"map file {m} has schema version 6, newer than the 5 this robotd")
        assert r.stderr.rstrip().endswith("understands; upgrade robotd"), r.stderr
    assert snapshot(tmp_path) == before


# -- 13. paths that are not UTF-8 --------------------------------------------------------

def test_paths_that_are_not_utf8_are_refused_before_anything_is_written(material: Path,
                                                                       tmp_path: Path):
    bad = Path(os.fsdecode(bytes(tmp_path) + b"/bad\xffname"))
    assert_refused(run("replay", material / "drive.mcap", "--map", bad), "not valid UTF-8")
    assert_refused(run("demo", "--no-plot", "--duration", "1", "--out", bad), "not valid UTF-8")
    assert list(tmp_path.iterdir()) == []


# -- 15, 17. eval forward and empty paths ------------------------------------------------

def _sequence(tmp_path: Path, n: int = 4) -> Path:
    import cv2

    folder = tmp_path / "seq"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:03d}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))
    return folder


def test_eval_forward_refuses_a_ground_truth_with_nan(tmp_path: Path):
    seq = _sequence(tmp_path)
    gt = tmp_path / "gt.csv"
    m = np.eye(4)
    m[0, 2] = m[2, 0] = np.nan
    np.savetxt(gt, m, delimiter=",")
    before = snapshot(tmp_path)
    r = run("eval", "forward", "--images", seq, "--ground-truth", gt, "--out", tmp_path / "fw")
    assert_refused(r, "not numbers (NaN or infinite), the first at row 0, column 2")
    assert snapshot(tmp_path) == before and not (tmp_path / "fw").exists()


@pytest.mark.parametrize("args, says", [
    (["--every", "0"], "--every must be at least 1"),
    (["--tolerance", "-1"], "--tolerance must be >= 0"),
    (["--method", "best"], "invalid choice: 'best'"),
])
def test_eval_forward_refuses_bad_options(args: list[str], says: str, tmp_path: Path):
    seq = _sequence(tmp_path)
    gt = tmp_path / "gt.csv"
    np.savetxt(gt, np.eye(4), delimiter=",")
    before = snapshot(tmp_path)
    assert_refused(run("eval", "forward", "--images", seq, "--ground-truth", gt, *args), says)
    assert snapshot(tmp_path) == before


def test_eval_forward_refuses_an_out_that_is_a_file_before_the_run(tmp_path: Path):
    seq = _sequence(tmp_path)
    gt = tmp_path / "gt.csv"
    np.savetxt(gt, np.eye(4), delimiter=",")
    out = tmp_path / "results"
    out.write_text("not a folder")
    before = snapshot(tmp_path)
    r = run("eval", "forward", "--images", seq, "--ground-truth", gt, "--out", out)
    assert_refused(r, f"--out {out} is a regular file; give a folder")
    assert "images" not in r.stdout  # refused before the sequence was read
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("text, says", [
    ("x_m,y_m,yaw_rad\n0,0,0\n1,0,0\n", "2 rows of 3 values for 4 images"),
    ("x_m,y_m\n0,0\n1,0\n2,0\n3,0\n", "no column yaw_rad in its header"),
    ("x_m,y_m,yaw_rad\n0,0,0\n1,0,a\n2,0,0\n3,0,0\n", "cannot read odometry file"),
    ("x_m,y_m,yaw_rad,var_x_m2\n0,0,0,1\n1,0,0,-1\n2,0,0,1\n3,0,0,1\n", "a negative variance"),
])
def test_eval_forward_refuses_a_bad_odometry_file(text: str, says: str, tmp_path: Path):
    seq = _sequence(tmp_path)
    gt = tmp_path / "gt.csv"
    np.savetxt(gt, np.eye(4), delimiter=",")
    odo = tmp_path / "odometry.csv"
    odo.write_text(text)
    before = snapshot(tmp_path)
    r = run("eval", "forward", "--images", seq, "--ground-truth", gt, "--odometry", odo, "--out", tmp_path / "fw")
    assert_refused(r, says)
    assert snapshot(tmp_path) == before and not (tmp_path / "fw").exists()


def test_eval_forward_refuses_a_damaged_mat_file(tmp_path: Path):
    seq = _sequence(tmp_path)
    gt = tmp_path / "gt.mat"
    gt.write_bytes(b"MATLAB 5.0 MAT-file, cut short" + bytes(20))
    assert_refused(run("eval", "forward", "--images", seq, "--ground-truth", gt),
                   f"cannot read ground-truth file {gt}")


def test_eval_forward_names_a_folder_given_as_ground_truth(tmp_path: Path):
    seq = _sequence(tmp_path)
    r = run("eval", "forward", "--images", seq, "--ground-truth", seq)
    assert_refused(r, "is a folder, not a file")


def test_empty_map_paths_are_refused(material: Path, tmp_path: Path):
    cfg = tmp_path / "robotd.toml"
    cfg.write_text('[map]\npath = ""\n')
    assert_refused(run("config", "check", cfg), "[map] path: must not be empty")
    assert_refused(run("replay", material / "drive.mcap", "--map", ""), "--map: empty path")
    assert list(p.name for p in tmp_path.iterdir()) == ["robotd.toml"]


def test_a_broken_config_is_named_on_one_line(tmp_path: Path):
    cfg = tmp_path / "robotd.toml"
    for text, says in [("[map\n", "not valid TOML"), ("[base]\nbaudrate = 'fast'\n", "[base] baudrate"),
                       ("[nosuch]\n", "unknown section [nosuch]"),
                       ("[odometry]\nwheel_rounding = true\n",
                        "[odometry] wheel_rounding: works only with wheel_increments"),
                       ("[odometry]\nslip_event_rate_hz = 0.3\n",
                        "[odometry] slip_event_rate_hz: works only with slip_gate_sigma > 0"),
                       ("[odometry]\nedge_floor_m = 1.0\n", "[odometry] edge_floor_m: 1.0 is above the maximum"),
                       ("[forward_detector]\nmax_deferred_tests = 65\n",
                        "[forward_detector] max_deferred_tests: 65 is above the maximum"),
                       ("[forward_detector]\nchecks_per_keyframe = 1\nmax_deferred_tests = 0\n",
                        "[forward_detector] checks_per_keyframe: works only with max_deferred_tests > 0"),
                       ("[forward_detector]\nchecks_per_keyframe = 17\n",
                        "[forward_detector] checks_per_keyframe: 17 is above the maximum"),
                       ("[pose_graph]\nscale_wear = 0.005\n",
                        "[pose_graph] scale_wear: works only with odometry_model = \"bias_scale_window\""),
                       ("[pose_graph]\nscale_wear_gyro = 0.001\n",
                        "[pose_graph] scale_wear_gyro: works only with odometry_model = \"bias_scale_window\""),
                       ("[floor_detector]\nransac_confidence = 1.5\n",
                        "[floor_detector] ransac_confidence: 1.5 is above the maximum"),
                       ("[daemon]\ngc_full_between_messages = \"yes\"\n",
                        "[daemon] gc_full_between_messages: expected true or false")]:
        cfg.write_text(text)
        assert_refused(run("config", "check", cfg), says)
        assert_refused(run("run", "--config", cfg), says)


def test_a_config_with_an_old_and_a_new_name_of_one_key_or_a_virtual_camera_is_refused(
        tmp_path: Path):
    """Renamed keys (CHANGELOG.md): both names in one file is one line, for every command
    that reads a config; so is the demo's virtual camera in a file for ``robotd run``."""
    cfg = tmp_path / "robotd.toml"
    m = tmp_path / "m.sqlite"
    for text, says in [
        ("[floor_detector]\nmode = 4\ndescriptor_mode = 4\n",
         "[floor_detector] mode and [floor_detector] descriptor_mode are the same key"),
        ("[forward_detector]\nfx_px = 500.0\n[forward_camera]\nfx_px = 500.0\n",
         "[forward_detector] fx_px and [forward_camera] fx_px are the same key"),
        ('[floor_camera]\nsource = "virtual"\n', "'virtual' is not a camera of `robotd run`"),
    ]:
        cfg.write_text(text)
        before = snapshot(tmp_path)
        assert_refused(run("config", "check", cfg), says)
        assert_refused(run("run", "--config", cfg), says)
        assert_refused(run("demo", "--config", cfg, "--no-plot", "--duration", "1",
                           "--out", tmp_path / "demo"), says)
        assert snapshot(tmp_path) == before and not m.exists()


def test_an_old_config_checks_with_one_warning_per_renamed_key(tmp_path: Path):
    cfg = tmp_path / "robotd.toml"
    cfg.write_text("[odometry]\naccel_noise_mps2 = 0.7\n[pose_graph]\nsave_every_keyframes = 50\n")
    r = subprocess.run([sys.executable, "-m", "robotd.app.cli", "--log-level", "warning", "config",
                        "check", cfg], stdin=subprocess.DEVNULL, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and r.stdout == f"{cfg}: OK\n", r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 2 and "Traceback" not in r.stderr, r.stderr
    assert "[odometry] accel_noise_mps2 is now [odometry] accel_noise_density_mps2_per_sqrt_hz" in lines[0]
    assert "[pose_graph] save_every_keyframes is now [pose_graph] full_solve_every_keyframes" in lines[1]


# -- 7. Ctrl-C during start-up, and mid-run ----------------------------------------------

@pytest.mark.parametrize("command", ["replay", "demo"])
def test_ctrl_c_during_start_up_ends_cleanly(command: str, material: Path, demo_out: Path,
                                             tmp_path: Path):
    """SIGINT as soon as robotd's own start-up began (gtsam and the pipeline still
    loading): no ImportError traceback; nothing written, or a run that is closed."""
    m = tmp_path / "m.sqlite"
    args = (["replay", material / "drive.mcap", "--map", m] if command == "replay"
            else ["demo", "--no-plot", "--duration", "2", "--out", demo_out])
    before = snapshot(demo_out)
    proc = start(*args)
    wait_for(lambda: catches_sigterm(proc.pid), proc, "robotd's start-up guard", timeout_s=30)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert "Traceback" not in err and "ImportError" not in err, err[-3000:]
    assert proc.returncode == 130, err[-3000:]
    assert err.strip().splitlines()[-1].startswith("robotd: ")
    map_path = m if command == "replay" else demo_out / "map.sqlite"
    assert not lock_path(map_path).exists()
    stopped_before_writing = (not m.exists() if command == "replay"
                              else snapshot(demo_out) == before)
    if not stopped_before_writing:  # else the run it opened is closed
        with MapStore.open(map_path, create=False, read_only=True) as store:
            assert [run.ended_ns is not None for run in store.runs()] == [True]


# -- 8. a map folder the user may not enter; a read-only map -----------------------------

@pytest.fixture
def private_folder(material: Path) -> Iterator[tuple[Path, Path]]:
    """A folder nobody may enter (mode 000) with a map in it, and a folder the command may
    write its other outputs to."""
    root = Path(tempfile.mkdtemp(prefix="robotd-private-"))
    os.chmod(root, 0o755)
    private = root / "private"
    private.mkdir()
    shutil.copy(material / "demo" / "map.sqlite", private / "map.sqlite")
    mine = root / "mine"
    mine.mkdir()
    os.chmod(private, 0o000)
    yield private, mine
    os.chmod(private, 0o700)
    shutil.rmtree(root, ignore_errors=True)


def test_a_map_in_a_folder_the_user_cannot_enter(material: Path, private_folder):
    private, mine = private_folder
    m = private / "map.sqlite"
    who = unprivileged()
    for args in (["replay", material / "drive.mcap", "--map", m],
                 ["graph", "export", m, "--out", mine / "exp"],
                 ["demo", "--no-plot", "--duration", "1", "--out", private]):
        r = run(*args, preexec=who)
        assert "Traceback" not in r.stderr, r.stderr[-2000:]
        assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, r.stderr
        assert str(private) in r.stderr
    os.chmod(private, 0o700)
    assert (private / "map.sqlite").read_bytes() == (material / "demo" / "map.sqlite").read_bytes()
    assert list(mine.iterdir()) == []


def test_a_read_only_map_is_refused_for_writing_and_still_exported(material: Path, tmp_path: Path):
    folder = Path(tempfile.mkdtemp(prefix="robotd-ro-"))
    try:
        os.chmod(folder, 0o755)
        m = folder / "map.sqlite"
        shutil.copy(material / "demo" / "map.sqlite", m)
        os.chmod(m, 0o444)
        out = folder / "exp"
        out.mkdir()
        before = snapshot(m)
        who = unprivileged()
        r = run("replay", material / "drive.mcap", "--map", m, preexec=who)
        assert_refused(r, "read-only")
        r = run("graph", "export", m, "--out", out, preexec=who)
        assert r.returncode == 0, r.stderr
        assert snapshot(m) == before
        assert sorted(p.name for p in out.iterdir()) == ["graph.g2o", "odometry.tum", "optimized.tum"]
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# -- output into a closed pipe ------------------------------------------------------------

def test_output_piped_into_head(material: Path):
    proc = subprocess.Popen([*ROBOTD, "kobuki", "decode", str(material / "drive.mcap")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.readline()
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(60) in (0, 141) and err == ""


@pytest.mark.parametrize("args", [["config", "default"], ["config", "default", "--service"],
                                  ["config", "reference"]])
def test_generated_config_text_piped_into_head(args: list[str]):
    """The generated config and reference end quietly when the reader has gone (closed
    before robotd writes: the text would fit in the pipe's buffer otherwise)."""
    proc = subprocess.Popen([*ROBOTD, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(60) in (0, 141) and err == ""


def test_config_default_refuses_an_argument_it_does_not_take(tmp_path: Path):
    before = snapshot(tmp_path)
    assert_refused(run("config", "default", "--service", tmp_path / "robotd.toml"), "unrecognized arguments")
    assert snapshot(tmp_path) == before


def test_the_lock_file_names_its_holder_and_goes_away(material: Path, tmp_path: Path):
    """The lock file names its holder in one line, removed when the holder lets go."""
    m = tmp_path / "m.sqlite"
    first = start("replay", material / "drive.mcap", "--map", m, "--speed", "1")
    wait_for(lambda: lock_path(m).exists() and lock_path(m).read_text().endswith("\n"), first,
             "the lock's line")
    line = lock_path(m).read_text()
    assert line.startswith(f"pid {first.pid}: ") and "replay" in line and line.count("\n") == 1
    first.send_signal(signal.SIGTERM)
    first.communicate(timeout=60)
    assert not lock_path(m).exists()
    conn = sqlite3.connect(m)
    assert conn.execute("PRAGMA quick_check").fetchone() == ("ok",)
    conn.close()
    assert stat.S_ISREG(m.stat().st_mode)
