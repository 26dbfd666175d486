"""One writer per map: an advisory lock held for the whole run, in a file beside the map.

``MAP.lock`` (``map.sqlite.lock`` beside ``map.sqlite``) is locked with ``flock`` by the
process that writes the map, for as long as it writes, and holds one line naming that
process (its PID and command line). A second writer is refused at once with a
:class:`~robotd.base.errors.MapStoreError` that names the map and the process holding it;
it changes nothing, the lock file included. Readers (``graph export``, read-only opens)
take no lock.

The kernel drops the lock when its process dies (SIGKILL, power cut), so a stale lock file
never blocks the next run; the holder removes the file when it lets go. Within one process
the lock is re-entrant (the demo holds it around the daemon, which opens the map again);
:func:`hold_map_lock` counts the holders and releases on the last.

Why not SQLite's own locking: SQLite locks one transaction at a time, so two daemons
interleave their transactions into one map (the second marking the live first run as
killed, both appending keyframes). Why not ``fcntl`` record locks on the map itself: SQLite
uses them on that file, and closing any descriptor of a file drops every record lock the
process holds on it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shlex
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from robotd.base.errors import MapStoreError

LOCK_SUFFIX = ".lock"
"""The lock file's name is the map's with this suffix."""


def lock_path(map_path: Path) -> Path:
    """The lock file of the map at ``map_path``."""
    return map_path.with_name(map_path.name + LOCK_SUFFIX)


@dataclass
class _Held:
    fd: int
    path: Path
    count: int


_held: dict[str, _Held] = {}
_held_guard = threading.Lock()


def _key(map_path: Path) -> str:
    return os.path.realpath(map_path)


def holder_of(map_path: Path) -> str:
    """The line the lock file holds (PID and command of the writer), or ``""``."""
    try:
        with open(lock_path(map_path), "rb") as f:
            return f.read(4096).decode("utf-8", "backslashreplace").strip()
    except OSError:
        return ""


def live_holder(map_path: Path) -> str:
    """The lock file's line when the process it names is alive, else ``""``: for a reader to
    tell a map being created from an empty or damaged one, without touching the lock (a
    reader taking it, even shared for a moment, could make a starting writer refused)."""
    line = holder_of(map_path)
    parts = line.split(":", 1)[0].split()
    if len(parts) != 2 or parts[0] != "pid" or not parts[1].isdigit():
        return ""
    try:
        os.kill(int(parts[1]), 0)
    except ProcessLookupError:
        return ""
    except OSError:
        pass  # alive, owned by another user
    return line


def _acquire(map_path: Path) -> int:
    path = lock_path(map_path)
    folder = map_path.parent
    if not folder.is_dir():
        raise MapStoreError(f"cannot create map file {map_path}: directory {folder} does not exist")
    if not os.access(folder, os.X_OK):
        raise MapStoreError(f"map file {map_path}: cannot enter its folder {folder} "
                            "(permission denied: run as the user the map belongs to)")
    if not os.access(folder, os.W_OK):
        raise MapStoreError(f"map file {map_path}: its folder {folder} is not writable (read-only "
                            "file system or permissions; the map writes its lock, -wal and -shm "
                            "files beside it)")
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise MapStoreError(f"map {map_path}: cannot create its lock file {path}: "
                                f"{exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise MapStoreError(f"map {map_path}: cannot lock {path}: {exc.strerror or exc}") from None
            who = holder_of(map_path) or "a process that has not written its name yet"
            raise MapStoreError(f"map {map_path} is being written by another process ({who}); "
                                "one writer per map: stop it first, or use another map") from None
        # The previous holder may have removed the file between our open and our lock: then
        # we hold a lock on a file nobody else will see. Start again on the file that is there.
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    line = f"pid {os.getpid()}: {shlex.join(sys.argv) if sys.argv and sys.argv[0] else 'python'}\n"
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, line.encode("utf-8", "backslashreplace"), 0)
    except OSError:
        pass  # the lock holds without the name; a refused writer then cannot say who has it
    return fd


def acquire_map_lock(map_path: Path) -> None:
    """Take (or, in this process, count once more) the write lock of the map at
    ``map_path``; :class:`MapStoreError` when another process holds it."""
    key = _key(map_path)
    with _held_guard:
        held = _held.get(key)
        if held is not None:
            held.count += 1
            return
        _held[key] = _Held(_acquire(map_path), lock_path(map_path), 1)


def release_map_lock(map_path: Path) -> None:
    """Count one holder less; the last removes the lock file and lets go of the lock."""
    key = _key(map_path)
    with _held_guard:
        held = _held.get(key)
        if held is None:
            return
        held.count -= 1
        if held.count > 0:
            return
        del _held[key]
        with contextlib.suppress(OSError):
            # Remove while still locked, so no one else can take the lock on this file.
            if os.fstat(held.fd).st_ino == os.stat(held.path).st_ino:
                os.unlink(held.path)
        os.close(held.fd)


def holds_map_lock(map_path: Path) -> bool:
    """True while this process holds the map's lock."""
    with _held_guard:
        return _key(map_path) in _held


@contextlib.contextmanager
def hold_map_lock(map_path: Path) -> Iterator[None]:
    """The map's write lock for the ``with`` block (see :func:`acquire_map_lock`)."""
    acquire_map_lock(map_path)
    try:
        yield
    finally:
        release_map_lock(map_path)
