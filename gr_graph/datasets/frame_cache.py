"""``CachedFrames``: a view of a sequence that keeps every frame it reads on disk.

The learning rounds read every frame again (round r >= 1 densifies the scans round 0 read, and
recomputes the predictions of a loop's older frame), and so does the experiment harness's
KISS-ICP baseline. A synthetic frame is made by ray casting (0.07 s a 16-channel frame of the
``kitti`` preset on the reference machine), and once a round has freed the synthetic town
(about 2 GB) the next read builds it again. Read back from disk a frame costs milliseconds and
needs no town.

Frames are stored as they were made, uncompressed and in their own dtypes (``frame_<i>.npz``:
points, intensity, ring and per-point times when present, and a header of index, timestamp,
ring count and dropped non-finite points), so a frame read back is bit-identical to the one
first read: a run with the cache gives the same poses as a run without it
(``tests/test_frame_cache.py``). Writes are atomic. A file that cannot be read back (e.g.
truncated) is logged, counted in :attr:`CachedFrames.unreadable` and made again from the
parent; a frame that cannot be stored (e.g. a full disk) is logged, counted in
:attr:`CachedFrames.write_errors`, and the run goes on; below :data:`DISK_RESERVE` of free disk no
frame is stored (:attr:`CachedFrames.not_stored_low_disk`), so the run's results keep their room. ``key`` names what the frames depend on
(the pipeline passes a hash of the data, sensor and seed settings and the code's commit): a
directory written under another key is emptied first.

The pipeline enables the cache by default only for sequences that make their frames
(:func:`makes_frames`: synthetic worlds) and only when learning rounds will read them again;
real recordings are read from their files as they are (``data.frame_cache``).
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import threading
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.atomic import atomic_path, atomic_write_json, read_json_or_none
from gr_graph.datasets.base import DatasetError, LidarFrame, LidarSequence, check_index, find_in_chain, inherit_sweep_attributes

log = logging.getLogger(__name__)

__all__ = ["CachedFrames", "makes_frames", "remove_stale_frame_cache"]

META = "cache.json"
#: free disk the cache always leaves for the run's own results [bytes]
DISK_RESERVE = 2 * 1024**3


def makes_frames(sequence: Any) -> bool:
    """Whether ``sequence`` (or a sequence it is a view of) makes its frames instead of reading
    them from files: it has a ``release_cache()`` method (the synthetic worlds)."""
    return find_in_chain(sequence, "release_cache") is not None


class CachedFrames:
    """A view of ``parent`` whose frames are read once from the parent and then from ``directory``.

    Parameters
    ----------
    parent : LidarSequence
        The sequence whose frames are cached.
    directory : path
        Where the frames go (created; emptied when it holds frames of another ``key``).
    key : str
        What the frames depend on; stored in ``directory/cache.json``.
    open_now : bool
        Open the folder now (:meth:`open`); False: at :meth:`open` or the first read.
    """

    def __init__(self, parent: LidarSequence, directory: str | Path, key: str, open_now: bool = True) -> None:
        self.parent = parent
        self.directory = Path(directory)
        self.key = str(key)
        self.name = parent.name
        self.timestamps = parent.timestamps
        self.gt_poses = parent.gt_poses
        self.T_cam_velo = parent.T_cam_velo
        inherit_sweep_attributes(self, parent)
        self.hits = 0  # frames read from the cache
        self.misses = 0  # frames read from the parent (and written)
        self.unreadable = 0  # cached files that could not be read back (made again)
        self.write_errors = 0  # frames that could not be stored (e.g. a full disk; made again when read again)
        self.not_stored_low_disk = 0  # frames not stored to keep DISK_RESERVE free (made again when read again)
        self._lock = threading.Lock()
        self._opened = False
        if open_now:
            self.open()

    def open(self) -> None:
        """Create the folder (emptying one of another key) unless done already; the first read does it
        too (``open_now=False`` leaves the folder untouched until then: the pipeline opens it once the
        resume checks passed)."""
        with self._lock:
            if not self._opened:
                self._open_directory()
                self._opened = True

    def _open_directory(self) -> None:
        meta = read_json_or_none(self.directory / META)
        expected = {"key": self.key, "n_frames": len(self.parent), "name": self.parent.name}
        if meta != expected and self.directory.exists():
            _check_only_cache_files(self.directory)
            if meta is not None:
                log.info("frame cache %s holds frames of another sequence or configuration: emptied", self.directory)
            shutil.rmtree(self.directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        if meta != expected:
            atomic_write_json(self.directory / META, expected)

    def __len__(self) -> int:
        return len(self.parent)

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]

    def path(self, i: int) -> Path:
        """The file of frame position ``i``."""
        return self.directory / f"frame_{i:06d}.npz"

    def __getitem__(self, index: int) -> LidarFrame:
        if not self._opened:
            self.open()
        i = check_index(index, len(self), self.name)
        p = self.path(i)
        if p.is_file():
            frame = self._load(p, i)
            if frame is not None:
                with self._lock:
                    self.hits += 1
                return frame
        frame = self.parent[i]
        if not self._room_for_more():
            with self._lock:
                self.misses += 1
            return frame
        try:
            self._store(p, i, frame)
        except OSError as exc:  # e.g. a full disk: the run goes on, this frame is made again when read again
            with self._lock:
                self.write_errors += 1
                first = self.write_errors == 1
            log.log(logging.WARNING if first else logging.DEBUG, "frame cache: frame %d not stored in %s (%s: %s)%s",
                    i, self.directory, type(exc).__name__, exc, "; further failures are counted" if first else "")
        with self._lock:
            self.misses += 1
        return frame

    def _room_for_more(self) -> bool:
        """Whether the disk keeps :data:`DISK_RESERVE` free beside another frame; when not, the frame is not
        stored (counted in :attr:`not_stored_low_disk`, said once): the cache must never take the room the
        run's own results need (a 64-channel sequence caches about 16 GB)."""
        try:
            free = shutil.disk_usage(self.directory).free
        except OSError:  # cannot tell: store, and let a failed write be counted as usual
            return True
        if free >= DISK_RESERVE:
            return True
        with self._lock:
            self.not_stored_low_disk += 1
            first = self.not_stored_low_disk == 1
        if first:
            log.warning("frame cache: less than %.1f GB free on %s: frames are no longer stored (made again when "
                        "read again), so that the run's results still fit", DISK_RESERVE / 1e9, self.directory)
        return False

    def _store(self, p: Path, i: int, frame: LidarFrame) -> None:
        arrays: dict[str, np.ndarray] = {
            "header": np.array([i, frame.index, frame.timestamp, frame.n_rings, frame.dropped_nonfinite], np.float64),
            "points": frame.points, "intensity": frame.intensity}
        if frame.ring is not None:
            arrays["ring"] = frame.ring
        if frame.time is not None:
            arrays["time"] = frame.time
        with atomic_path(p, fsync=False) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)

    def _load(self, p: Path, i: int) -> LidarFrame | None:
        try:
            with np.load(p) as z:
                header = z["header"]
                if len(header) != 5 or int(header[0]) != i:
                    raise ValueError(f"header {header.tolist()} is not frame position {i}'s")
                return LidarFrame(index=int(header[1]), timestamp=float(header[2]), points=z["points"],
                                  intensity=z["intensity"], ring=z["ring"] if "ring" in z else None,
                                  n_rings=int(header[3]), dropped_nonfinite=int(header[4]),
                                  time=z["time"] if "time" in z else None)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
            with self._lock:
                self.unreadable += 1
            log.warning("frame cache: %s cannot be read back (%s: %s); the frame is made again", p,
                        type(exc).__name__, exc)
            return None

    def stats(self) -> dict[str, Any]:
        """Counts of this view: frames read from the cache, made by the parent, unreadable files,
        frames that could not be stored."""
        with self._lock:
            return {"directory": str(self.directory), "hits": self.hits, "misses": self.misses,
                    "unreadable": self.unreadable, "write_errors": self.write_errors,
                    "not_stored_low_disk": self.not_stored_low_disk}

    def remove(self) -> None:
        """Delete the cached frames (the view still works: frames are made again); a folder holding
        anything else is left as it is (logged)."""
        try:
            _check_only_cache_files(self.directory)
        except DatasetError as exc:
            log.warning("frame cache not removed: %s", exc)
            return
        shutil.rmtree(self.directory, ignore_errors=True)
        log.info("frame cache %s removed (%s)", self.directory, json.dumps(self.stats()))


