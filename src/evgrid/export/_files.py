"""One policy for every export writer (nav2, MCAP, rerun).

* An existing file is refused unless ``overwrite``; a folder given as the target is written
  into (the file gets its default name there).
* A map with no observed cell is refused by every writer alike (:func:`refuse_empty`), as
  nav2's map_server refuses an empty image: an export of nothing is no result.
* Files are written by :class:`evgrid.io.AtomicFile`, evgrid's one atomic writer: a temporary
  name in the file's folder, renamed when complete, removed on any exception; every error names
  the file.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from evgrid.io import AtomicFile, refuse_existing, write_error
from evgrid.io import FileWriteError as ExportFileError
from evgrid.io import TargetExistsError as ExportExistsError

__all__ = [
    "ExportExistsError",
    "ExportFileError",
    "AtomicFile",
    "EmptyMapError",
    "refuse_empty",
    "target_path",
    "refuse_existing",
    "write_all",
    "write_error",
]


class EmptyMapError(ValueError):
    """A map with no observed cell given to an exporter."""


def refuse_empty(maps: Mapping[str, Any], target: str | os.PathLike) -> None:
    """Refuse, naming ``target`` and the map, any of ``maps`` (name -> EvidentialMap) that has no
    observed cell, before a file is opened."""
    empty = [name for name, m in maps.items() if m.covered_bounds()[2] == 0]
    if empty:
        raise EmptyMapError(
            f"{target}: the map {', '.join(map(repr, empty))} has no observed cell (an empty "
            "map); nothing to export"
        )


def target_path(path: str | os.PathLike, default_name: str, suffix: str = "") -> Path:
    """Where an export goes: inside ``path`` when it is a folder (``default_name + suffix``),
    else ``path`` itself with ``suffix`` added when it does not end with it."""
    p = Path(path)
    if str(path).endswith(os.sep) or p.is_dir():
        return p / (default_name + suffix)
    if suffix and p.suffix != suffix:
        p = p.with_name(p.name + suffix)
    return p


def write_all(
    files: dict[Path, bytes | Callable[[AtomicFile], None]], overwrite: bool = False
) -> list[Path]:
    """Write several files together: all of them refused, or all written to temporary names
    first and then renamed (a failure on any removes every temporary file). A file's content
    is its bytes, or a function that writes them piece by piece into the file it is given."""
    refuse_existing(files, overwrite)
    pending = [AtomicFile(p, overwrite) for p in files]
    try:
        for f, data in zip(pending, files.values()):
            if callable(data):
                data(f)
            else:
                f.write(data)
        return [f.commit() for f in pending]
    finally:
        for f in pending:
            f.abort()  # no-op for committed files
