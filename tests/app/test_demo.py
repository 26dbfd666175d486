"""`robotd demo` end to end: the daemon on the virtual robot, through the real drivers."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from robotd.base.config import Config
from robotd.app.demo import run_demo
from sim.route import MotionLimits, build_route, plan_motion
from robotd.io.store import MapStore
from robotd.io.trajectory import read_tum


def test_short_demo_writes_a_consistent_map_and_trajectories(tmp_path: Path):
    s = run_demo(Config(), out=tmp_path, route="square", duration_s=12.0, seed=3)
    # Lossless: every rendered frame reached the pipeline, nothing dropped, no bad bytes.
    assert s["frames_processed"] == s["frames_rendered"] == int(math.ceil(12.0 * 30))
    assert all(v == 0 for v in s["drops"].values()), s["drops"]
    assert all(v == 0 for v in s["packet_errors"].values()), s["packet_errors"]
    assert s["odometry_samples"] >= 12.0 * 50 - 2
    # The robot answered the daemon's RequestExtra over the pty.
    assert s["commands_seen_by_robot"].get("RequestExtra") == 1
    # A keyframe every [keyframes] distance_m or rotation_deg: at least distance / distance_m.
    assert s["keyframes"] >= s["distance_m"] / Config().keyframes.distance_m
    # TUM files: one line per odometry sample, stamps increasing.
    stamps, fused = read_tum(tmp_path / "fused.tum")
    assert len(stamps) == s["odometry_samples"] and np.all(np.diff(stamps) > 0)
    gt_stamps, gt = read_tum(tmp_path / "groundtruth.tum")
    assert len(gt_stamps) > 0 and abs(gt_stamps[-1] / 1e9 - 12.0) < 0.05
    # Over 12 s the fused odometry is within a few centimetres of the truth.
    assert s["fused"]["ape_origin_max_m"] < 0.05
    # Keyframe poses in the map are the fused poses at the frame stamps: near the truth.
    motion = plan_motion(build_route("square"), MotionLimits())
    with MapStore.open(tmp_path / "map.sqlite", create=False) as store:
        kfs = list(store.keyframes())
        assert len(kfs) == s["keyframes"]
        truth = motion.pose_at(np.array([k.stamp_ns / 1e9 for k in kfs]))
        est = np.array([[k.x_m, k.y_m] for k in kfs])
        assert np.max(np.hypot(*(est - truth[:, :2]).T)) < 0.05
        img = store.keyframe_image(kfs[len(kfs) // 2].id)
        assert img.shape == (120, 160) and img.std() > 5  # a real, textured floor image
        assert all(np.all(np.linalg.eigvalsh(k.covariance) >= 0) for k in kfs)
    png = cv2.imread(str(tmp_path / "trajectories.png"))
    assert png is not None and png.shape[0] > 400 and png.std() > 10
    assert json.loads((tmp_path / "summary.json").read_text())["keyframes"] == s["keyframes"]
    # Every trajectory the summary prints is a TUM file: the same figures come back from it.
    kf_stamps, corrected = read_tum(tmp_path / "corrected.tum")
    _, at_keyframes = read_tum(tmp_path / "keyframes.tum")
    assert len(kf_stamps) == s["pose_graph"]["keyframes"] and np.all(np.diff(kf_stamps) > 0)
    truth = motion.pose_at(kf_stamps / 1e9)
    for name, est in (("loop_corrected", corrected), ("odometry", at_keyframes)):
        ape = float(np.sqrt(np.mean(np.sum((est[:, :2] - truth[:, :2]) ** 2, axis=1))))
        assert ape == pytest.approx(s["pose_graph"][name]["ape_origin_rmse_m"], abs=2e-6), name


@pytest.mark.slow
def test_default_demo_from_the_command_line(tmp_path: Path):
    """What `./dev demo` runs: the whole office route (about 110 m), with the figures the
    README shows pinned: at least 1400 loop edges accepted and every one truly overlapping
    (README: 1658 of 1658), none of the true ones refused by the gate, the loop-corrected
    APE (RMS, anchored at the start) under 1 cm (README: 1 mm), the fused end error under 0.1 m (README: 0.043 m) and
    far below the wheel-only one with the nominal model (README: 2.14 m)."""
    r = subprocess.run([sys.executable, "-m", "robotd.app.cli", "demo", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "end position error (m)" in r.stdout
    s = json.loads((tmp_path / "summary.json").read_text())
    assert 100.0 < s["distance_m"] < 125.0
    assert s["frames_processed"] == s["frames_rendered"]
    assert all(v == 0 for v in s["drops"].values())
    # Fusion beats wheel-only odometry at the end of the route. The baseline is wheel only
    # with the nominal model, which the demo also reports when its calibration holds one.
    wheel = s["wheel_only_nominal"] or s["wheel_only"]
    assert s["fused"]["end_position_error_m"] < wheel["end_position_error_m"]
    assert s["fused"]["end_heading_error_deg"] < wheel["end_heading_error_deg"]
    fd, pg = s["floor_detector"], s["pose_graph"]
    assert fd["loops_accepted"] >= 1400
    assert fd["loops_truly_overlapping"] == fd["loops_accepted"]
    assert fd["refused_truly_overlapping"] == 0
    assert pg["loop_corrected"]["ape_origin_rmse_m"] < 0.01
    assert s["fused"]["end_position_error_m"] < 0.1
    assert s["fused"]["end_position_error_m"] < 0.25 * wheel["end_position_error_m"]


def _small_disk(limit_bytes: int):
    """preexec_fn: no file of the child may grow past ``limit_bytes`` (writes beyond fail
    with EFBIG, as on a full disk; SIGXFSZ ignored so the write fails instead of killing)."""
    import resource
    import signal

    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return apply


def test_recording_to_a_full_disk_stops_the_demo_with_one_line(tmp_path: Path):
    """`robotd demo --record` on a disk that fills up: it used to hang for ever (the
    camera's source thread died, the demo waited for its frames)."""
    rec = tmp_path / "x.mcap"
    r = subprocess.run([sys.executable, "-m", "robotd.app.cli", "demo", "--route", "square",
                        "--duration", "5", "--no-plot", "--out", str(tmp_path / "out"),
                        "--record", str(rec)],
                       capture_output=True, text=True, timeout=300, check=False,
                       preexec_fn=_small_disk(1_000_000))
    assert r.returncode == 2, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("robotd: error:")]
    assert len(errors) == 1 and "x.mcap.partial: cannot write: File too large" in errors[0]
    assert not rec.exists()
    from drivers.recording.reader import RecordingReader

    with RecordingReader(str(rec) + ".partial") as reader:
        topics = {t for t, _ in reader.messages()}
        assert reader.damage.unread_tail_bytes == 0 and reader.damage.damaged_chunks == 0
    assert {"/wheel_ticks", "/imu", "/floor_camera/image/compressed"} <= topics
    with MapStore.open(tmp_path / "out" / "map.sqlite", create=False) as store:
        (run,) = store.runs()
        assert run.ended_ns is not None and store.count_keyframes() >= 1  # closed, consistent


