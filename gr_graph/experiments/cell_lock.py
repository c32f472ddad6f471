"""One process at a time in a cell's folder: a lock file beside it, ``ROOT/<table>/.<key>.lock``.

Cells are meant to be spread over processes and machines (``--cell K`` from a SLURM array, or a
whole table started twice on a shared ``--root``); two processes writing one cell's folder would
mix their rounds. The lock is an exclusive ``flock`` on that file, held while the cell runs. The
operating system releases it when its process ends in any way (finished, failed, killed, out of
memory), so a dead run never leaves a stale lock behind; on NFS, Linux carries it as a POSIX
lock to the server, so it holds across machines sharing the root (there, unlike on a local disk,
two ``cell_lock`` of one process do not exclude each other; the harness runs a process's cells
one after another). A file system that takes no locks at all gives a warning and the cell runs
unlocked. The file stays (a few bytes, hidden) and names its last owner: host, process id and
start time, quoted when the cell is busy.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

__all__ = ["CellBusyError", "cell_lock", "lock_path"]


log = logging.getLogger(__name__)

_NO_LOCKS = (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP, errno.EINVAL)
"""``flock`` errors of file systems without locks (NFS without lockd, Lustre mounted ``noflock``):
the cell runs without one, with a warning, rather than every cell failing."""


class CellBusyError(RuntimeError):
    """Another process holds the cell's lock: the cell is being run elsewhere."""


def lock_path(cell_folder: str | Path) -> Path:
    """The lock file of the cell whose folder is ``cell_folder`` (``ROOT/<table>/<key>``): a hidden
    file beside the folder, so that clearing the folder for a new definition keeps the lock."""
    folder = Path(cell_folder)
    return folder.parent / f".{folder.name}.lock"


def _owner_text(fd: int) -> str:
    """Who holds the lock, from the file's content (read through ``fd``: opening the file a second
    time would release a POSIX lock this process held on it)."""
    raw = os.pread(fd, 4096, 0)
    try:
        owner = json.loads(raw.decode("utf-8"))
        return f"process {owner['pid']} on {owner['host']} since {owner['started_utc']}"
    except (UnicodeDecodeError, ValueError, KeyError, TypeError):
        return "a process that has not written its name yet"


@contextmanager
def cell_lock(cell_folder: str | Path) -> Iterator[Path]:
    """Hold the lock of the cell whose folder is ``cell_folder`` while the block runs; yields the
    lock file's path.

    Raises
    ------
    CellBusyError
        Naming the cell, the lock file and its owner, when another process holds it (on a local
        file system also another ``cell_lock`` of this process: each takes its own open file).
    """
    path = lock_path(cell_folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except (BlockingIOError, PermissionError):  # EWOULDBLOCK; EACCES from some NFS servers
            raise CellBusyError(f"{cell_folder} is being run by {_owner_text(fd)} (lock {path}); wait for it, "
                                "or stop that run first") from None
        except OSError as exc:
            if exc.errno not in _NO_LOCKS:
                raise
            log.warning("%s: the file system takes no locks (%s); the cell runs unlocked: do not start it twice",
                        path, exc.strerror)
        owner = {"host": socket.gethostname(), "pid": os.getpid(),
                 "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(owner).encode("utf-8"), 0)
        os.fsync(fd)
        yield path
    finally:
        os.close(fd)  # releases the lock
