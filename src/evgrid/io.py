"""Small file helpers: the one atomic writer of evgrid (:class:`AtomicFile`: a temporary file
next to the target, then a rename), JSON.

* A file is written under a temporary name in its own folder (``.NAME.XXXX.part``) and renamed
  onto its final name only when complete, so a reader never sees half a file under the final
  name. On any exception, KeyboardInterrupt included, the temporary file is removed; a writer
  that is dropped without :meth:`AtomicFile.commit` removes it too (garbage collection or the
  interpreter's exit).
* Every error names the file it is about (a full disk says which file).
"""

from __future__ import annotations

import errno
import json
import math
import os
import tempfile
import weakref
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np

__all__ = [
    "AtomicFile",
    "FileWriteError",
    "TargetExistsError",
    "atomic_open",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "jsonable",
    "refuse_existing",
    "write_error",
    "write_json",
]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: mkstemp creates files readable by the owner only; written files get the usual mode instead.
_FILE_MODE = 0o666 & ~_umask()


class TargetExistsError(FileExistsError):
    """A file to write exists and ``overwrite`` was not given; the message names it."""

    def __str__(self) -> str:
        return str(self.strerror)


class FileWriteError(OSError):
    """A file could not be written; the message names the file and the reason."""

    def __init__(self, path: str | os.PathLike, cause: OSError):
        super().__init__(cause.errno, cause.strerror or str(cause), str(path))
        self.path = Path(path)

    def __str__(self) -> str:
        code = f" (errno {self.errno})" if self.errno else ""
        return f"{self.path}: {self.strerror}{code}; nothing was written under that name"


def write_error(path: Path, e: BaseException) -> BaseException:
    """``e`` as an error naming ``path`` (OS errors), or ``e`` itself (anything else)."""
    if isinstance(e, OSError) and not isinstance(e, (FileWriteError, FileExistsError)):
        return FileWriteError(path, e)
    return e


def refuse_existing(paths: Iterable[Path], overwrite: bool) -> None:
    """Raise FileExistsError naming the first of ``paths`` that exists, unless ``overwrite``;
    a folder is refused always."""
    for p in paths:
        if p.is_dir():
            raise IsADirectoryError(errno.EISDIR, f"{p} is a folder, not a file to write", str(p))
        if not overwrite and (p.exists() or p.is_symlink()):
            raise TargetExistsError(
                errno.EEXIST, f"{p} exists; pass overwrite (--overwrite) to replace it", str(p)
            )


def _remove(fh: IO, tmp: str) -> None:
    try:
        fh.close()
    except OSError:
        pass
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass


class AtomicFile:
    """A file written under a temporary name beside ``path``, renamed onto it by
    :meth:`commit`; :meth:`abort` (or any exception inside ``with``) removes it.

    ``mode`` is ``"wb"`` (bytes) or ``"w"`` (UTF-8 text). ``path`` is refused when it exists
    unless ``overwrite`` (checked at the start and, without ``overwrite``, again at the rename,
    which never replaces a file that appeared meanwhile).
    """

    def __init__(self, path: str | os.PathLike, overwrite: bool = False, mode: str = "wb"):
        if mode not in ("wb", "w"):
            raise ValueError(f"AtomicFile supports modes 'wb' and 'w', got {mode!r}")
        self.path = Path(path)
        self.overwrite = overwrite
        refuse_existing([self.path], overwrite)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(
                prefix="." + self.path.name + ".", suffix=".part", dir=self.path.parent
            )
        except OSError as e:
            raise write_error(self.path, e) from e
        self.tmp = Path(tmp)
        text = {"encoding": "utf-8"} if mode == "w" else {}
        self.file: IO = os.fdopen(fd, mode, **text)
        self._cleanup = weakref.finalize(self, _remove, self.file, tmp)

    @property
    def done(self) -> bool:
        """Whether the file was committed or aborted."""
        return not self._cleanup.alive

    def write(self, data: bytes | str) -> int:
        """Write ``data``; an OS error removes the temporary file and names ``path``."""
        try:
            return self.file.write(data)
        except BaseException as e:
            self.abort()
            raise write_error(self.path, e) from e

    def tell(self) -> int:
        return self.file.tell()

    def commit(self) -> Path:
        """Flush, sync and rename the file onto ``path``; returns ``path``."""
        try:
            self.file.flush()
            os.fsync(self.file.fileno())  # the data is on disk before the rename shows it
            self.file.close()
            os.chmod(self.tmp, _FILE_MODE)
            if self.overwrite:
                os.replace(self.tmp, self.path)
            else:
                refuse_existing([self.path], False)
                os.link(self.tmp, self.path)  # fails if the name appeared meanwhile
                os.unlink(self.tmp)
        except BaseException as e:
            self.abort()
            raise write_error(self.path, e) from e
        self._cleanup.detach()
        return self.path

    def abort(self) -> None:
        """Remove the temporary file (nothing is left under ``path``); safe to call twice."""
        self._cleanup()

    def __enter__(self) -> AtomicFile:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


@contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """The file object of an :class:`AtomicFile` that replaces ``path`` when the block ends
    without an exception (an existing ``path`` is replaced)."""
    with AtomicFile(path, overwrite=True, mode=mode) as f:
        yield f.file


def atomic_write(path: str | os.PathLike, write: Callable[[IO], None], mode: str = "wb") -> Path:
    """Write a file through ``write(fileobj)`` atomically; return its path."""
    with atomic_open(path, mode) as f:
        write(f)
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_open(path, "wb") as f:
        f.write(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    with atomic_open(path, "w") as f:
        f.write(text)


def jsonable(x: Any) -> Any:
    """Plain JSON values: numpy numbers to Python numbers, NaN to null, tuples to lists, keys to
    strings."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if math.isnan(float(x)) else float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (see :func:`jsonable`), atomically; the one JSON writer of
    evgrid."""
    text = json.dumps(jsonable(obj), indent=2)
    atomic_write_text(path, text + "\n")
    return Path(path)
