"""robotd: on-robot loop-closure daemon for Turtlebot-class robots."""

import os

# One BLAS thread unless the environment says otherwise, set before numpy loads OpenBLAS.
# robotd's matrices are small (at most a few hundred rows per product) and the daemon has
# threads of its own: on 2 cores OpenBLAS's second thread only spins. Measured on the
# square demo: 31 % less CPU time (user 24.4 -> 16.9 s), and a floor descriptor match
# (robotd.floor.match.local_score) takes 1.9 ms of CPU instead of 8.2 ms.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