def _foreign_files(tmp_path: Path) -> dict[str, bytes]:
    """What a user may keep at OUT/map.sqlite: text, a damaged map, another program's SQLite
    database, a robotd map the demo did not write."""
    import sqlite3

    files = {"text": b"my notes, not a map\n"}
    other = tmp_path / "other.sqlite"
    with sqlite3.connect(other) as conn:
        conn.execute("CREATE TABLE songs (title TEXT)")
    conn.close()
    files["sqlite"] = other.read_bytes()
    robotd_map = tmp_path / "robot.sqlite"
    with MapStore.open(robotd_map) as store:
        store.begin_run("[map]\n")
    files["robotd map"] = robotd_map.read_bytes()
    files["damaged"] = files["robotd map"][:4096] + bytes(4096) + files["robotd map"][8192:]
    return files


@pytest.mark.parametrize("kind", ["text", "sqlite", "robotd map", "damaged"])
def test_demo_leaves_a_foreign_file_at_its_map_path_alone(tmp_path: Path, kind: str):
    """It used to delete whatever was at OUT/map.sqlite."""
    from robotd.base.errors import MapStoreError

    content = _foreign_files(tmp_path)[kind]
    out = tmp_path / "out"
    out.mkdir()
    (out / "map.sqlite").write_bytes(content)
    with pytest.raises(MapStoreError, match=r"map.sqlite is in the way.*left as it is"):
        run_demo(Config(), out=out, route="square", duration_s=0.5, plot=False)
    assert (out / "map.sqlite").read_bytes() == content
    assert sorted(p.name for p in out.iterdir()) == ["map.sqlite"]


def test_demo_replaces_its_own_earlier_map(tmp_path: Path):
    s1 = run_demo(Config(), out=tmp_path, route="square", duration_s=0.5, plot=False)
    s2 = run_demo(Config(), out=tmp_path, route="square", duration_s=0.5, plot=False, seed=1)
    assert s1["ok"] and s2["ok"]
    with MapStore.open(tmp_path / "map.sqlite", create=False) as store:
        assert len(store.runs()) == 1 and store.count_keyframes() == s2["keyframes"]


