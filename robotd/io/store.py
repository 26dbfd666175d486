"""The map store: everything durable lives in one SQLite file in WAL mode.

Tables (schema version :data:`SCHEMA_VERSION`):

``meta``
    ``key TEXT -> value TEXT``; ``schema_version`` is the one the code relies on.
``runs``
    One row per daemon run: ``started_ns``/``ended_ns`` (the run's own clock), the full
    TOML configuration text, the robotd version and free-form notes; since version 2 also
    the run's epoch, ``epoch_unix_ns`` (the host's wall clock, Unix time, when the run
    started; NULL for runs recorded before version 2). Each run has its own time base:
    keyframe stamps are ``CLOCK_MONOTONIC`` on the robot, which restarts at every boot, or
    the virtual robot's time from 0, so stamps of two runs are never compared. Within a
    run they grow with time; across runs the keyframe ids (never reused) give the order.
``keyframes``
    Pose ``x_m, y_m, yaw_rad`` (map frame, REP-103), ``stamp_ns``, the 3x3 pose
    covariance as 9 little-endian float64 (row-major), the keyframe image encoded (JPEG or
    PNG) with its width and height, and the compact descriptor bytes with their mode
    (both NULL until the descriptor is computed).
``links``
    Pose-graph edges: ``kind`` ``'odometry'`` or ``'loop'``, the relative transform of
    ``to_id`` expressed in the frame of ``from_id`` (``dx_m, dy_m, dyaw_rad``) and its 3x3
    information matrix (9 little-endian float64, row-major).
``calibration``
    Named text documents (TOML) with their creation time; every version is kept and the
    newest one is returned.
``optimized_poses`` (since version 3)
    The newest pose-graph solution per keyframe: ``x_m, y_m, yaw_rad`` (map frame) and
    ``solved_unix_ns`` (host wall clock, Unix time, when the graph was solved).
``loop_candidates`` (since version 3)
    Every loop-closure candidate considered: ``query_id``, ``candidate_id`` (keyframes),
    the local ``score``, its ``fate`` (one of :data:`LOOP_CANDIDATE_FATES`) and a free
    ``detail`` text (e.g. the chi-square value, the optimiser's weight). Since version 6
    the fate may be ``grouped`` (the table rebuilt with it in its CHECK).

``forward_images``, ``forward_words`` (since version 4)
    The forward camera's memory (:meth:`MapStore.add_forward_image`,
    :meth:`MapStore.forward_memory`): per forward keyframe its word ids, compact
    keypoints and descriptors; per word its descriptor, the image that made it and
    whether it was purged. One image and its new words are one transaction. Since
    version 5 the word ids may be deflated and a word's descriptor may be left to its
    founder feature's (:func:`pack_word_ids`, :meth:`MapStore.add_forward_image`).

Durability. Every write is its own transaction (``BEGIN IMMEDIATE`` ... ``COMMIT``), so
a crash never leaves half a keyframe. The journal is a write-ahead log with
``synchronous=FULL`` by default: every commit is synced to disk, so a power cut loses at
most the keyframe being written (DESIGN.md, "Map store"), at one ``fsync`` per keyframe
(0.38 ms here against 0.19 ms with NORMAL; a few keyframes a second at most). With
``synchronous="NORMAL"`` the WAL is synced only at checkpoints: a *process* crash still
loses nothing committed, but a power cut may roll back the commits since the last
checkpoint (never corrupting the file); tools that write many rows at once may choose it.

Threads. A :class:`MapStore` belongs to the thread that opened it: the connection is
made with ``check_same_thread=True``, so use from another thread raises
:class:`sqlite3.ProgrammingError` instead of corrupting state. The daemon writes from one
thread; a reader elsewhere (another thread, the CLI while the daemon runs) opens its own
:class:`MapStore` on the same file, which WAL allows alongside the single writer.

Opening an existing file first inspects it through a *read-only* connection (header
magic, ``PRAGMA quick_check``, schema version); a file that is not SQLite, is damaged, is
not a robotd map, or has a newer schema raises :class:`~robotd.base.errors.MapStoreError` and
is left byte-for-byte untouched. An older schema is upgraded by :data:`MIGRATIONS`.
"""

from __future__ import annotations

