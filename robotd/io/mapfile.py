"""The map file on disk: its schema versions, their migrations, and the checks made
before a file is opened for writing (see :mod:`robotd.io.store` for the tables).

Version history:

1. the first schema: ``meta``, ``runs``, ``keyframes``, ``links``, ``calibration``;
2. runs get their epoch (``epoch_unix_ns``: each run has its own clock), keyframes are
   indexed by ``(run_id, stamp_ns)``;
3. the pose graph's results: ``optimized_poses`` (the newest solved pose of each
   keyframe) and ``loop_candidates`` (every loop-closure candidate and its fate);
4. the forward camera's memory: ``forward_images`` (what the detector keeps of
   each forward keyframe: word ids, compact keypoints, descriptors) and ``forward_words``
   (the incremental vocabulary's words, with the image that made each one and whether it
   was purged), so a restarted daemon goes on detecting forward loops against earlier runs;
5. the same tables; forward word ids may be deflated, a word's descriptor left to its
   founder feature's (a version-4 reader would misread them);
6. ``loop_candidates.fate`` may be ``grouped`` (a member of a relocalising group that entered
   the pose graph as one edge); the members' rows of an older map are relabelled so.
"""

from __future__ import annotations

import contextlib
import functools
import os
import sqlite3
from collections.abc import Callable, Mapping
from pathlib import Path

import robotd
from robotd.base.errors import MapStoreError

_SQLITE_MAGIC = b"SQLite format 3\x00"

Migration = Callable[[sqlite3.Connection], None]
"""Brings a database from version ``v - 1`` to ``v`` (the key it is stored under in
:data:`MIGRATIONS`). It runs inside a write transaction that also records the new
version, so a crash leaves the file at the old version or the new one, never between."""


_SCHEMA_V1 = (
    """CREATE TABLE meta (
        key   TEXT PRIMARY KEY,
        value TEXT NOT NULL
    ) WITHOUT ROWID""",
    """CREATE TABLE runs (
        id             INTEGER PRIMARY KEY AUTOINCREMENT,
        started_ns     INTEGER NOT NULL,
        ended_ns       INTEGER,
        config         TEXT NOT NULL,
        robotd_version TEXT NOT NULL,
        notes          TEXT NOT NULL DEFAULT ''
    )""",
    # AUTOINCREMENT: an id is never reused, so ids exported to g2o/TUM files or written
    # in logs keep naming the same keyframe for the life of the map.
    """CREATE TABLE keyframes (
        id              INTEGER PRIMARY KEY AUTOINCREMENT,
        run_id          INTEGER NOT NULL REFERENCES runs(id),
        stamp_ns        INTEGER NOT NULL,
        x_m             REAL NOT NULL,
        y_m             REAL NOT NULL,
        yaw_rad         REAL NOT NULL,
        covariance      BLOB NOT NULL CHECK (length(covariance) = 72),
        image           BLOB,
        image_width     INTEGER,
        image_height    INTEGER,
        descriptor      BLOB,
        descriptor_mode INTEGER,
        CHECK ((image IS NULL) = (image_width IS NULL)
               AND (image IS NULL) = (image_height IS NULL)),
        CHECK ((descriptor IS NULL) = (descriptor_mode IS NULL))
    )""",
    "CREATE INDEX keyframes_by_run ON keyframes(run_id, id)",
    """CREATE TABLE links (
        id          INTEGER PRIMARY KEY AUTOINCREMENT,
        kind        TEXT NOT NULL CHECK (kind IN ('odometry', 'loop')),
        from_id     INTEGER NOT NULL REFERENCES keyframes(id),
        to_id       INTEGER NOT NULL REFERENCES keyframes(id),
        dx_m        REAL NOT NULL,
        dy_m        REAL NOT NULL,
        dyaw_rad    REAL NOT NULL,
        information BLOB NOT NULL CHECK (length(information) = 72)
    )""",
    "CREATE INDEX links_by_from ON links(from_id)",
    "CREATE INDEX links_by_to ON links(to_id)",
    """CREATE TABLE calibration (
        id         INTEGER PRIMARY KEY AUTOINCREMENT,
        name       TEXT NOT NULL,
        created_ns INTEGER NOT NULL,
        content    TEXT NOT NULL
    )""",
    "CREATE INDEX calibration_by_name ON calibration(name, id)",
)


