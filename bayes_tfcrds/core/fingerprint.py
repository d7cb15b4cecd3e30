"""Content fingerprints: a SHA-256 of what a result depends on, to refuse reusing stale work.

A resumed computation (chains on disk) is only valid when everything that defines it is
unchanged: the data, every option and the code version. :func:`content_hash` digests nested
dataclasses, mappings, sequences, numpy arrays and scalars by value, so two objects with equal
content give one hash whichever file or process they came from.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Mapping
from pathlib import PurePath

import numpy as np


def content_hash(obj) -> str:
    """Hex SHA-256 of ``obj``'s content (see the module doc for the types understood)."""
    h = hashlib.sha256()
    _feed(h, obj)
    return h.hexdigest()


def _feed(h, obj) -> None:
    if obj is None or isinstance(obj, (bool, int, str, PurePath)):
        h.update(f"{type(obj).__name__}:{obj!s};".encode())
    elif isinstance(obj, float):
        h.update(f"float:{obj!r};".encode() if math.isfinite(obj) else f"float:{obj};".encode())
    elif isinstance(obj, np.generic):
        _feed(h, obj.item())
    elif isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        if a.dtype == object:
            h.update(f"objarray{a.shape}[".encode())
            for x in a.ravel():
                _feed(h, x)
            h.update(b"]")
        else:
            h.update(f"array:{a.dtype.str}:{a.shape}:".encode())
            h.update(a.tobytes())
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        h.update(f"{type(obj).__name__}{{".encode())
        for f in sorted(dataclasses.fields(obj), key=lambda f: f.name):
            h.update(f"{f.name}=".encode())
            _feed(h, getattr(obj, f.name))
        h.update(b"}")
    elif isinstance(obj, Mapping):
        h.update(b"map{")
        for k in sorted(obj, key=str):
            h.update(f"{k!s}=".encode())
            _feed(h, obj[k])
        h.update(b"}")
    elif isinstance(obj, (list, tuple)):
        h.update(f"seq{len(obj)}[".encode())
        for x in obj:
            _feed(h, x)
        h.update(b"]")
    else:
        raise TypeError(f"cannot fingerprint a {type(obj).__name__}")