def remove_stale_frame_cache(directory: Path) -> bool:
    """Delete ``directory`` when it is a frame cache (its ``cache.json`` there, and nothing but the
    cache's files) that an earlier, interrupted run left; whether it did. Anything else is left."""
    directory = Path(directory)
    if not (directory / META).is_file():
        return False
    try:
        _check_only_cache_files(directory)
    except DatasetError:
        return False
    shutil.rmtree(directory, ignore_errors=True)
    return not directory.exists()


_CACHE_FILE = re.compile(r"(frame_\d+\.npz|cache\.json|\.(frame_\d+|cache)\..+\.(npz|json))")
"""Names of a cache's files: its frames, its ``cache.json`` and their temporary names while written."""


def _check_only_cache_files(directory: Path) -> None:
    """Refuse to delete ``directory`` when it holds anything but a frame cache's files (e.g. a
    ``frames`` folder of the user's own in ``--out``).

    Raises
    ------
    DatasetError
        Naming the folder and one file that is not the cache's.
    """
    if not directory.is_dir():
        if directory.exists():
            raise DatasetError(f"{directory}: the frame cache's place holds a file; move it or pick another --out")
        return
    other = next((p for p in directory.iterdir() if not (p.is_file() and _CACHE_FILE.fullmatch(p.name))), None)
    if other is not None:
        raise DatasetError(f"{directory}: the frame cache's folder holds {other.name}, not a cached frame; it is not "
                           "deleted: move it or pick another --out (or set data.frame_cache: false)")
