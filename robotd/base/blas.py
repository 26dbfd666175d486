"""One BLAS thread for the process, set by the entry points (never on import).

robotd's matrices are small (at most a few hundred rows per product) and the daemon has
threads of its own: on 2 cores OpenBLAS's second thread only spins. Measured on the square
demo: 31 % less CPU time (user 24.4 -> 16.9 s), and a floor descriptor match
(:func:`robotd.floor.match.local_score`) takes 1.9 ms of CPU instead of 8.2 ms.
"""

from __future__ import annotations

import os

def one_blas_thread() -> bool:
    """Run numpy's BLAS (and every BLAS library loaded later) on one thread, unless the
    environment already sets ``OPENBLAS_NUM_THREADS``; returns whether it limited them.

    The libraries already loaded (numpy's OpenBLAS) are limited with ``threadpoolctl``;
    those loaded later in the process (scipy's and OpenCV's own OpenBLAS builds, through
    scikit-image and the floor code) and child processes read ``OPENBLAS_NUM_THREADS``, set
    here. Called by :func:`robotd.app.cli.main`, the benchmarks and the tests.
    """
    if "OPENBLAS_NUM_THREADS" in os.environ:
        return False
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    import numpy  # noqa: F401  (loads numpy's OpenBLAS, so that the limit reaches it)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    return True
