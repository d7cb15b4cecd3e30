"""Atomic file writes: the one way the toolkit puts a file in place.

A result file is either the old one or the complete new one, never half-written: the content
goes to a unique hidden temporary name in the target's directory (``.NAME.<hex>.tmp``), is
flushed to disk (fsync), and is moved over the target with ``os.replace`` (atomic on POSIX).
On any failure the temporary file is removed and the target is untouched.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: pattern of the temporary names made here (for cleaning up after a killed process)
TEMP_GLOB = ".*.tmp*"


def temporary_name(path: Path, suffix: str = "") -> Path:
    """A unique hidden name beside ``path``.

    ``suffix`` keeps a file type (``.png``) for writers that choose their format from the name.
    """
    return path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp{suffix}")


def _fsync(path: Path) -> None:
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())


@contextmanager
def atomic_path(path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path to write ``path``'s new content to.

    On a clean exit it is synced and moved into place, on an exception it is removed.

    The directory must exist. ``suffix`` is appended to the temporary name (see
    :func:`temporary_name`).
    """
    target = Path(os.path.abspath(os.fspath(path)))
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
