"""robotd: on-robot loop-closure daemon for Turtlebot-class robots.

Nothing is set on import: the command line (:func:`robotd.app.cli.main`) runs BLAS on one
thread (:func:`robotd.base.blas.one_blas_thread`).
"""

__version__ = "0.1.0"
