"""Small file helpers: the one atomic writer of evgrid (:class:`AtomicFile`: a temporary file
next to the target, then a rename), JSON.

* A file is written under a temporary name in its own folder (``.NAME.XXXX.part``) and renamed
  onto its final name only when complete, so a reader never sees half a file under the final
  name. On any exception, KeyboardInterrupt included, the temporary file is removed; a writer
  that is dropped without :meth:`AtomicFile.commit` removes it too (garbage collection or the
  interpreter's exit).
* Every error names the file it is about (a full disk says which file).
* Files read whole (configs, rigs, JSON tables) are read through :func:`read_bounded`: at most
  a limit of bytes per kind of file (:data:`READ_LIMITS`), whatever size the file reports (a
  device such as ``/dev/zero`` reports 0 and never ends); :func:`load_json_bounded` also turns
  JSON nested too deep for Python's parser, or an integer too long for ``int``, into one line
  naming the file.
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import stat
import sys
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
    "InputFileError",
    "READ_LIMITS",
    "TargetExistsError",
    "atomic_open",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "jsonable",
    "load_json_bounded",
    "read_bounded",
    "refuse_existing",
    "size_text",
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
    if isinstance(e, NotAFolderError):
        return e  # make_folder's own one line
    if isinstance(e, OSError) and not isinstance(e, (FileWriteError, FileExistsError)):
        return FileWriteError(path, e)
    return e


class NotAFolderError(NotADirectoryError):
    """A folder to make whose path runs through a file; the message names both."""

    def __str__(self) -> str:
        return str(self.strerror)


def make_folder(folder: str | os.PathLike) -> Path:
    """``folder`` and its parents, made where missing; a path through a file is refused naming
    that file (mkdir's own words are ``File exists`` or ``Not a directory``, naming neither)."""
    folder = Path(folder)
    for p in (folder, *folder.parents):
        if p.exists() or p.is_symlink():
            if not p.is_dir():
                why = "is a file, not a folder" if p == folder else f"cannot be made: {p} is a file"
                raise NotAFolderError(errno.ENOTDIR, f"{folder} {why}", str(p))
            break
    folder.mkdir(parents=True, exist_ok=True)
    return folder


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
            make_folder(self.path.parent)
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


# --- files read whole --------------------------------------------------------------------------

#: The most bytes a file of each kind may hold when it is read whole. A config or rig of evgrid
#: is a few kB; nuScenes' largest table (v1.0-trainval's ``sample_data.json``) is some hundred
#: MB, so the tables get 4 GiB. Past the limit the file is refused before it is parsed: a
#: recording passed as ``--config`` by mistake is not read into memory.
READ_LIMITS: dict[str, int] = {
    "config": 16 * 2**20,
    "rig": 16 * 2**20,
    "nuScenes table": 4 * 2**30,
}


class InputFileError(ValueError):
    """A file read whole is too large, nested too deep or holds a value Python cannot read;
    the message names the file."""


def size_text(n: float) -> str:
    """``n`` bytes in the largest binary unit below it (``16 MiB``, ``2.73 PiB``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    raise AssertionError  # unreachable


def read_bounded(path: str | os.PathLike, kind: str, limit: int | None = None) -> bytes:
    """The bytes of ``path``, a file of ``kind`` (a key of :data:`READ_LIMITS`), or
    :class:`InputFileError` when it holds more than ``limit`` bytes (default: the kind's limit).

    A regular file's reported size is checked first; anything else (a device, a pipe) is read
    up to ``limit + 1`` bytes, as its reported size says nothing.
    """
    limit = READ_LIMITS[kind] if limit is None else limit
    too_big = (
        f"{path}: more than {size_text(limit)}, the most a {kind} file may hold; is it the "
        f"right file?"
    )
    with open(path, "rb") as f:
        st = os.fstat(f.fileno())
        if stat.S_ISREG(st.st_mode) and st.st_size > limit:
            raise InputFileError(too_big + f" (it holds {size_text(st.st_size)})")
        data = f.read(limit + 1)
    if len(data) > limit:
        raise InputFileError(too_big)
    return data


class _LongInteger(ValueError):
    def __init__(self, digits: str):
        super().__init__(digits)
        self.digits = digits


def _parse_int(s: str) -> int:
    limit = sys.get_int_max_str_digits() if hasattr(sys, "get_int_max_str_digits") else 0
    if limit and len(s.lstrip("-")) > limit:
        raise _LongInteger(s)
    return int(s)


def _line_col(text: str, pos: int) -> str:
    line = text.count("\n", 0, pos) + 1
    return f"line {line} column {pos - (text.rfind(chr(10), 0, pos) + 1) + 1}"


def load_json_bounded(path: str | os.PathLike, kind: str, limit: int | None = None) -> Any:
    """The JSON value of ``path`` read by :func:`read_bounded`; :class:`InputFileError` naming
    the file for a file too large, not UTF-8, nested deeper than Python's parser goes (its
    recursion limit, about a thousand levels), or holding an integer of more digits than
    Python converts (4300); ``json.JSONDecodeError`` (a ``ValueError``) for invalid JSON."""
    text_bytes = read_bounded(path, kind, limit)
    try:
        text = text_bytes.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputFileError(f"{path}: not UTF-8 text (byte {e.start}); is it the right file?")
    try:
        return json.loads(text, parse_int=_parse_int)
    except RecursionError:
        depth = _max_depth(text)
        raise InputFileError(
            f"{path}: JSON nested {depth} levels deep, deeper than Python's JSON parser reads "
            f"(about {sys.getrecursionlimit()}); a {kind} file nests a few levels"
        ) from None
    except _LongInteger as e:
        pos = text.find(e.digits)
        where = _line_col(text, pos) if pos >= 0 else "somewhere"
        raise InputFileError(
            f"{path}: an integer of {len(e.digits.lstrip('-'))} digits at {where}, more than "
            f"the {sys.get_int_max_str_digits()} Python reads"
        ) from None


def _max_depth(text: str) -> int:
    """The deepest nesting of ``[``/``{`` in JSON ``text`` (brackets inside strings ignored)."""
    body = re.sub(r'"(?:[^"\\]|\\.)*"', '""', text)
    opens = np.frombuffer(body.encode(), dtype=np.uint8)
    step = np.isin(opens, (ord("["), ord("{"))).astype(np.int64) - np.isin(
        opens, (ord("]"), ord("}"))
    )
    return int(np.cumsum(step).max(initial=0))