def _migrate_0_to_1(conn: sqlite3.Connection) -> None:
    """Version 1, the first schema: create every table on an empty database.

    Statements run one by one with ``execute``: ``executescript`` would commit the
    enclosing migration transaction first.
    """
    for statement in _SCHEMA_V1:
        conn.execute(statement)


def _migrate_1_to_2(conn: sqlite3.Connection) -> None:
    """Version 2: runs get their epoch (``epoch_unix_ns``, NULL for the runs before), and
    keyframes are indexed by run and stamp, the key of "recent" in the floor detector."""
    conn.execute("ALTER TABLE runs ADD COLUMN epoch_unix_ns INTEGER")
    conn.execute("CREATE INDEX keyframes_by_run_stamp ON keyframes(run_id, stamp_ns)")


def _migrate_2_to_3(conn: sqlite3.Connection) -> None:
    """Version 3: ``optimized_poses`` (one row per keyframe, replaced by each new solution)
    and ``loop_candidates`` (one row per candidate considered, with what became of it).
    The fates are spelled out here, not taken from the store: a released step never
    changes."""
    conn.execute(
        """CREATE TABLE optimized_poses (
            keyframe_id    INTEGER PRIMARY KEY REFERENCES keyframes(id),
            x_m            REAL NOT NULL,
            y_m            REAL NOT NULL,
            yaw_rad        REAL NOT NULL,
            solved_unix_ns INTEGER NOT NULL
        )"""
    )
    conn.execute(
        """CREATE TABLE loop_candidates (
            id           INTEGER PRIMARY KEY AUTOINCREMENT,
            query_id     INTEGER NOT NULL REFERENCES keyframes(id),
            candidate_id INTEGER NOT NULL REFERENCES keyframes(id),
            score        REAL NOT NULL,
            fate         TEXT NOT NULL CHECK (fate IN ('accepted', 'below_threshold',
                             'failed_gate', 'no_transform', 'down_weighted')),
            detail       TEXT NOT NULL DEFAULT ''
        )"""
    )
    conn.execute("CREATE INDEX loop_candidates_by_query ON loop_candidates(query_id)")


def _migrate_3_to_4(conn: sqlite3.Connection) -> None:
    """Version 4: the forward camera's memory. ``forward_images``: one row per forward
    keyframe (``image_id``, the detector's image number, in arrival order over all runs;
    ``kind`` of features; ``words`` uint32, ``keypoints`` uint16 pairs in 1/16 px,
    ``descriptors`` as extracted, all little-endian). ``forward_words``: one row per word
    (``descriptor``, ``born_image``, ``purged`` = 1 once it left the search, its descriptor
    then emptied). The inverted
    index and the Bayes filter are rebuilt from these at start (the filter starts at "no
    loop", as at any start)."""
    conn.execute(
        """CREATE TABLE forward_images (
            image_id     INTEGER PRIMARY KEY,
            keyframe_id  INTEGER NOT NULL UNIQUE REFERENCES keyframes(id),
            kind         TEXT NOT NULL CHECK (kind IN ('orb', 'sift')),
            image_width  INTEGER NOT NULL,
            image_height INTEGER NOT NULL,
            words        BLOB NOT NULL,
            keypoints    BLOB NOT NULL,
            descriptors  BLOB NOT NULL
        )"""
    )
    conn.execute(
        """CREATE TABLE forward_words (
            id         INTEGER PRIMARY KEY,
            kind       TEXT NOT NULL CHECK (kind IN ('orb', 'sift')),
            descriptor BLOB NOT NULL,
            born_image INTEGER NOT NULL,
            purged     INTEGER NOT NULL DEFAULT 0 CHECK (purged IN (0, 1))
        )"""
    )


