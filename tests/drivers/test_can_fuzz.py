"""Fuzz of the CAN driver's decode path (hypothesis): random ids, lengths, payloads, flags
and timestamps never raise out of :meth:`CanBaseDriver.read`, and every frame is counted
in exactly one class.

The frames are handed to the driver by a bus stand-in (a list), so each example costs no
thread or queue; ids are drawn mostly from the DBC's own (so the decoder, not only the
unknown-id path, is exercised) and the rest at random, standard and extended.
``ROBOTD_FUZZ_EXAMPLES`` sets the number of examples (default 200); run with ``-s`` to see
the inputs tried: ``ROBOTD_FUZZ_EXAMPLES=5000 pytest tests/drivers/test_can_fuzz.py -s``.
"""

from __future__ import annotations

import math
import os

import can
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.can.driver import CanBaseDriver, load_dbc
from robotd.base.clock import ManualClock
from robotd.base.messages import BaseStatus, WheelTicks, YawRate

EXAMPLES = int(os.environ.get("ROBOTD_FUZZ_EXAMPLES", "200"))

_DBC = {name: load_dbc(name) for name in ("diff_drive", "odrive_cansimple")}
_SIGNALS = {
    "diff_drive": {"left": "Base_Wheels.Left_Wheel_Pos", "right": "Base_Wheels.Right_Wheel_Pos",
                   "wheel_unit": "rad", "yaw": "Base_Gyro.Yaw_Rate"},
    "odrive_cansimple": {"left": "Left_Encoder_Estimates.Pos_Estimate",
                         "right": "Right_Encoder_Estimates.Pos_Estimate", "wheel_unit": "turn"},
}
_KNOWN_IDS = sorted({m.frame_id for db in _DBC.values() for m in db.messages})


class ListBus:
    """Hands out the frames it was given, then None."""

    def __init__(self) -> None:
        self.frames: list[can.Message] = []

    def recv(self, timeout=None):
        return self.frames.pop(0) if self.frames else None

    def shutdown(self) -> None:
        pass


timestamps = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                       st.floats(min_value=0.0, max_value=1e6), st.just(0.0))
frames = st.builds(
    lambda fid, ext, data, err, rtr, ts: can.Message(
        timestamp=ts, arbitration_id=fid & (0x1FFFFFFF if ext else 0x7FF), is_extended_id=ext,
        data=data, dlc=len(data), is_error_frame=err, is_remote_frame=rtr and not err),
    st.one_of(st.sampled_from(_KNOWN_IDS), st.integers(0, 0x1FFFFFFF)),
    st.booleans(),
    st.binary(min_size=8, max_size=8) | st.binary(min_size=4, max_size=4) | st.binary(max_size=64),
    st.booleans() | st.just(False),
    st.booleans() | st.just(False),
    timestamps,
)

_tried = {"examples": 0, "frames": 0, "messages": 0}


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(dbc=st.sampled_from(sorted(_DBC)), batch=st.lists(frames, max_size=40),
       speed=st.booleans(), clock_s=st.floats(0.0, 1e6))
def test_random_frames_never_raise_out_of_the_driver(dbc, batch, speed, clock_s):
    sig = dict(_SIGNALS[dbc])
    if speed:  # the integrating path too
        sig["wheel_unit"] = "rad/s" if dbc == "diff_drive" else "turn/s"
    bus = ListBus()
    clock = ManualClock(int(clock_s * 1e9))
    driver = CanBaseDriver(bus, clock, _DBC[dbc], max_frames_per_read=16, **sig)
    bus.frames = list(batch)
    out = []
    for _ in range(len(batch) // 16 + 2):
        out += driver.read(0.0)
    s = driver.stats()
    assert s["frames"] == len(batch)
    classes = ("frames_used", "frames_other", "unknown_frames", "decode_errors",
               "remote_frames", "error_frames")
    assert sum(s[k] for k in classes) == len(batch)
    for m in out:
        assert isinstance(m, WheelTicks | YawRate | BaseStatus)
        if isinstance(m, WheelTicks):
            assert 0 <= m.left_ticks < 65536 and 0 <= m.right_ticks < 65536
        if isinstance(m, YawRate):
            assert math.isfinite(m.yaw_rate_radps)
    stamps = [m.stamp_ns for m in out if not isinstance(m, BaseStatus)]
    assert stamps == sorted(stamps)  # never back in time
    _tried["examples"] += 1
    _tried["frames"] += len(batch)
    _tried["messages"] += len(out)


def teardown_module() -> None:
    print(f"\nCAN decode fuzz: {_tried['examples']} examples, {_tried['frames']} frames tried, "
          f"{_tried['messages']} messages out, 0 crashes (any exception fails the test)")
