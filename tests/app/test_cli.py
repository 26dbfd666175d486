"""The robotd command as a user meets it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from drivers.kobuki.protocol import BasicSensorData, InertialData, encode_feedback


def test_output_into_a_closed_pipe_ends_quietly(tmp_path: Path):
    """`robotd kobuki decode capture | head -1`: no traceback once head has gone."""
    packets = b"".join(
        encode_feedback(BasicSensorData(timestamp_ms=i & 0xFFFF, bumper=0, wheel_drop=0, cliff=0,
                                        left_encoder=i & 0xFFFF, right_encoder=i & 0xFFFF,
                                        left_pwm=0, right_pwm=0, buttons=0, charger=0,
                                        battery_decivolts=160, overcurrent=0),
                        InertialData(angle_centideg=0, angle_rate_centidegps=0))
        for i in range(20000))
    capture = tmp_path / "capture.bin"
    capture.write_bytes(packets)
    proc = subprocess.Popen([sys.executable, "-m", "robotd.app.cli", "kobuki", "decode", str(capture)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = proc.stdout.readline()
    proc.stdout.close()  # what head does after its line
    err = proc.stderr.read().decode()
    code = proc.wait(60)
    assert first.startswith(b'{"packet": 0')
    assert err == "" and code == 141
