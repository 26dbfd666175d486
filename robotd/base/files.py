"""Output files the user names: checked before anything is written, replaced atomically.

Every command that writes a file the user named (``graph optimize --out``, ``graph export
--out``, ``kobuki decode --out``, ``record``) follows one contract:

- the output is checked before any work starts (:func:`check_output_file`): a folder where
  a file is asked for, a missing parent folder, an existing file without ``--force``, and an
  output that is one of the command's inputs are refused with one line naming the path;
- the output is written to a temporary file in the same folder and renamed over the target
  when complete (:func:`replacing`), so a full disk, a read-only file system or Ctrl-C leaves
  the previous file exactly as it was, and no partial file behind.

:class:`~robotd.base.errors.OutputError` carries the one line.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from robotd.base.errors import OutputError


def describe_path_kind(path: Path) -> str:
    """What ``path`` is, in words, for a message ("a folder", "a character device", ...)."""
    try:
        mode = path.stat().st_mode
    except PermissionError:
        return "not accessible (permission denied on a folder on its path)"
    except OSError:
        return "missing"
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a regular file" if stat.S_ISREG(mode) else "not a regular file"


def check_utf8_path(path: Path, option: str) -> None:
    """OutputError unless ``path`` is valid UTF-8: robotd stores paths as text (the map's
    run records, its summaries), and a name with a stray byte cannot be written there."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(path).decode("utf-8", "backslashreplace")
        raise OutputError(f"{option} {shown}: the path is not valid UTF-8; choose a name in "
                          "UTF-8") from None


def nonempty_path(text: str) -> Path:
    """An ``argparse`` type for paths: refuses an empty one, which ``Path`` would read as
    the current folder."""
    import argparse

    if not text.strip():
        raise argparse.ArgumentTypeError("empty path")
    return Path(text)


def same_file(a: Path, b: Path) -> bool:
    """True when ``a`` and ``b`` name one existing file (through links, ``..`` or case)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_output_file(path: Path, *, force: bool, inputs: Iterable[Path] = (),
                      option: str = "--out", force_option: str | None = "--force") -> None:
    """Refuse, before anything is written, an output file that cannot or must not be
    written: a folder or device at ``path``, a parent that is not a folder, an existing
    file unless ``force``, or one of ``inputs`` (never overwritten, even with ``force``).
    Raises :class:`OutputError` naming ``path`` and ``option``; ``force_option`` is the
    command's option that allows overwriting (None: the command has none)."""
    for src in inputs:
        if same_file(path, src):
            raise OutputError(f"{option} {path} is the input {src}: write the output to another file")
    if path.exists() or path.is_symlink():
        kind = describe_path_kind(path)
        if kind != "a regular file":
            raise OutputError(f"{option} {path} is {kind}; give a file name")
        if not force:
            raise OutputError(f"{path} exists (use {force_option} to overwrite)" if force_option
                              else f"{path} exists: choose another name")
    parent = path.parent
    if not parent.is_dir():
        what = "does not exist" if not parent.exists() else "is not a folder"
        raise OutputError(f"cannot write {path}: folder {parent} {what}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {path}: folder {parent} is not writable "
                          "(read-only file system or permissions)")


@contextlib.contextmanager
def replacing(path: Path, mode: str = "w", encoding: str | None = "utf-8") -> Iterator[IO[Any]]:
    """Write ``path`` through a temporary file in its folder, renamed over ``path`` only
    when the ``with`` block ends normally (after ``fsync``). On any error, Ctrl-C
    included, the temporary file is removed and ``path`` is left as it was; an
    :class:`OSError` (disk full, read-only file system, I/O error) becomes
    :class:`OutputError` naming ``path``. ``mode`` is ``"w"`` or ``"wb"``."""
    if mode not in ("w", "wb"):
        raise ValueError(f"mode must be 'w' or 'wb', got {mode!r}")
    # Created 0o666 less the umask, as a plain open() would (mkstemp's 0o600 would need the
    # umask read back, which os.umask can only do by changing it for every thread).
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None
    try:
        try:
            f = os.fdopen(fd, mode, encoding=None if "b" in mode else encoding)
        except BaseException:
            os.close(fd)
            raise
        with f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        if path.exists():  # keep the permissions the user gave the file it replaces
            with contextlib.suppress(OSError):
                os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}; "
                          f"{'the previous file is unchanged' if path.exists() else 'nothing written'}"
                          ) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def check_output_folder(path: Path, gets: str, option: str = "--out") -> None:
    """:class:`OutputError` when ``path`` exists and is not a folder; ``gets`` says what the
    folder would receive (checked before any work, so that nothing is spent on a run whose
    output cannot be written)."""
    if path.exists() and not path.is_dir():
        raise OutputError(f"{option} {path} is {describe_path_kind(path)}; give a folder (it gets {gets})")


def write_text_replacing(path: Path, text: str, encoding: str = "utf-8") -> None:
    """``path.write_text(text)`` through :func:`replacing`."""
    with replacing(path, "w", encoding) as f:
        f.write(text)
