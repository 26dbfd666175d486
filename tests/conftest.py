"""Settings and fixtures shared by the whole test suite."""

import fcntl
import json
import os

import pytest
from hypothesis import settings

from robotd.base.blas import one_blas_thread
from tests.drives import RecordedDrive, record_square

one_blas_thread()  # as the command line runs the daemon (robotd.base.blas)

# Property tests check values, never speed: hypothesis' default 200 ms deadline per example
# fails them on a loaded 2-core machine (CI included), so it is off. Speed is measured in
# bench/, against a baseline in the same run.
settings.register_profile("robotd", deadline=None)
settings.load_profile("robotd")


@pytest.fixture(scope="session")
def recorded_square(tmp_path_factory: pytest.TempPathFactory) -> RecordedDrive:
    """8 s of the square route (seed 5) through ``run_demo``, recorded lossless: made once
    per test run, under pytest-xdist once for all its workers (the first one to ask makes
    it, holding a lock on the run's shared temporary folder, the others wait and read it)."""
    duration_s = 8.0
    if os.environ.get("PYTEST_XDIST_WORKER"):
        folder = tmp_path_factory.getbasetemp().parent / "recorded-square"
    else:
        folder = tmp_path_factory.getbasetemp() / "recorded-square"
    folder.mkdir(exist_ok=True)
    with open(folder.parent / "recorded-square.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (folder / "done").exists():
            record_square(folder, duration_s)
    summary = json.loads((folder / "live" / "summary.json").read_text())
    return RecordedDrive(folder / "run.mcap", folder / "live", summary, duration_s)
