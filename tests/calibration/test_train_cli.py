"""`robotd calibrate loop-curve` never loses thresholds already in the calibration file."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from calibration.train import TrainParams
from robotd.app.cli import main
from robotd.io.calibfile import (
    CalibrationFile,
    LoopThresholds,
    read_calibration,
    write_calibration,
)
from tests.drives import RecordedDrive

OLD = LoopThresholds(thresholds=(20.0, 32.0, 48.0, 93.0, 136.0, 234.0))


def test_a_drive_too_short_to_train_keeps_the_old_thresholds(tmp_path: Path, capsys,
                                                             recorded_square: RecordedDrive):
    """It used to exit 0 and write a file with no threshold at all. (8 s of the square: about a
    dozen keyframes at the default 0.15 m spacing, enough to be read, no revisit to train on.)"""
    rec = recorded_square.recording
    calib = tmp_path / "calibration.yml"
    write_calibration(calib, CalibrationFile(loop=OLD))
    before = calib.read_bytes()
    capsys.readouterr()
    code = main(["calibrate", "loop-curve", str(rec), "--calibration", str(calib), "--modes", "2",
                 "--workers", "1"])
    err = capsys.readouterr().err
    assert code == 2, err
    errors = [line for line in err.splitlines() if line.startswith("robotd: error:")]
    assert len(errors) == 1, err
    assert re.fullmatch(rf"robotd: error: {re.escape(str(rec))}: no mode could be trained \(\d+ "
                        rf"keyframes: too short a drive, or too few revisits\); {re.escape(str(calib))} "
                        r"is left as it was, with its thresholds for modes 1, 2, 3, 4, 5, 6",
                        errors[0]), errors[0]
    assert "Traceback" not in err
    assert calib.read_bytes() == before
    assert read_calibration(calib).loop == OLD


def test_modes_not_trained_now_keep_their_thresholds():
    from calibration.train_cli import merge_thresholds

    params = TrainParams(modes=(2, 4))
    by_mode, kept, dropped = merge_thresholds(OLD, {2: 40.0, 4: None}, params)
    assert by_mode == {1: 20.0, 2: 40.0, 3: 48.0, 4: 93.0, 5: 136.0, 6: 234.0}
    assert kept == [1, 3, 4, 5, 6] and dropped == []
    assert merge_thresholds(None, {2: 40.0, 4: None}, params) == ({2: 40.0}, [], [])


def test_thresholds_of_another_r_are_not_mixed_with_new_ones():
    from calibration.train_cli import merge_thresholds

    params = TrainParams(modes=(2,), r=0.5)
    by_mode, kept, dropped = merge_thresholds(OLD, {2: 40.0}, params)
    assert by_mode == {2: 40.0} and kept == [] and dropped == [1, 3, 4, 5, 6]


@pytest.mark.parametrize("r", [0.33])
def test_merged_thresholds_make_a_valid_file(tmp_path: Path, r: float):
    from calibration.train_cli import merge_thresholds

    by_mode, _, _ = merge_thresholds(OLD, {2: 40.0}, TrainParams(modes=(2,), r=r))
    loop = LoopThresholds.from_mapping(by_mode, overlap_r=r, confidence=0.99)
    assert loop.thresholds == (20.0, 40.0, 48.0, 93.0, 136.0, 234.0)
