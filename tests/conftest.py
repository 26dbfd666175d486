"""Settings shared by the whole test suite."""

from hypothesis import settings

from robotd.base.blas import one_blas_thread

one_blas_thread()  # as the command line runs the daemon (robotd.base.blas)

# Property tests check values, never speed: hypothesis' default 200 ms deadline per example
# fails them on a loaded 2-core machine (CI included), so it is off. Speed is measured in
# bench/, against a baseline in the same run.
settings.register_profile("robotd", deadline=None)
settings.load_profile("robotd")
