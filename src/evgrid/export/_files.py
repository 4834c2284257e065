"""One policy for every export writer (nav2, MCAP, rerun).

* An existing file is refused unless ``overwrite``; a folder given as the target is written
  into (the file gets its default name there).
* A file is written under a temporary name in its own folder (``.NAME.XXXX.part``) and renamed
  onto its final name only when complete, so a reader never sees half a file under the final
  name. On any exception, KeyboardInterrupt included, the temporary file is removed; a writer
  that is dropped without :meth:`AtomicFile.commit` removes it too (garbage collection or the
  interpreter's exit).
* Every error names the file it is about (a full disk says which file).
"""

from __future__ import annotations

import errno
import os
import tempfile
import weakref
from collections.abc import Iterable
from pathlib import Path
from typing import IO

from evgrid.io import _FILE_MODE

__all__ = [
    "ExportExistsError",
    "ExportFileError",
    "AtomicFile",
    "target_path",
    "refuse_existing",
    "write_all",
]


class ExportExistsError(FileExistsError):
    """An export's target exists and ``overwrite`` was not given; the message names it."""

    def __str__(self) -> str:
        return str(self.strerror)


class ExportFileError(OSError):
    """An export file could not be written; the message names the file and the reason."""

    def __init__(self, path: str | os.PathLike, cause: OSError):
        super().__init__(cause.errno, cause.strerror or str(cause), str(path))
        self.path = Path(path)

    def __str__(self) -> str:
        code = f" (errno {self.errno})" if self.errno else ""
        return f"{self.path}: {self.strerror}{code}; nothing was written under that name"


def _named(path: Path, e: BaseException) -> BaseException:
    """``e`` as an error naming ``path`` (OS errors), or ``e`` itself (anything else)."""
    if isinstance(e, OSError) and not isinstance(e, (ExportFileError, FileExistsError)):
        return ExportFileError(path, e)
    return e


def target_path(path: str | os.PathLike, default_name: str, suffix: str = "") -> Path:
    """Where an export goes: inside ``path`` when it is a folder (``default_name + suffix``),
    else ``path`` itself with ``suffix`` added when it does not end with it."""
    p = Path(path)
    if str(path).endswith(os.sep) or p.is_dir():
        return p / (default_name + suffix)
    if suffix and p.suffix != suffix:
        p = p.with_name(p.name + suffix)
    return p


def refuse_existing(paths: Iterable[Path], overwrite: bool) -> None:
    """Raise FileExistsError naming the first of ``paths`` that exists, unless ``overwrite``."""
    for p in paths:
        if p.is_dir():
            raise IsADirectoryError(errno.EISDIR, f"{p} is a folder, not a file to write", str(p))
        if not overwrite and (p.exists() or p.is_symlink()):
            raise ExportExistsError(
                errno.EEXIST, f"{p} exists; pass overwrite (--overwrite) to replace it", str(p)
            )


def _remove(fh: IO[bytes], tmp: str) -> None:
    try:
        fh.close()
    except OSError:
        pass
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass


class AtomicFile:
    """A binary file written under a temporary name beside ``path``, renamed onto it by
    :meth:`commit`; :meth:`abort` (or any exception inside ``with``) removes it.

    ``path`` is refused when it exists unless ``overwrite`` (checked at the start and, without
    ``overwrite``, again at the rename, which never replaces a file that appeared meanwhile).
    """

    def __init__(self, path: str | os.PathLike, overwrite: bool = False):
        self.path = Path(path)
        self.overwrite = overwrite
        refuse_existing([self.path], overwrite)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(
                prefix="." + self.path.name + ".", suffix=".part", dir=self.path.parent
            )
        except OSError as e:
            raise _named(self.path, e) from e
        self.tmp = Path(tmp)
        self.file: IO[bytes] = os.fdopen(fd, "wb")
        self._cleanup = weakref.finalize(self, _remove, self.file, tmp)

    @property
    def done(self) -> bool:
        """Whether the file was committed or aborted."""
        return not self._cleanup.alive

    def write(self, data: bytes) -> int:
        """Write ``data``; an OS error removes the temporary file and names ``path``."""
        try:
            return self.file.write(data)
        except BaseException as e:
            self.abort()
            raise _named(self.path, e) from e

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
            raise _named(self.path, e) from e
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


def write_all(files: dict[Path, bytes], overwrite: bool = False) -> list[Path]:
    """Write several files together: all of them refused, or all written to temporary names
    first and then renamed (a failure on any removes every temporary file)."""
    refuse_existing(files, overwrite)
    pending = [AtomicFile(p, overwrite) for p in files]
    try:
        for f, data in zip(pending, files.values()):
            f.write(data)
        return [f.commit() for f in pending]
    finally:
        for f in pending:
            f.abort()  # no-op for committed files
