"""Where robotd's log goes: the journal's native protocol under systemd, stderr elsewhere.

When systemd connects a service's stderr to the journal it sets ``JOURNAL_STREAM`` to
``DEVICE:INODE`` of that stream (``systemd.exec(5)``); a program that finds its own stderr
there may switch to the native protocol. robotd then logs through
:class:`systemd.journal.JournalHandler` (systemd-python), so every line carries its
priority (``journalctl -p warning``), ``SYSLOG_IDENTIFIER=robotd`` and the logger's name
(``LOGGER=``), instead of the text prefix of a plain stream. Anywhere else (a terminal, a
test, a child whose stderr was redirected although it inherited the variable) it logs
to stderr as before. ``INVOCATION_ID`` alone is not enough: a unit may send stderr to a
file or a tty.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from typing import IO

__all__ = ["STREAM_FORMAT", "JOURNAL_FORMAT", "configure_logging", "journal_wanted", "make_handler"]

STREAM_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
"""Lines on stderr: time, level and logger, which the journal's fields replace."""

JOURNAL_FORMAT = "%(name)s: %(message)s"
"""MESSAGE= in the journal (time and priority are fields of their own there)."""

SYSLOG_IDENTIFIER = "robotd"


def journal_wanted(env: Mapping[str, str], stream: IO[str] | None) -> bool:
    """True when ``env["JOURNAL_STREAM"]`` names ``stream``'s file (device and inode), i.e.
    systemd connected it to the journal. False when the variable is absent or malformed,
    or ``stream`` has no file descriptor or is another file."""
    value = env.get("JOURNAL_STREAM", "")
    dev_ino = value.split(":")
    if len(dev_ino) != 2:
        return False
    try:
        dev, ino = int(dev_ino[0]), int(dev_ino[1])
        st = os.fstat(stream.fileno()) if stream is not None else None
    except (ValueError, OSError, AttributeError):  # AttributeError/OSError: no real fd
        return False
    return st is not None and (st.st_dev, st.st_ino) == (dev, ino)


def make_handler(env: Mapping[str, str], stream: IO[str] | None) -> logging.Handler:
    """A :class:`~systemd.journal.JournalHandler` when :func:`journal_wanted`, and
    systemd-python imports; a :class:`logging.StreamHandler` on ``stream`` otherwise."""
    if journal_wanted(env, stream):
        try:
            from systemd.journal import JournalHandler
        except ImportError:
            pass  # the stream still reaches the journal, as plain text
        else:
            handler: logging.Handler = JournalHandler(SYSLOG_IDENTIFIER=SYSLOG_IDENTIFIER)
            handler.setFormatter(logging.Formatter(JOURNAL_FORMAT))
            return handler
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter(STREAM_FORMAT))
    return handler


def configure_logging(level: str, env: Mapping[str, str] | None = None,
                      stream: IO[str] | None = None) -> logging.Handler | None:
    """Send the root logger to the journal or ``stream`` (default stderr) at ``level``
    (``"info"``, ...); returns the handler installed. A root logger that already has
    handlers keeps them and its level (as with :func:`logging.basicConfig`); None is
    returned then."""
    root = logging.getLogger()
    if root.handlers:
        return None
    root.setLevel(level.upper())
    handler = make_handler(os.environ if env is None else env,
                           sys.stderr if stream is None else stream)
    root.addHandler(handler)
    return handler
