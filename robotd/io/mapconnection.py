"""Opening, locking, migrating and closing a map file, and its transactions.

The durability, thread and inspection rules are :mod:`robotd.io.store`'s docstring's;
this module holds the connection they apply to (:class:`MapConnection`), the base of
:class:`~robotd.io.store.MapStore`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sqlite3
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Self

from robotd.base.clock import Clock, MonotonicClock
from robotd.base.errors import MapStoreError
from robotd.io.mapfile import MIGRATIONS, inspect_file, migrate
from robotd.io.maplock import acquire_map_lock, live_holder, release_map_lock

__all__ = ["MapConnection"]

_log = logging.getLogger("robotd.io.store")  # one logger for the map store's messages


class MapConnection:
    """The SQLite connection of a map file, opened safely: the file inspected read-only
    first, migrated, locked for its one writer; one transaction per write. The tables'
    methods are :class:`~robotd.io.store.MapStore`'s, which is this class with them.

    Create it with :meth:`open`. A context manager; :meth:`close` may be called more than
    once. Not shareable between threads (see :mod:`robotd.io.store`).
    """

    def __init__(
        self,
        conn: sqlite3.Connection,
        path: Path,
        *,
        image_codec: Literal["jpeg", "png"],
        jpeg_quality: int,
        clock: Clock,
    ) -> None:
        """Use :meth:`open`; this only wraps an already validated connection."""
        self._conn: sqlite3.Connection | None = conn
        self._path = path
        self._clock = clock
        self._image_codec = image_codec
        self._jpeg_quality = int(jpeg_quality)
        self._holds_lock = False  # set by open() for a writable store

    # -- opening and closing -------------------------------------------------------

    @classmethod
    def open(
        cls,
        path: str | Path,
        create: bool = True,
        *,
        image_codec: Literal["jpeg", "png"] = "jpeg",
        jpeg_quality: int = 90,
        synchronous: Literal["NORMAL", "FULL"] = "FULL",
        clock: Clock | None = None,
        read_only: bool = False,
    ) -> Self:
        """Open the map at ``path``, creating it if it does not exist and ``create``.

        ``read_only`` opens an existing map of the current schema for reading only, never
        writing to the file (a map on a read-only mount can be read and exported); its
        write methods raise :class:`MapStoreError`. Opened for writing, a map whose file
        or folder cannot be written (the map writes its ``-wal``/``-shm`` files beside it)
        is refused with a MapStoreError saying so, after the read-only inspection.

        ``image_codec`` encodes keyframe images added through this store (``"png"`` is
        lossless, ``"jpeg"`` at ``jpeg_quality`` 0..100 is several times smaller); images
        of either codec are read back regardless. ``synchronous`` trades commit latency
        for power-cut durability (module docstring). ``clock`` (default: the host
        monotonic clock, the time base of keyframe stamps) supplies the times that
        :meth:`begin_run`, :meth:`end_run` and :meth:`put_calibration` are not given.

        Raises :class:`MapStoreError` naming ``path`` if the file is missing (and not
        ``create``), is not an SQLite database, fails ``PRAGMA quick_check``, is an
        SQLite database of something else, or has a schema newer than
        :data:`SCHEMA_VERSION`; in all these cases the file is not modified. The check
        reads the whole file once (40 ms for 100 MB in the page cache; from a cold SD
        card it is bound by the card's read speed, a few seconds).
        """
        if image_codec not in ("jpeg", "png"):
            raise ValueError(f"image_codec must be 'jpeg' or 'png', got {image_codec!r}")
        if not 0 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in 0..100, got {jpeg_quality}")
        if synchronous not in ("NORMAL", "FULL"):
            raise ValueError(f"synchronous must be 'NORMAL' or 'FULL', got {synchronous!r}")
        path = Path(path).absolute()
        if path.parent.is_dir() and not os.access(path.parent, os.X_OK):
            raise MapStoreError(f"map file {path}: cannot enter its folder {path.parent} "
                                "(permission denied: run as the user the map belongs to)")
        migrations = MIGRATIONS
        target = max(migrations)

        if path.exists():
            if not path.is_file():
                raise MapStoreError(f"map file {path} is not a regular file")
            if path.stat().st_size == 0 and (not create or read_only):
                _refuse_if_being_created(path)
                raise MapStoreError(f"map file {path} is empty")
            version = inspect_file(path, target)
        elif create and not read_only:
            if not path.parent.is_dir():
                raise MapStoreError(
                    f"cannot create map file {path}: directory {path.parent} does not exist"
                )
            version = 0
        else:
            raise MapStoreError(f"map file {path} does not exist")
        if read_only:
            return cls._open_read_only(path, version, target, image_codec=image_codec,
                                       jpeg_quality=jpeg_quality, clock=clock)
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise MapStoreError(
                f"{'map file' if version else 'cannot create map file'} {path}: its folder"
                f" {path.parent} is read-only (the map writes its -wal and -shm files beside it)"
            )
        if version and not os.access(path, os.W_OK):
            raise MapStoreError(f"map file {path} is read-only")

        acquire_map_lock(path)  # one writer per map (robotd.io.maplock); refused at once
        try:
            store = cls._open_writable(path, version, target, migrations, synchronous=synchronous,
                                       image_codec=image_codec, jpeg_quality=jpeg_quality,
                                       clock=clock)
        except BaseException:
            release_map_lock(path)
            raise
        store._holds_lock = True
        return store

    @classmethod
    def _open_writable(cls, path: Path, version: int, target: int,
                       migrations: Mapping[int, Callable[[sqlite3.Connection], None]], *,
                       synchronous: str, image_codec: Literal["jpeg", "png"], jpeg_quality: int,
                       clock: Clock | None) -> Self:
        try:
            conn = sqlite3.connect(
                path.as_uri() + "?mode=rwc",
                uri=True,
                isolation_level=None,  # no implicit transactions: we BEGIN/COMMIT ourselves
                check_same_thread=True,
                timeout=5.0,  # wait this long (s) for another connection's write lock
            )
        except sqlite3.Error as exc:
            raise MapStoreError(f"cannot open map file {path}: {exc}") from exc
        try:
            mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise MapStoreError(
                    f"map file {path}: the file system does not support SQLite's WAL mode"
                    f" (journal_mode is {mode!r})"
                )
            conn.execute(f"PRAGMA synchronous={synchronous}")
            conn.execute("PRAGMA foreign_keys=ON")
            migrate(conn, path, migrations, target)
        except sqlite3.Error as exc:
            conn.close()
            raise MapStoreError(f"cannot open map file {path}: {exc}") from exc
        except BaseException:
            conn.close()
            raise
        if 0 < version < target:
            _log.info("map %s migrated from schema version %d to %d", path, version, target)
        _log.info("map store %s open (schema version %d)", path, target)
        return cls(
            conn,
            path,
            image_codec=image_codec,
            jpeg_quality=jpeg_quality,
            clock=MonotonicClock() if clock is None else clock,
        )

    @classmethod
    def _open_read_only(cls, path: Path, version: int, target: int, *,
                        image_codec: Literal["jpeg", "png"], jpeg_quality: int,
                        clock: Clock | None) -> Self:
        if version == 0:
            _refuse_if_being_created(path)
        if version != target:
            raise MapStoreError(
                f"map file {path} has schema version {version}; open it once for writing to"
                f" upgrade it to {target} before reading it read-only"
            )
        uri = path.as_uri() + "?mode=ro"
        wal = path.with_name(path.name + "-wal")
        if not os.access(path.parent, os.W_OK | os.X_OK) and not wal.exists():
            uri += "&immutable=1"  # see mapfile.inspect_file
        try:
            conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=True,
                                   timeout=5.0)
        except sqlite3.Error as exc:
            raise MapStoreError(f"cannot open map file {path}: {exc}") from exc
        _log.info("map store %s open read-only (schema version %d)", path, version)
        return cls(conn, path, image_codec=image_codec, jpeg_quality=jpeg_quality,
                   clock=MonotonicClock() if clock is None else clock)

    @property
    def path(self) -> Path:
        """Absolute path of the map file."""
        return self._path

    @property
    def closed(self) -> bool:
        """True after :meth:`close`."""
        return self._conn is None

    def close(self) -> None:
        """Close the file (the last connection to close checkpoints and removes the WAL).

        Safe to call more than once.
        """
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.execute("PRAGMA optimize")
            except sqlite3.Error as exc:  # an optimisation hint: never fail close on it
                _log.debug("PRAGMA optimize failed on %s: %s", self._path, exc)
            conn.close()
            if self._holds_lock:
                self._holds_lock = False
                release_map_lock(self._path)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- internals -----------------------------------------------------------------

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise MapStoreError(f"map store {self._path} is closed")
        return self._conn

    @contextlib.contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One write transaction; SQLite errors become MapStoreError, constraint
        violations (unknown ids) ValueError."""
        conn = self._connection()
        try:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")
        except sqlite3.ProgrammingError:
            raise  # misuse (closed cursor, wrong thread): a bug, not a map problem
        except sqlite3.IntegrityError as exc:
            raise ValueError(f"map {self._path}: {exc}") from exc
        except sqlite3.Error as exc:
            raise MapStoreError(f"map {self._path}: write failed: {exc}") from exc

    def _read(self, sql: str, params: Sequence[object] = ()) -> list[tuple[Any, ...]]:
        """The rows of ``sql`` (SQLite's values: their types are the columns')."""
        try:
            return self._connection().execute(sql, params).fetchall()
        except sqlite3.ProgrammingError:
            raise  # misuse (wrong thread): a bug, not a map problem
        except sqlite3.Error as exc:
            raise MapStoreError(f"map {self._path}: read failed: {exc}") from exc

    # -- meta ----------------------------------------------------------------------

    @property
    def schema_version(self) -> int:
        """The schema version stored in the file."""
        value = self.get_meta("schema_version")
        assert value is not None  # written by every migration
        return int(value)

    def get_meta(self, key: str) -> str | None:
        """Value stored under ``key`` in ``meta``, None if absent."""
        rows = self._read("SELECT value FROM meta WHERE key = ?", (key,))
        return rows[0][0] if rows else None

    def set_meta(self, key: str, value: str) -> None:
        """Store ``value`` under ``key``; ``schema_version`` is reserved."""
        if key == "schema_version":
            raise ValueError("schema_version is managed by the migrations")
        with self._write() as conn:
            conn.execute(
                "INSERT INTO meta(key, value) VALUES (?, ?)"
                " ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (key, str(value)),
            )


def _refuse_if_being_created(path: Path) -> None:
    """A reader that finds a map without its schema while a live writer holds the lock has
    met a map being created, not an empty or old one: say so."""
    who = live_holder(path)
    if who:
        raise MapStoreError(f"map file {path} is being created by another process ({who}); "
                            "read it once that process has started")