import logging
import math
import time
import zlib
from collections.abc import Iterator, Sequence
from typing import Any, Literal

import cv2
import numpy as np

import robotd
from robotd.base.errors import MapStoreError
from robotd.base.messages import LoopFate
from robotd.io.mapconnection import MapConnection
from robotd.io.mapfile import MIGRATIONS, SCHEMA_VERSION
from robotd.io.maprecords import (
    UNCLEAN_END_NOTE,
    KeyframeRecord,
    LinkRecord,
    LoopCandidateRecord,
    RunRecord,
    blob_to_matrix,
    candidate_record,
    check_descriptor,
    finite_triple,
    matrix_to_blob,
)

__all__ = [
    "LOOP_CANDIDATE_FATES", "MIGRATIONS", "SCHEMA_VERSION", "UNCLEAN_END_NOTE", "KeyframeRecord",
    "LinkRecord",
    "LoopCandidateRecord", "MapStore", "RunRecord",
]

_log = logging.getLogger(__name__)

_LINK_KINDS = ("odometry", "loop")
_PAGE_ROWS = 256  # rows fetched per query when iterating (see MapStore.keyframes)
LOOP_CANDIDATE_FATES: tuple[LoopFate, ...] = tuple(LoopFate)
"""The allowed ``loop_candidates.fate`` values (the table's CHECK constraint, spelled out
in :mod:`robotd.io.mapfile`)."""
_FATE_TEXTS = ", ".join(LOOP_CANDIDATE_FATES)


