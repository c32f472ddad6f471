"""Atomic file output: every result file of gr_graph is written through here.

A file is written to a temporary sibling in the same directory, flushed to disk, and
renamed over the target with :func:`os.replace`, so a reader (or a resumed run) sees either
the old file or the complete new one, never a torn write. On any error the temporary file
is removed and the target is left as it was.
"""

from __future__ import annotations

import errno
import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

PathLike = str | os.PathLike[str]


def default_mode(directory: bool = False) -> int:
    """The mode ``open()`` (or ``mkdir``) would give a new file (directory) under the umask."""
    return (0o777 if directory else 0o666) & ~_umask()


def _umask() -> int:
    """The process's umask: read from ``/proc/self/status`` where Linux gives it, since setting it
    to learn it (the only portable way) would briefly give files made by other threads mode 0666."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    umask = os.umask(0)
    os.umask(umask)
    return umask


def fsync_file(path: PathLike) -> None:
    """Flush a written file's data to the disk."""
    with open(path, "rb+") as fh:
        os.fsync(fh.fileno())


def fsync_directory(directory: PathLike) -> None:
    """Flush ``directory``'s entries (files created, renamed or removed in it) to the disk.

    File systems that cannot (``EINVAL``: some network and FUSE file systems) are skipped."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: PathLike, fsync: bool = True) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write; rename it onto ``path`` on success.

    The temporary name keeps ``path``'s suffix, so writers that pick a format from the
    suffix (``savefig``, ``np.save``) behave as for ``path`` itself. The file gets the mode
    a plain ``open()`` would give it. ``fsync=False`` skips flushing the file to the disk
    before the rename (for caches whose readers check what they read: after a power loss the
    file may be empty, never half-replaced by another).

    An ``OSError`` while the file is made, written or renamed (a full disk, a file size limit, no
    permission) is raised as the same kind of error (type and ``errno``) naming ``path``; one about
    another file (``filename`` set to it) or of another kind (a network's) passes unchanged.
    """
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=target.suffix, dir=target.parent)
    except OSError as exc:
        raise _naming(exc, target) from exc
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if fsync:
            fsync_file(tmp)
        os.chmod(tmp, default_mode())  # mkstemp makes 0600; results get the usual mode
        os.replace(tmp, target)
        if fsync:
            fsync_directory(target.parent)  # the rename itself survives a power loss
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if not _about_writing(exc, tmp) or str(target) in str(exc) or str(exc.strerror).startswith("cannot write "):
            raise  # about another file or something else (an input, a network), or naming a file already
        raise _naming(exc, target) from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


#: errno values of a ``write`` that failed for want of room, permission or a working disk (path errors such
#: as ENOENT come with a file name, and are about the file they name)
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EACCES, errno.EPERM, errno.EROFS, errno.EIO})


def _about_writing(exc: OSError, tmp: Path) -> bool:
    """Whether ``exc`` is about writing the temporary file: raised on it (``filename``); with no file named,
    an errno of a failed write (a full disk in ``write``), or a plain ``OSError`` without errno (a writer's
    own, e.g. an image encoder's). A network's error (an errno of its own, or a subclass such as URLError)
    or another file's is not."""
    if exc.filename is not None:
        return str(exc.filename) == str(tmp)
    if exc.errno is None:
        return type(exc) is OSError
    return exc.errno in _WRITE_ERRNOS


def _naming(exc: OSError, target: Path) -> OSError:
    """``exc`` (a full disk, a file size limit, a folder that is a file) as the same kind of error, naming
    ``target``: the temporary sibling written in its place means nothing to the user."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    message = f"cannot write {target}: {reason}"
    try:
        return type(exc)(exc.errno, message) if exc.errno is not None else type(exc)(message)
    except TypeError:  # a subclass with its own constructor
        return OSError(exc.errno, message)


def atomic_write_bytes(path: PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; return the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8, ``\\n`` line ends) to ``path`` atomically; return the path."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
    return Path(path)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def atomic_write_json(path: PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (numpy scalars and arrays allowed) atomically."""
    return atomic_write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def read_json_or_none(path: PathLike) -> Any:
    """The JSON in ``path``, or None when the file is missing or not valid JSON (e.g. cut short, or
    bytes that are not text)."""
    p = Path(path)
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None


def atomic_save_npz(path: PathLike, **arrays: np.ndarray) -> Path:
    """``np.savez_compressed`` to ``path`` atomically; return the path."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return Path(path)


def atomic_savefig(fig: Any, path: PathLike, **savefig_kwargs: Any) -> Path:
    """``fig.savefig`` to ``path`` atomically (format from the suffix); return the path."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, **savefig_kwargs)
    return Path(path)