def _migrate_4_to_5(conn: sqlite3.Connection) -> None:
    """Version 5: the same tables; two encodings of the forward memory that a version-4
    reader would misread, so that one refuses the file instead. ``forward_images.words``
    may hold the uint32 ids' bytes regrouped by significance and deflated, when shorter
    than the raw ``4 N`` bytes (the value's length tells the two forms apart:
    :func:`robotd.io.store.pack_word_ids`); a ``forward_words`` row that is not purged
    may have an empty ``descriptor``, meaning its founder's (the first feature of image
    ``born_image`` with that word). Rows written before stay as they are and read as
    before."""
    del conn  # no table changes: the version number is the whole step


_GROUP_MEMBER_DETAIL_V5 = ("forward: relocalisation: a member of the relocalising group, which entered "
                          "the graph as one edge")
"""How a version-5 map's row of a relocalising group's member begins its ``detail`` (the gate
wrote it, fate ``failed_gate``, for these members only). Spelled out: a released step never
changes, whatever the gate writes later."""


def _migrate_5_to_6(conn: sqlite3.Connection) -> None:
    """Version 6: ``loop_candidates.fate`` may also be ``grouped``: a member of a relocalising
    group that entered the pose graph as one edge (the gate never judged it). SQLite cannot
    change a CHECK in place, so the table is rebuilt as SQLite's ALTER TABLE page says: the
    new table created, the rows copied with their ids, the old table dropped, the new one
    renamed and its index made again; its AUTOINCREMENT counter is carried over, so an id
    is never reused. Nothing refers to ``loop_candidates``, so the drop breaks no foreign
    key. It all runs in the migration's transaction: a crash leaves version 5 as it was.

    Rows of version 5 whose fate is ``failed_gate`` and whose detail begins with
    :data:`_GROUP_MEMBER_DETAIL_V5` are relabelled ``grouped`` (their detail unchanged): the
    gate wrote that text for those members alone, so the old fate misnamed what became of
    them, and a map's fates then mean one thing whichever version recorded them."""
    conn.execute(
        """CREATE TABLE loop_candidates_v6 (
            id           INTEGER PRIMARY KEY AUTOINCREMENT,
            query_id     INTEGER NOT NULL REFERENCES keyframes(id),
            candidate_id INTEGER NOT NULL REFERENCES keyframes(id),
            score        REAL NOT NULL,
            fate         TEXT NOT NULL CHECK (fate IN ('accepted', 'below_threshold',
                             'failed_gate', 'no_transform', 'down_weighted', 'grouped')),
            detail       TEXT NOT NULL DEFAULT ''
        )"""
    )
    conn.execute(
        """INSERT INTO loop_candidates_v6 (id, query_id, candidate_id, score, fate, detail)
           SELECT id, query_id, candidate_id, score,
                  CASE WHEN fate = 'failed_gate' AND substr(detail, 1, ?) = ? THEN 'grouped'
                       ELSE fate END,
                  detail
           FROM loop_candidates ORDER BY id""",
        (len(_GROUP_MEMBER_DETAIL_V5), _GROUP_MEMBER_DETAIL_V5),
    )
    row = conn.execute("SELECT seq FROM sqlite_sequence WHERE name = 'loop_candidates'").fetchone()
    conn.execute("DROP TABLE loop_candidates")
    conn.execute("ALTER TABLE loop_candidates_v6 RENAME TO loop_candidates")
    conn.execute("CREATE INDEX loop_candidates_by_query ON loop_candidates(query_id)")
    # The copy set the new table's counter (to its largest id, or 0 for no rows); the old
    # one may be higher, or absent (never written): as it was.
    conn.execute("DELETE FROM sqlite_sequence WHERE name = 'loop_candidates'")
    if row is not None:
        conn.execute("INSERT INTO sqlite_sequence (name, seq) VALUES ('loop_candidates', ?)", (row[0],))


MIGRATIONS: Mapping[int, Migration] = {
    1: _migrate_0_to_1,
    2: _migrate_1_to_2,
    3: _migrate_2_to_3,
    4: _migrate_3_to_4,
    5: _migrate_4_to_5,
    6: _migrate_5_to_6,
}
"""Schema migrations keyed by the version each one produces, contiguous from 1.

A new database is "migrated" from version 0 through every step, so creating a map and
upgrading an old one are the same code path. To change the schema, append
``N + 1: _migrate_N_to_N_plus_1``; never edit a released step."""