class MapStore(MapConnection):
    """The robot's map in one SQLite file; see the module docstring for the layout.

    Create it with :meth:`MapStore.open` (:class:`~robotd.io.mapconnection.MapConnection`:
    opening, locking, migrating, closing). A context manager; :meth:`close` may be called
    more than once. Not shareable between threads (see the module docstring).
    """

    # -- the map frame -------------------------------------------------------------

    MAP_FRAME_RUNS_KEY = "map_frame_runs"
    """``meta`` key: the runs whose optimised poses are in the map frame, comma-separated
    ids (the run that started the map, and every run that relocalised against it)."""

    def map_frame_runs(self) -> set[int]:
        """The runs whose optimised poses are in the map frame. A map written before this
        was recorded counts its first run with keyframes (the others ran each in a frame of
        its own)."""
        value = self.get_meta(self.MAP_FRAME_RUNS_KEY)
        if value is None:
            rows = self._read("SELECT MIN(run_id) FROM keyframes")
            return {int(rows[0][0])} if rows and rows[0][0] is not None else set()
        try:
            return {int(v) for v in value.split(",") if v.strip()}
        except ValueError:
            _log.warning("map %s: meta %s is not a list of run ids (%r); no run counts as in the "
                        "map frame", self._path, self.MAP_FRAME_RUNS_KEY, value)
            return set()

    def add_map_frame_run(self, run_id: int) -> None:
        """Record that run ``run_id``'s optimised poses are (from now on) in the map frame."""
        runs = self.map_frame_runs() | {int(run_id)}
        self.set_meta(self.MAP_FRAME_RUNS_KEY, ",".join(str(r) for r in sorted(runs)))

    def map_frame_poses(self, exclude_run: int | None = None) -> dict[int, tuple[np.ndarray, int]]:
        """Keyframe id -> ``(optimised pose (3,), run id)`` of every keyframe of a map-frame
        run (:meth:`map_frame_runs`) that has an optimised pose, except those of
        ``exclude_run``."""
        runs = self.map_frame_runs() - ({int(exclude_run)} if exclude_run is not None else set())
        if not runs:
            return {}
        marks = ",".join("?" * len(runs))
        rows = self._read(
            "SELECT o.keyframe_id, o.x_m, o.y_m, o.yaw_rad, k.run_id FROM optimized_poses o"
            f" JOIN keyframes k ON k.id = o.keyframe_id WHERE k.run_id IN ({marks})"
            " ORDER BY o.keyframe_id", tuple(sorted(runs)))
        return {int(r[0]): (np.array(r[1:4], dtype=np.float64), int(r[4])) for r in rows}

    # -- runs ----------------------------------------------------------------------

    def begin_run(
        self,
        config_text: str,
        started_ns: int | None = None,
        *,
        notes: str = "",
        robotd_version: str = robotd.__version__,
        epoch_unix_ns: int | None = None,
    ) -> int:
        """Record the start of a run at ``started_ns`` (default: the store's clock now)
        with the full configuration text it runs with; returns the run id.
        ``epoch_unix_ns`` (default: the host's wall clock now) dates the run for people
        and orders runs whose own clocks restarted."""
        if started_ns is None:
            started_ns = self._clock.now_ns()
        if epoch_unix_ns is None:
            epoch_unix_ns = time.time_ns()
        with self._write() as conn:
            cur = conn.execute(
                "INSERT INTO runs(started_ns, config, robotd_version, notes, epoch_unix_ns)"
                " VALUES (?, ?, ?, ?, ?)",
                (int(started_ns), str(config_text), str(robotd_version), str(notes), int(epoch_unix_ns)),
            )
        assert cur.lastrowid is not None  # an INSERT's
        run_id = cur.lastrowid
        _log.info("map %s: run %d started", self._path, run_id)
        return run_id

    def end_run(self, run_id: int, ended_ns: int | None = None) -> None:
        """Record that run ``run_id`` ended at ``ended_ns`` (default: the store's clock
        now); KeyError if there is no such run."""
        if ended_ns is None:
            ended_ns = self._clock.now_ns()
        with self._write() as conn:
            cur = conn.execute(
                "UPDATE runs SET ended_ns = ? WHERE id = ?", (int(ended_ns), int(run_id))
            )
            if cur.rowcount != 1:
                raise KeyError(f"no run {run_id} in map {self._path}")

    def mark_unfinished_runs(self) -> list[tuple[RunRecord, int]]:
        """Mark the runs that never recorded their end (``ended_ns`` NULL: the process was
        killed, or the power cut) as ended at their last keyframe's stamp (their start
        when they have none), with a note beginning :data:`UNCLEAN_END_NOTE`; nothing else
        changes. Returns each such run as it was found, with its number of keyframes.

        Call it when a run starts: one daemon writes a map at a time, so a run without an
        end is not running any more.
        """
        found = [RunRecord(*row) for row in self._read(
            "SELECT id, started_ns, ended_ns, config, robotd_version, notes, epoch_unix_ns"
            " FROM runs WHERE ended_ns IS NULL ORDER BY id")]
        out = []
        for run in found:
            last, count = self._read(
                "SELECT max(stamp_ns), count(*) FROM keyframes WHERE run_id = ?", (run.id,))[0]
            ended = run.started_ns if last is None else max(int(last), run.started_ns)
            note = (f"{UNCLEAN_END_NOTE}: no end was recorded (killed or power cut?); ended_ns is "
                    f"its last keyframe's stamp, set when the next run started")
            with self._write() as conn:
                conn.execute(
                    "UPDATE runs SET ended_ns = ?, notes = CASE WHEN notes = '' THEN ?"
                    " ELSE notes || char(10) || ? END WHERE id = ? AND ended_ns IS NULL",
                    (ended, note, note, run.id))
            out.append((run, int(count)))
        return out

    def runs(self) -> list[RunRecord]:
        """Every run, oldest first."""
        rows = self._read(
            "SELECT id, started_ns, ended_ns, config, robotd_version, notes, epoch_unix_ns"
            " FROM runs ORDER BY id"
        )
        return [RunRecord(*row) for row in rows]

    # -- keyframes -----------------------------------------------------------------

    def add_keyframe(
        self,
        run_id: int,
        stamp_ns: int,
        pose_xyyaw: Sequence[float] | np.ndarray,
        covariance: np.ndarray | Sequence[Sequence[float]],
        image: np.ndarray | None,
        descriptor: bytes | None = None,
        descriptor_mode: int | None = None,
    ) -> int:
        """Store one keyframe and commit it; returns its id (ids only grow).

        ``pose_xyyaw`` is ``(x_m, y_m, yaw_rad)`` in the map frame; ``covariance`` is
        ``(3, 3)`` over the same; ``image`` is ``(H, W) uint8`` grey (already downsampled
        as wanted: it is encoded, not resized) or None; ``descriptor`` and
        ``descriptor_mode`` come together or not at all (see :meth:`set_descriptor`).
        Raises ValueError for bad arguments or an unknown ``run_id``.
        """
        x_m, y_m, yaw_rad = finite_triple(pose_xyyaw, "pose_xyyaw")
        cov_blob = matrix_to_blob(covariance, "covariance")
        check_descriptor(descriptor, descriptor_mode)
        image_blob: bytes | None = None
        width = height = None
        if image is not None:
            image_blob, height, width = self._encode_image(image)
        with self._write() as conn:
            cur = conn.execute(
                "INSERT INTO keyframes(run_id, stamp_ns, x_m, y_m, yaw_rad, covariance,"
                " image, image_width, image_height, descriptor, descriptor_mode)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (int(run_id), int(stamp_ns), x_m, y_m, yaw_rad, cov_blob, image_blob, width,
                 height, None if descriptor is None else bytes(descriptor),
                 None if descriptor_mode is None else int(descriptor_mode)),
            )
        assert cur.lastrowid is not None  # an INSERT's
        return cur.lastrowid

    def set_descriptor(self, keyframe_id: int, descriptor: bytes, mode: int) -> None:
        """Store (or replace) the compact descriptor of a keyframe; KeyError if unknown."""
        check_descriptor(descriptor, mode)
        with self._write() as conn:
            cur = conn.execute(
                "UPDATE keyframes SET descriptor = ?, descriptor_mode = ? WHERE id = ?",
                (bytes(descriptor), int(mode), int(keyframe_id)),
            )
            if cur.rowcount != 1:
                raise KeyError(f"no keyframe {keyframe_id} in map {self._path}")

    _KEYFRAME_COLUMNS = (
        "id, run_id, stamp_ns, x_m, y_m, yaw_rad, covariance, image_width, image_height,"
        " descriptor, descriptor_mode"
    )

    @staticmethod
    def _keyframe_record(row: tuple[Any, ...]) -> KeyframeRecord:
        kf_id, run_id, stamp_ns, x_m, y_m, yaw_rad, cov, width, height, desc, mode = row
        return KeyframeRecord(
            kf_id, run_id, stamp_ns, x_m, y_m, yaw_rad, blob_to_matrix(cov), width, height,
            None if desc is None else bytes(desc), mode,
        )

    def keyframe(self, keyframe_id: int) -> KeyframeRecord:
        """One keyframe's record; KeyError if there is no such keyframe."""
        rows = self._read(
            f"SELECT {self._KEYFRAME_COLUMNS} FROM keyframes WHERE id = ?", (int(keyframe_id),)
        )
        if not rows:
            raise KeyError(f"no keyframe {keyframe_id} in map {self._path}")
        return self._keyframe_record(rows[0])

    def keyframe_descriptor(self, keyframe_id: int) -> tuple[bytes | None, int | None]:
        """One keyframe's compact descriptor and its mode, ``(None, None)`` if it has none
        (the floor index's read back: the descriptor columns alone, no record built);
        KeyError if there is no such keyframe."""
        rows = self._read("SELECT descriptor, descriptor_mode FROM keyframes WHERE id = ?", (int(keyframe_id),))
        if not rows:
            raise KeyError(f"no keyframe {keyframe_id} in map {self._path}")
        desc, mode = rows[0]
        return (None if desc is None else bytes(desc)), mode

    def keyframes(self, run_id: int | None = None) -> Iterator[KeyframeRecord]:
        """Keyframes in id order, of one run or of the whole map, without images.

        Rows are fetched in pages by id, so no read transaction stays open while the
        caller works through a large map (an open reader would stop WAL checkpoints).
        Keyframes added during the iteration are included if their id comes later.
        """
        last_id = -1
        while True:
            if run_id is None:
                rows = self._read(
                    f"SELECT {self._KEYFRAME_COLUMNS} FROM keyframes"
                    " WHERE id > ? ORDER BY id LIMIT ?",
                    (last_id, _PAGE_ROWS),
                )
            else:
                rows = self._read(
                    f"SELECT {self._KEYFRAME_COLUMNS} FROM keyframes"
                    " WHERE run_id = ? AND id > ? ORDER BY id LIMIT ?",
                    (int(run_id), last_id, _PAGE_ROWS),
                )
            for row in rows:
                yield self._keyframe_record(row)
            if len(rows) < _PAGE_ROWS:
                return
            last_id = rows[-1][0]

    def keyframe_image(self, keyframe_id: int) -> np.ndarray | None:
        """The decoded ``(H, W) uint8`` image of a keyframe, None if it was stored without
        one; KeyError if there is no such keyframe, MapStoreError if it does not decode."""
        rows = self._read(
            "SELECT image, image_width, image_height FROM keyframes WHERE id = ?",
            (int(keyframe_id),),
        )
        if not rows:
            raise KeyError(f"no keyframe {keyframe_id} in map {self._path}")
        blob, width, height = rows[0]
        if blob is None:
            return None
        image = cv2.imdecode(np.frombuffer(blob, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        if image is None or image.shape != (height, width):
            raise MapStoreError(
                f"map {self._path}: the image of keyframe {keyframe_id} does not decode"
                f" to {width}x{height} grey"
            )
        return image

    def count_keyframes(self, run_id: int | None = None) -> int:
        """Number of keyframes in the map, or in one run."""
        if run_id is None:
            return int(self._read("SELECT count(*) FROM keyframes")[0][0])
        return int(
            self._read("SELECT count(*) FROM keyframes WHERE run_id = ?", (int(run_id),))[0][0]
        )

    def _encode_image(self, image: np.ndarray) -> tuple[bytes, int, int]:
        array = np.asarray(image)
        if array.ndim != 2 or array.dtype != np.uint8 or array.size == 0:
            raise ValueError(
                f"image must be a non-empty (H, W) uint8 grey array, got shape"
                f" {array.shape} dtype {array.dtype}"
            )
        array = np.ascontiguousarray(array)
        if self._image_codec == "png":
            ok, buf = cv2.imencode(".png", array)
        else:
            ok, buf = cv2.imencode(".jpg", array, [cv2.IMWRITE_JPEG_QUALITY, self._jpeg_quality])
        if not ok:
            raise ValueError(f"image of shape {array.shape} could not be encoded")
        return buf.tobytes(), int(array.shape[0]), int(array.shape[1])

    # -- links ---------------------------------------------------------------------

    def add_link(
        self,
        kind: Literal["odometry", "loop"],
        from_id: int,
        to_id: int,
        delta_xyyaw: Sequence[float] | np.ndarray,
        information: np.ndarray | Sequence[Sequence[float]],
    ) -> int:
        """Store a pose-graph edge and commit it; returns its id.

        ``delta_xyyaw`` is ``(dx_m, dy_m, dyaw_rad)``, the pose of ``to_id`` in the frame
        of ``from_id``; ``information`` is its ``(3, 3)`` information matrix. Raises
        ValueError for an unknown kind or keyframe id.
        """
        if kind not in _LINK_KINDS:
            raise ValueError(f"link kind must be one of {_LINK_KINDS}, got {kind!r}")
        dx_m, dy_m, dyaw_rad = finite_triple(delta_xyyaw, "delta_xyyaw")
        info_blob = matrix_to_blob(information, "information")
        with self._write() as conn:
            cur = conn.execute(
                "INSERT INTO links(kind, from_id, to_id, dx_m, dy_m, dyaw_rad, information)"
                " VALUES (?, ?, ?, ?, ?, ?, ?)",
                (kind, int(from_id), int(to_id), dx_m, dy_m, dyaw_rad, info_blob),
            )
        assert cur.lastrowid is not None  # an INSERT's
        return cur.lastrowid

    def links(self, kind: Literal["odometry", "loop"] | None = None) -> list[LinkRecord]:
        """Every link (or every link of one kind), in id order."""
        sql = "SELECT id, kind, from_id, to_id, dx_m, dy_m, dyaw_rad, information FROM links"
        params: tuple[object, ...] = ()
        if kind is not None:
            sql += " WHERE kind = ?"
            params = (kind,)
        rows = self._read(sql + " ORDER BY id", params)
        return [LinkRecord(i, kind_, a, b, dx, dy, dyaw, blob_to_matrix(info))
                for i, kind_, a, b, dx, dy, dyaw, info in rows]

    # -- calibration ---------------------------------------------------------------

    def put_calibration(self, name: str, content: str, created_ns: int | None = None) -> None:
        """Store a new version of the calibration ``name`` (older versions are kept),
        created at ``created_ns`` (default: the store's clock now)."""
        if created_ns is None:
            created_ns = self._clock.now_ns()
        with self._write() as conn:
            conn.execute(
                "INSERT INTO calibration(name, created_ns, content) VALUES (?, ?, ?)",
                (str(name), int(created_ns), str(content)),
            )

    def get_calibration(self, name: str) -> str | None:
        """The newest version of calibration ``name``, None if there is none."""
        rows = self._read(
            "SELECT content FROM calibration WHERE name = ? ORDER BY id DESC LIMIT 1",
            (str(name),),
        )
        return rows[0][0] if rows else None

    # -- pose graph results --------------------------------------------------------

    def put_optimized_poses(
        self, keyframe_ids: Sequence[int], poses: np.ndarray, solved_unix_ns: int | None = None
    ) -> None:
        """Store a pose-graph solution in one transaction, replacing any older solved
        pose of the same keyframes.

        ``poses`` is ``(N, 3)`` rows of ``(x_m, y_m, yaw_rad)`` (map frame), one per id
        in ``keyframe_ids`` (distinct); ``solved_unix_ns`` (default: the host's wall clock
        now) is when the graph was solved. ValueError for bad shapes or values, KeyError
        naming the first unknown keyframe; nothing is written then.
        """
        ids = [int(i) for i in keyframe_ids]
        array = np.asarray(poses, dtype=np.float64)
        if array.size == 0 and not ids:
            array = array.reshape(0, 3)
        if array.shape != (len(ids), 3):
            raise ValueError(f"poses must have shape ({len(ids)}, 3), got {array.shape}")
        if not np.all(np.isfinite(array)):
            raise ValueError("poses must be finite")
        if len(set(ids)) != len(ids):
            raise ValueError("keyframe_ids must be distinct")
        stamp = time.time_ns() if solved_unix_ns is None else int(solved_unix_ns)
        with self._write() as conn:
            for kf_id in ids:
                if not conn.execute("SELECT 1 FROM keyframes WHERE id = ?", (kf_id,)).fetchone():
                    raise KeyError(f"no keyframe {kf_id} in map {self._path}")
            conn.executemany(
                "INSERT INTO optimized_poses(keyframe_id, x_m, y_m, yaw_rad, solved_unix_ns)"
                " VALUES (?, ?, ?, ?, ?) ON CONFLICT(keyframe_id) DO UPDATE SET"
                " x_m = excluded.x_m, y_m = excluded.y_m, yaw_rad = excluded.yaw_rad,"
                " solved_unix_ns = excluded.solved_unix_ns",
                [(kf_id, *map(float, row), stamp) for kf_id, row in zip(ids, array)],
            )

    def optimized_poses(self) -> dict[int, np.ndarray]:
        """Keyframe id -> its newest solved pose, ``(3,) float64`` ``(x_m, y_m, yaw_rad)``."""
        rows = self._read(
            "SELECT keyframe_id, x_m, y_m, yaw_rad FROM optimized_poses ORDER BY keyframe_id"
        )
        return {r[0]: np.array(r[1:], dtype=np.float64) for r in rows}

    def optimized_pose(self, keyframe_id: int) -> np.ndarray | None:
        """The newest solved ``(x_m, y_m, yaw_rad)`` of a keyframe, None if never solved."""
        rows = self._read(
            "SELECT x_m, y_m, yaw_rad FROM optimized_poses WHERE keyframe_id = ?",
            (int(keyframe_id),),
        )
        return np.array(rows[0], dtype=np.float64) if rows else None

    def add_loop_candidates(self, rows: Sequence[tuple[int, int, float, LoopFate | str, str]]) -> None:
        """Record loop candidates ``(query_id, candidate_id, score, fate, detail)`` in one
        transaction. ValueError (nothing written) for a fate not in
        :data:`LOOP_CANDIDATE_FATES`, a non-finite score or an unknown keyframe id."""
        values = []
        for query_id, candidate_id, score, fate, detail in rows:  # ValueError if not 5
            if fate not in LOOP_CANDIDATE_FATES:
                raise ValueError(f"fate must be one of {_FATE_TEXTS}, got {fate!r}")
            if not math.isfinite(float(score)):
                raise ValueError(f"score must be finite, got {score}")
            values.append((int(query_id), int(candidate_id), float(score), str(fate), str(detail)))
        with self._write() as conn:
            conn.executemany(
                "INSERT INTO loop_candidates(query_id, candidate_id, score, fate, detail)"
                " VALUES (?, ?, ?, ?, ?)", values)

    def loop_candidates(self, fate: LoopFate | str | None = None) -> list[LoopCandidateRecord]:
        """Every loop candidate (or those of one fate), in the order recorded."""
        sql = "SELECT id, query_id, candidate_id, score, fate, detail FROM loop_candidates"
        if fate is None:
            return [candidate_record(r) for r in self._read(sql + " ORDER BY id")]
        if fate not in LOOP_CANDIDATE_FATES:
            raise ValueError(f"fate must be one of {_FATE_TEXTS}, got {fate!r}")
        rows = self._read(sql + " WHERE fate = ? ORDER BY id", (str(fate),))
        return [candidate_record(r) for r in rows]


    # -- the forward camera's memory (version 4, encodings of version 5) -----------------------------------

    def add_forward_image(self, image_id: int, keyframe_id: int, kind: str, image_size_px: tuple[int, int],
                          words: np.ndarray, keypoints_q: np.ndarray, descriptors: np.ndarray,
                          new_words: Sequence[tuple[int, bytes]] = (), purged: Sequence[int] = ()) -> None:
        """Store one forward image (``words (N,) uint32``, ``keypoints_q (N, 2) uint16`` in
        1/16 px, ``descriptors``), the words it made (``(word id, descriptor bytes)``) and
        the words purged after it (their descriptors are dropped), in one transaction (a
        power cut loses at most this image). ValueError for an unknown keyframe or a repeated id.

        A new word whose descriptor is that of its founder, the image's first feature with
        that word (as :class:`robotd.forward.vocabulary.Vocabulary` makes words), is written
        without it: :meth:`forward_memory` takes it from the image row (a word row then
        holds a few bytes instead of a descriptor more)."""
        w, h = (int(v) for v in image_size_px)
        words = np.asarray(words)
        ids = words.tolist()
        first: dict[int, int] = {}
        for at, wid in enumerate(ids):
            first.setdefault(int(wid), at)
        raw = np.ascontiguousarray(descriptors, descriptors.dtype.newbyteorder("<"))
        rows = []
        for wid, d in new_words:
            founder = first.get(int(wid))
            own = founder is None or raw[founder].tobytes() != bytes(d)
            rows.append((int(wid), kind, bytes(d) if own else b"", int(image_id)))
        with self._write() as conn:
            conn.execute(
                "INSERT INTO forward_images (image_id, keyframe_id, kind, image_width, image_height, words,"
                " keypoints, descriptors) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (int(image_id), int(keyframe_id), kind, w, h, pack_word_ids(words),
                 np.ascontiguousarray(keypoints_q, "<u2").tobytes(),
                 raw.tobytes()))
            if rows:
                conn.executemany("INSERT INTO forward_words (id, kind, descriptor, born_image) VALUES (?, ?, ?, ?)",
                                 rows)
            if purged:
                # A purged word is never searched again: its descriptor is dropped.
                conn.executemany("UPDATE forward_words SET purged = 1, descriptor = X'' WHERE id = ?",
                                 [(int(i),) for i in purged])

    def forward_memory(self, features_from: int = 0) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]]:
        """Everything :meth:`add_forward_image` stored: the images as ``(image_id,
        keyframe_id, kind, (width, height), words (N,) uint32, keypoints_q (N, 2) uint16,
        descriptors bytes)`` in image order, and the words as ``(id, kind, descriptor
        bytes, born_image, purged)`` in id order (the caller knows the descriptor type; a
        purged word's descriptor is empty; a word written without its descriptor gets its
        founder's from the image row). Images before ``features_from`` come without their
        keypoints and descriptors (``(0, 2)`` and empty bytes; :meth:`forward_image` reads
        them when needed), so a long memory is taken up without holding every image's
        features at once. MapStoreError when a stored row does not decode."""
        images = []
        for image_id, kf, kind, w, h, words, n_kps, kps, desc in self._read(
                "SELECT image_id, keyframe_id, kind, image_width, image_height, words, length(keypoints),"
                " CASE WHEN image_id >= ? THEN keypoints ELSE X'' END,"
                " CASE WHEN image_id >= ? THEN descriptors ELSE X'' END"
                " FROM forward_images ORDER BY image_id", (int(features_from), int(features_from))):
            try:
                ids = unpack_word_ids(bytes(words), int(n_kps) // 4)
            except ValueError as exc:
                raise MapStoreError(f"map {self._path}: forward image {image_id}: {exc}") from exc
            images.append((image_id, kf, kind, (w, h), ids,
                           np.frombuffer(kps, "<u2").astype(np.uint16).reshape(-1, 2), bytes(desc)))
        by_id = {im[0]: im for im in images}
        founder_desc: tuple[int, bytes] = (-1, b"")  # the last image read back for its founders (words come by image)
        words = []
        for i, kind, d, born, p in self._read(
                "SELECT id, kind, descriptor, born_image, purged FROM forward_words ORDER BY id"):
            d = bytes(d)
            if not d and not p:  # written without it: the founder's descriptor
                im = by_id.get(born)
                at = np.flatnonzero(im[4] == i) if im is not None else np.empty(0, np.intp)
                if im is None or not len(at):
                    raise MapStoreError(f"map {self._path}: forward word {i} has no descriptor and its image "
                                        f"{born} no feature of it")
                desc = im[6]
                if len(im[4]) and not desc:  # not read above: this image's descriptors alone
                    if founder_desc[0] != born:
                        row = self._read("SELECT descriptors FROM forward_images WHERE image_id = ?", (int(born),))
                        founder_desc = (born, bytes(row[0][0]))
                    desc = founder_desc[1]
                size = len(desc) // max(len(im[4]), 1)
                d = desc[int(at[0]) * size:(int(at[0]) + 1) * size]
            words.append((i, kind, d, born, bool(p)))
        return images, words

    def forward_image_count(self) -> int:
        """How many forward images the map holds."""
        return int(self._read("SELECT COUNT(*) FROM forward_images")[0][0])

    def forward_image(self, image_id: int) -> tuple[str, tuple[int, int], np.ndarray, bytes] | None:
        """One stored forward image's features: ``(kind, (width, height), keypoints_q (N, 2)
        uint16, descriptors bytes)``; None when the map has no such image."""
        rows = self._read("SELECT kind, image_width, image_height, keypoints, descriptors FROM forward_images"
                          " WHERE image_id = ?", (int(image_id),))
        if not rows:
            return None
        kind, w, h, kps, desc = rows[0]
        return kind, (w, h), np.frombuffer(kps, "<u2").astype(np.uint16).reshape(-1, 2), bytes(desc)


def pack_word_ids(words: np.ndarray) -> bytes:
    """An image's word ids ``(N,)`` as ``forward_images.words`` stores them: the ids'
    little-endian uint32 bytes regrouped by significance (all lowest bytes, then the next,
    ...) and deflated (zlib), when that is shorter than the ``4 N`` raw bytes (the high
    bytes of ids below 2^24 are mostly alike: about half the size on the office route);
    else the raw bytes, as every map before this encoding has them. The length tells the
    two apart (:func:`unpack_word_ids`)."""
    raw = np.ascontiguousarray(words, "<u4")
    packed = zlib.compress(raw.view(np.uint8).reshape(-1, 4).T.tobytes(), 6)
    return packed if len(packed) < raw.nbytes else raw.tobytes()


def unpack_word_ids(blob: bytes, n: int) -> np.ndarray:
    """The ``n`` word ids ``(n,) uint32`` of a ``forward_images.words`` value
    (:func:`pack_word_ids`: raw when it is ``4 n`` bytes long, else deflated). ValueError
    when it holds no ``n`` ids."""
    if len(blob) == 4 * n:
        return np.frombuffer(blob, "<u4").astype(np.uint32)
    try:
        planes = zlib.decompress(blob)
    except zlib.error as exc:
        raise ValueError(f"word ids are neither {n} raw ids nor deflated ({exc})") from None
    if len(planes) != 4 * n:
        raise ValueError(f"word ids hold {len(planes) // 4} ids, the keypoints {n}")
    return np.frombuffer(planes, np.uint8).reshape(4, n).T.copy().view("<u4").reshape(n).astype(np.uint32)
