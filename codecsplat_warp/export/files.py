"""Atomic file output: a result file either appears complete or not at all (interruptions lose nothing).

Everything the command line writes (bitstreams, PLY files, renders, tables, plots) goes through
:func:`atomic_output` (JSON through :func:`write_json`): the
writer fills ``.<name>.tmp-<pid>`` next to the destination, which is moved into place with ``os.replace``
only when the writer finished without an exception.
"""

from __future__ import annotations

import contextlib
import json
import os
import pathlib
from typing import Iterator


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[pathlib.Path]:
    """Yield a temporary path in ``path``'s folder; on success it replaces ``path``, on error it is removed.

    The temporary name keeps ``path``'s suffix, so writers that pick a format from it still work.
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    with atomic_output(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_json(path: str | os.PathLike, payload: dict) -> None:
    """Write ``payload`` (JSON-serialisable) to ``path`` as JSON indented by 2, atomically."""
    write_text(path, json.dumps(payload, indent=2))
