"""One process at a time in a cell's folder: a lock file beside it, ``ROOT/<table>/.<key>.lock``.

Cells are meant to be spread over processes and machines (``--cell K`` from a SLURM array, or a
whole table started twice on a shared ``--root``); two processes writing one cell's folder would
mix their rounds. The lock is :func:`gr_graph.folder_lock.folder_lock` on that file, held while the
cell runs (released when its process ends in any way; on NFS it holds across machines sharing the
root, where two locks of one process do not exclude each other: the harness runs a process's cells
one after another). The file stays (a few bytes, hidden) and names its last owner: host, process
id and start time, quoted when the cell is busy.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from gr_graph.folder_lock import FolderBusyError, folder_lock

__all__ = ["CellBusyError", "cell_lock", "lock_path"]


class CellBusyError(FolderBusyError):
    """Another process holds the cell's lock: the cell is being run elsewhere."""


def lock_path(cell_folder: str | Path) -> Path:
    """The lock file of the cell whose folder is ``cell_folder`` (``ROOT/<table>/<key>``): a hidden
    file beside the folder, so that clearing the folder for a new definition keeps the lock."""
    folder = Path(cell_folder)
    return folder.parent / f".{folder.name}.lock"


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
    with folder_lock(lock_path(cell_folder), str(cell_folder), CellBusyError) as path:
        yield path