SCHEMA_VERSION: int = max(MIGRATIONS)
"""The schema version this code writes; a file with a newer version is refused."""



@functools.cache
def expected_schema(version: int) -> Mapping[str, frozenset[str]]:
    """Table name -> column names of a map at schema ``version``, found by running the
    migrations up to it on an empty in-memory database (so it cannot drift from them)."""
    conn = sqlite3.connect(":memory:", isolation_level=None)
    try:
        for v in range(1, version + 1):
            MIGRATIONS[v](conn)
        return _schema_of(conn)
    finally:
        conn.close()


def _schema_of(conn: sqlite3.Connection) -> dict[str, frozenset[str]]:
    tables = [row[0] for row in conn.execute(
        "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'")]
    return {t: frozenset(row[1] for row in conn.execute(f"PRAGMA table_info({_quote(t)})"))
            for t in tables}


def _quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _missing(found: Mapping[str, frozenset[str]], expected: Mapping[str, frozenset[str]]) -> list[str]:
    """What ``expected`` has and ``found`` lacks: ``table`` or ``table.column``."""
    out = []
    for table, columns in sorted(expected.items()):
        if table not in found:
            out.append(table)
        else:
            out.extend(f"{table}.{c}" for c in sorted(columns - found[table]))
    return out


def _writable_dir(path: Path) -> bool:
    return os.access(path.parent, os.W_OK | os.X_OK)


def _sidecars(path: Path) -> tuple[Path, Path]:
    return path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")


def inspect_file(path: Path, target: int) -> int:
    """Check an existing file without writing to it; return its schema version.

    Uses a read-only connection, so SQLite itself cannot modify the database file. A
    read-only connection to a WAL database still creates empty ``-wal``/``-shm`` files
    next to it when they are missing; on rejection those are removed again. In a folder
    it cannot write (a read-only mount), with no ``-wal`` file beside the map, the file is
    read as immutable, which needs no ``-shm``. A file whose tables or columns fall short
    of its schema version (as the migrations make them) is refused: migrating it would
    write to it first.
    """
    try:
        with path.open("rb") as f:
            header = f.read(len(_SQLITE_MAGIC))
    except OSError as exc:
        raise MapStoreError(f"cannot read map file {path}: {exc.strerror or exc}") from None
    if header == b"":
        return 0  # an empty file is an empty database: SQLite treats it so too
    if header != _SQLITE_MAGIC:
        raise MapStoreError(f"map file {path} is not an SQLite database")

    wal, shm = _sidecars(path)
    existed = {wal: wal.exists(), shm: shm.exists()}
    writable_dir = _writable_dir(path)
    uri = path.as_uri() + "?mode=ro"
    if not writable_dir and not existed[wal]:
        uri += "&immutable=1"  # nothing to read from a log, and no -shm can be made
    try:
        try:
            ro = sqlite3.connect(uri, uri=True, isolation_level=None)
        except sqlite3.Error as exc:
            raise MapStoreError(f"cannot open map file {path}: {exc}") from exc
        try:
            problems = [row[0] for row in ro.execute("PRAGMA quick_check(5)").fetchall()]
            if problems != ["ok"]:
                raise MapStoreError(
                    f"map file {path} is damaged (quick_check: {'; '.join(problems)})"
                )
            tables = {
                row[0]
                for row in ro.execute("SELECT name FROM sqlite_master WHERE type = 'table'")
            }
            if not tables:
                return 0
            if "meta" not in tables:
                raise MapStoreError(f"map file {path} is an SQLite database but not a robotd map")
            row = ro.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            try:
                version = int(row[0])
            except (TypeError, ValueError):
                raise MapStoreError(
                    f"map file {path} has no valid schema_version in its meta table"
                ) from None
            found = _schema_of(ro) if 1 <= version <= target else {}
        except sqlite3.Error as exc:
            if not writable_dir:
                raise MapStoreError(
                    f"cannot read map file {path} in the read-only folder {path.parent}: {exc}"
                    " (a map with a write-ahead log needs its -shm file beside it)"
                ) from exc
            raise MapStoreError(f"map file {path} is damaged or unreadable: {exc}") from exc
        finally:
            ro.close()
        if version > target:
            raise MapStoreError(
                f"map file {path} has schema version {version}, newer than the {target}"
                f" this robotd {robotd.__version__} understands; upgrade robotd"
            )
        if version < 1:
            raise MapStoreError(f"map file {path} has an invalid schema version {version}")
        missing = _missing(found, expected_schema(min(version, SCHEMA_VERSION)))
        if missing:
            raise MapStoreError(
                f"map file {path} claims schema version {version} but lacks "
                f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}: not a robotd map,"
                " or a damaged one; left as it is"
            )
        return version
    except MapStoreError:
        _remove_new_sidecars(existed)
        raise


