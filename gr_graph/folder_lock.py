"""One process at a time in a folder: an exclusive ``flock`` on a lock file, held while the work runs.

Used for a run's ``--out`` (:class:`gr_graph.pipeline.SlamPipeline`: ``<out>/.gr_graph.lock``; a
SLURM job requeued while its first attempt still runs, or one command started twice, would
otherwise mix their rounds in one folder) and for the harness's cells
(:mod:`gr_graph.experiments.cell_lock`). The operating system releases the lock when its process
ends in any way (finished, failed, killed, out of memory), so a dead run never leaves a stale
lock behind; on NFS, Linux carries it as a POSIX lock to the server, so it holds across machines
sharing the folder (there, unlike on a local disk, two locks of one process do not exclude each
other). A file system that takes no locks at all gives a warning and the work runs unlocked. The
file stays (a few bytes, hidden) and names its last owner: host, process id and start time,
quoted when the folder is busy.
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

__all__ = ["FolderBusyError", "folder_lock"]


log = logging.getLogger(__name__)

_NO_LOCKS = (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP, errno.EINVAL)
"""``flock`` errors of file systems without locks (NFS without lockd, Lustre mounted ``noflock``):
the work runs without one, with a warning, rather than failing."""


class FolderBusyError(RuntimeError):
    """Another process holds the folder's lock: the folder is being written by another run."""


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
def folder_lock(path: str | Path, what: str, busy: type[FolderBusyError] = FolderBusyError) -> Iterator[Path]:
    """Hold the exclusive lock of the file ``path`` (made, with its folder, when missing) while the
    block runs; yields ``path``.

    Raises
    ------
    FolderBusyError
        Or its subclass ``busy``, naming ``what`` (the folder it guards), the lock file and its owner,
        when another process holds it (on a local file system also another lock of this process on
        the same file: each takes its own open file).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except (BlockingIOError, PermissionError):  # EWOULDBLOCK; EACCES from some NFS servers
            raise busy(f"{what} is being run by {_owner_text(fd)} (lock {path}); wait for it, "
                       "or stop that run first") from None
        except OSError as exc:
            if exc.errno not in _NO_LOCKS:
                raise
            log.warning("%s: the file system takes no locks (%s); %s runs unlocked: do not start it twice",
                        path, exc.strerror, what)
        owner = {"host": socket.gethostname(), "pid": os.getpid(),
                 "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(owner).encode("utf-8"), 0)
        os.fsync(fd)
        yield path
    finally:
        os.close(fd)  # releases the lock