def _cli(capsys, *args: str) -> tuple[int, str]:
    from robotd.app.cli import main

    code = main(list(args))
    return code, capsys.readouterr().err


@pytest.mark.parametrize("duration", ["1e-9", "0.05", "nan", "inf", "-1"])
def test_demo_and_record_refuse_a_duration_that_is_no_drive(tmp_path: Path, capsys, duration: str):
    """`--duration 1e-9` ended in an IndexError; `robotd record --virtual --duration nan`
    recorded the whole route."""
    out = tmp_path / "out"
    for args in (("demo", "--out", str(out)), ("record", str(tmp_path / "x.mcap"), "--virtual")):
        code, err = _cli(capsys, *args, "--route", "square", "--duration", duration)
        assert code == 2 and err == (f"robotd: error: --duration must be a number of seconds of "
                                     f"robot time, at least 0.1, got {float(duration)}\n")
    assert sorted(tmp_path.iterdir()) == []  # nothing made


def test_demo_out_that_cannot_be_a_folder_is_one_line(tmp_path: Path, capsys):
    """`--out` on an existing file, or below one, ended in a traceback."""
    afile = tmp_path / "afile"
    afile.write_text("keep me\n")
    code, err = _cli(capsys, "demo", "--route", "square", "--duration", "0.5", "--out", str(afile))
    assert code == 2 and err == (f"robotd: error: output folder {afile} exists and is not a folder "
                                 "(choose another --out)\n")
    code, err = _cli(capsys, "demo", "--route", "square", "--duration", "0.5", "--out",
                     str(afile / "sub"))
    assert code == 2 and err == (f"robotd: error: cannot create the output folder {afile / 'sub'}: "
                                 "Not a directory\n")
    assert afile.read_text() == "keep me\n"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_demo_out_in_a_read_only_folder_is_one_line(tmp_path: Path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        code, err = _cli(capsys, "demo", "--route", "square", "--duration", "0.5", "--out", str(ro))
        assert code == 2 and err.startswith(f"robotd: error: output folder {ro} is not writable")
        code, err = _cli(capsys, "demo", "--route", "square", "--duration", "0.5", "--out",
                         str(ro / "sub"))
        assert code == 2 and err == (f"robotd: error: cannot create the output folder {ro / 'sub'}: "
                                     "Permission denied\n")
    finally:
        ro.chmod(0o755)


def _interrupt_when(proc: subprocess.Popen, marker: str) -> list[str]:
    """Read ``proc``'s stderr until a line holds ``marker``, then send SIGINT (Ctrl-C);
    returns the lines read."""
    import signal

    lines = []
    for line in proc.stderr:
        lines.append(line)
        if marker in line:
            proc.send_signal(signal.SIGINT)
            return lines
    raise AssertionError(f"no {marker!r} on stderr: {''.join(lines)[-2000:]}")


def test_an_interrupted_demo_says_so_and_reports_what_it_did(tmp_path: Path):
    """Ctrl-C used to give the planned duration's figures and exit 0 (or 1)."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "robotd.app.cli", "demo", "--route", "square",
                             "--duration", "40", "--no-plot", "--out", str(out),
                             "--record", str(tmp_path / "x.mcap")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _interrupt_when(proc, "demo:  ")  # the first progress line: 10 % of the drive done
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 130, stderr[-3000:]
    assert "Traceback" not in stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"] == "SIGINT" and not s["ok"] and s["planned_robot_time_s"] == 40.0
    assert 4.0 <= s["robot_time_s"] < 40.0
    assert stdout.splitlines()[0] == (f"interrupted (SIGINT) after {s['robot_time_s']:.1f} s of robot "
                                      "time of the planned 40.0 s; the figures below are of that part")
    assert f"in {s['robot_time_s']:.0f} s robot time" in stdout
    gt_stamps, _ = read_tum(out / "groundtruth.tum")
    assert gt_stamps[-1] / 1e9 <= s["robot_time_s"] + 1e-9  # the truth of the part driven
    with MapStore.open(out / "map.sqlite", create=False) as store:  # consistent, run closed
        (run,) = store.runs()
        assert run.ended_ns is not None and store.count_keyframes() == s["keyframes"] > 0
    from drivers.recording.reader import RecordingReader

    with RecordingReader(tmp_path / "x.mcap") as r:
        assert not r.damage.any
        assert r.metadata["robotd.end"]["completed"] == "false"
        assert r.metadata["robotd.end"]["reason"] == "interrupted (SIGINT)"