def read_meta(path: Path) -> dict[str, str]:
    """The ``meta`` table of the robotd map at ``path``, read without writing to it.

    Raises :class:`MapStoreError` for what :func:`inspect_file` refuses (not SQLite,
    damaged, not a robotd map, a newer schema), and for an empty or unreadable file.
    """
    path = Path(path).absolute()
    existed = {p: p.exists() for p in _sidecars(path)}
    version = inspect_file(path, SCHEMA_VERSION)
    if version == 0:
        raise MapStoreError(f"map file {path} is empty")
    uri = path.as_uri() + "?mode=ro"
    if not _writable_dir(path) and not existed[_sidecars(path)[0]]:
        uri += "&immutable=1"
    try:
        ro = sqlite3.connect(uri, uri=True, isolation_level=None)
        try:
            return {str(k): str(v) for k, v in ro.execute("SELECT key, value FROM meta")}
        finally:
            ro.close()
    except sqlite3.Error as exc:
        raise MapStoreError(f"map file {path} is damaged or unreadable: {exc}") from exc
    finally:
        _remove_new_sidecars(existed)


def _remove_new_sidecars(existed: Mapping[Path, bool]) -> None:
    """Remove the empty ``-wal``/``-shm`` files our read-only check created."""
    wal, shm = existed
    if existed[wal] or existed[shm]:
        return  # someone else's: leave them alone
    with contextlib.suppress(FileNotFoundError):
        if wal.stat().st_size != 0:
            return
    for sidecar in (wal, shm):
        # none made in a read-only place (unlink says EROFS/EACCES there, not ENOENT)
        with contextlib.suppress(OSError):
            sidecar.unlink()


def migrate(
    conn: sqlite3.Connection, path: Path, migrations: Mapping[int, Migration], target: int
) -> None:
    """Apply ``migrations`` one version at a time until the file is at ``target``.

    Each step and the new ``schema_version`` commit together under ``BEGIN IMMEDIATE``,
    which also stops two processes from migrating the same file at once.
    """
    if sorted(migrations) != list(range(1, target + 1)):
        raise MapStoreError(f"internal: migrations must be numbered 1..{target}")
    while True:
        conn.execute("BEGIN IMMEDIATE")
        try:
            has_meta = conn.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'meta'"
            ).fetchone()
            version = 0
            if has_meta:
                row = conn.execute(
                    "SELECT value FROM meta WHERE key = 'schema_version'"
                ).fetchone()
                version = int(row[0]) if row else 0
            if version > target:  # changed between the inspection and now
                raise MapStoreError(
                    f"map file {path} has schema version {version}, newer than {target}"
                )
            if version == target:
                conn.execute("COMMIT")
                return
            migrations[version + 1](conn)
            conn.execute(
                "INSERT INTO meta(key, value) VALUES ('schema_version', ?)"
                " ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (str(version + 1),),
            )
            if version == 0:
                conn.execute(
                    "INSERT INTO meta(key, value) VALUES ('created_by', ?)",
                    (f"robotd {robotd.__version__}",),
                )
            conn.execute("COMMIT")
        except BaseException:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            raise
