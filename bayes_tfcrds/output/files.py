"""Atomic file writes: the one way the toolkit puts a file in place.

A result file is either the old one or the complete new one, never half-written: the content
goes to a unique hidden temporary name in the target's directory (``.NAME.<pid>-<hex>.tmp``), is
flushed to disk (fsync), and is moved over the target with ``os.replace`` (atomic on POSIX).
On any failure the temporary file is removed and the target is untouched.
"""

from __future__ import annotations

import glob
import os
import re
import secrets
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: pattern of the temporary names made here (for cleaning up after a killed process)
TEMP_GLOB = ".*.tmp*"


def temporary_name(path: Path, suffix: str = "") -> Path:
    """A unique hidden name beside ``path``: ``.NAME.<pid>-<hex>.tmp<suffix>``.

    ``suffix`` keeps a file type (``.png``) for writers that choose their format from the name;
    the process id lets a later run tell a killed writer's leftover from a live one's file.
    """
    return path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(6)}.tmp{suffix}")


_TEMP_RE = re.compile(r"\.(?P<name>.+)\.(?P<pid>\d+)-[0-9a-f]{12}\.tmp.*")


def clean_stale_temporaries(target: Path) -> list:
    """Remove temporaries of ``target`` left by writers that were killed; returns their paths.

    Only names this module makes are touched, and only when the process that made them is no
    longer running (a SIGKILL during a 50 MB save would otherwise leave the file forever).
    """
    removed = []
    for tmp in target.parent.glob(f".{glob.escape(target.name)}.*.tmp*"):
        m = _TEMP_RE.fullmatch(tmp.name)
        if m is None or m["name"] != target.name or _alive(int(m["pid"])):
            continue
        tmp.unlink(missing_ok=True)
        removed.append(tmp)
    return removed


def clean_dead_writers(folder: Path) -> list:
    """Remove every temporary in ``folder`` whose writer was killed; returns their paths.

    For a folder of many results (a budget's), where the names a killed run was writing are not
    all known; a live writer's temporary (another run, this process) is never touched.
    """
    removed = []
    for tmp in Path(folder).glob(TEMP_GLOB):
        m = _TEMP_RE.fullmatch(tmp.name)
        if m is None or _alive(int(m["pid"])):
            continue
        tmp.unlink(missing_ok=True)
        removed.append(tmp)
    return removed


class FolderBusyError(OSError):
    """Another run holds the output folder (see :func:`folder_lock`)."""


@contextmanager
def folder_lock(folder) -> Iterator[Path]:
    """Hold ``folder`` (created if missing) for this run alone until the block ends.

    A budget resumes the chains it finds in its folder; a second budget there at the same time
    would interleave its commits with the first's (or stop in HDF5's BlockingIOError). The lock
    is an advisory ``flock`` on the folder itself: no file is added, and the kernel releases it
    when the process ends, however it ends. Raises :class:`FolderBusyError` at once if another
    process holds it; nested use in one process is allowed.
    """
    import fcntl

    path = Path(os.path.abspath(os.fspath(folder)))
    path.mkdir(parents=True, exist_ok=True)
    key = os.path.realpath(path)
    if key in _HELD:
        _HELD[key] += 1
        try:
            yield path
        finally:
            _HELD[key] -= 1
        return
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise FolderBusyError(
                f"{path} is in use by another run writing there; wait for it to end or give "
                "another output folder"
            ) from None
        _HELD[key] = 1
        try:
            yield path
        finally:
            del _HELD[key]
    finally:
        os.close(fd)  # releases the lock


#: folders this process holds with folder_lock (real path -> nesting depth)
_HELD: dict = {}


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # someone else's process (or not a pid we can ask about): leave it
    return True


def _fsync(path: Path) -> None:
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())


class OutputPathError(ValueError):
    """An output path the toolkit will not write: not a regular file, or a link."""


def check_replaceable(target: Path) -> None:
    """Refuse to put a file where something other than a regular file (or nothing) is.

    The rule: results replace regular files only. A symbolic link is not followed (the result
    would land outside the folder the user named) nor replaced (the link would be lost); FIFOs,
    sockets and device nodes (``-o /dev/null`` as root) are never replaced; a directory needs a
    file name inside it. Missing folders on the way are fine (the writer creates them).
    """
    try:
        st = os.lstat(target)
    except (FileNotFoundError, NotADirectoryError):
        # missing folders are created by the writer; the nearest existing one must be a folder
        for parent in target.parents:
            if os.path.lexists(parent):
                if not parent.is_dir():
                    raise OutputPathError(
                        f"{target}: {parent} is not a folder, so nothing can be written under it"
                    ) from None
                break
        return
    if stat.S_ISLNK(st.st_mode):
        raise OutputPathError(f"{target} is a symbolic link; give the path of a regular file")
    if stat.S_ISDIR(st.st_mode):
        raise OutputPathError(f"{target} is a directory; give a file name inside it")
    if not stat.S_ISREG(st.st_mode):
        raise OutputPathError(
            f"{target} is not a regular file (a FIFO, socket or device); results are not "
            "written over it"
        )


@contextmanager
def atomic_path(path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path to write ``path``'s new content to.

    On a clean exit it is synced and moved into place, on an exception it is removed.

    Missing folders are created. ``suffix`` is appended to the temporary name (see
    :func:`temporary_name`).
    """
    target = Path(os.path.abspath(os.fspath(path)))
    check_replaceable(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    clean_stale_temporaries(target)
    tmp = temporary_name(target, suffix)
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically, creating its directory if needed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
