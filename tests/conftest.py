"""Settings shared by the whole test suite."""

import robotd  # noqa: F401  (first: one BLAS thread, as the daemon runs; see robotd/__init__.py)
from hypothesis import settings

# Property tests check values, never speed: hypothesis' default 200 ms deadline per example
# fails them on a loaded 2-core machine (CI included), so it is off. Speed is measured in
# bench/, against a baseline in the same run.
settings.register_profile("robotd", deadline=None)
settings.load_profile("robotd")
