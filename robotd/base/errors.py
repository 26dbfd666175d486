"""The exception tree: one root, one subclass per area.

A known error ends the CLI with one clear line and a non-zero exit code.
"""


class RobotdError(Exception):
    """Root of every error robotd raises on purpose."""


class ConfigError(RobotdError):
    """A configuration file is missing, unreadable, or has an unknown key or a bad value."""


class DriverError(RobotdError):
    """A hardware device (serial port, camera, CAN bus) cannot be opened or has vanished."""


class RecordingError(RobotdError):
    """A recording cannot be written (disk full, I/O error). Not a :class:`DriverError`: the
    device is fine and reopening it would not help, so the run stops rather than go on
    without its recording."""


class CalibrationError(RobotdError):
    """A calibration is missing, invalid, or cannot be computed from the given data."""


class MapStoreError(RobotdError):
    """The map file cannot be opened, is damaged, or has an incompatible schema."""


class DescriptorError(RobotdError):
    """Descriptor bytes are corrupt, truncated, of an unknown version, or of a bad mode."""


class GraphError(RobotdError):
    """A pose graph or a pose-graph file is malformed: a missing vertex, a non-positive-definite
    information matrix, a truncated or garbled line, a duplicate vertex."""


class SequenceError(RobotdError):
    """An image sequence or its ground-truth matrix cannot be read, or they do not fit
    together (a missing folder, an unreadable image, a matrix of the wrong size)."""


class OutputError(RobotdError):
    """An output file the user named cannot or must not be written: it exists (without
    ``--force``), it is one of the inputs, it is a folder, or the disk is full or read-only.
    The previous file, if any, is left as it was."""
