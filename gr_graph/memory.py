"""The memory M = ({S_k}, T̂, C) of the paper, stored on disk and read memory-mapped.

SLAM writes one memory per round; the trainer reads it. A memory is a directory::

    meta.json          {"format": "gr_graph.memory", "version": 1, "n_scans", "n_edges",
                        "n_points", "n_correspondences", ...free-form "info"}
    points.npy         float32 (P, 3)   the stored scans' points, concatenated, LiDAR frame
    scan_offsets.npy   int64   (K+1,)   scan k is points[scan_offsets[k]:scan_offsets[k+1]]
    poses.npy          float64 (K,4,4)  optimised T_w_velo of every scan
    edges.npy          int64   (E, 2)   scan pairs (k, l): P = S_k (source), Q = S_l (target)
    edge_kind.npy      uint8   (E,)     0 = odometry, 1 = loop closure
    edge_T.npy         float64 (E,4,4)  T̂_kl, maps points of scan k into the frame of scan l
                                        (T̂_kl = T_w_l⁻¹ T_w_k of the optimised trajectory)
    edge_H.npy         float64 (E,6,6)  information (Hessian) of T̂_kl, gtsam order [ω, v]
    corr.npy           int32   (C, 2)   correspondences (i, j): point i of S_k, point j of S_l,
                                        indices local to each scan
    corr_offsets.npy   int64   (E+1,)   edge e owns corr[corr_offsets[e]:corr_offsets[e+1]]

A memory is written into a temporary sibling directory, flushed to the disk and renamed into
place, so a reader never sees a half-written memory and a failed write leaves the earlier
memory in place (a process killed between the two renames leaves it as a hidden ``.old-*``
sibling, kept).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.atomic import default_mode, fsync_directory, fsync_file

log = logging.getLogger(__name__)

FORMAT_NAME = "gr_graph.memory"
FORMAT_VERSION = 1
EDGE_ODOMETRY = 0
EDGE_LOOP = 1

_ARRAYS = {
    "points": (np.float32, (None, 3)),
    "scan_offsets": (np.int64, (None,)),
    "poses": (np.float64, (None, 4, 4)),
    "edges": (np.int64, (None, 2)),
    "edge_kind": (np.uint8, (None,)),
    "edge_T": (np.float64, (None, 4, 4)),
    "edge_H": (np.float64, (None, 6, 6)),
    "corr": (np.int32, (None, 2)),
    "corr_offsets": (np.int64, (None,)),
}


class MemoryFormatError(ValueError):
    """A memory directory is missing, incomplete or inconsistent; the message says which part."""


@dataclass(frozen=True)
class Edge:
    """One scan pair of the memory, as handed to the trainer.

    Attributes
    ----------
    index : int
        Edge index in the memory.
    k, l : int
        Source scan (P = S_k) and target scan (Q = S_l).
    kind : int
        ``EDGE_ODOMETRY`` or ``EDGE_LOOP``.
    T : np.ndarray
        ``(4, 4)`` T̂_kl, mapping source points into the target frame.
    H : np.ndarray
        ``(6, 6)`` information of T̂_kl (gtsam tangent order [ω, v]).
    corr : np.ndarray
        ``(C, 2)`` int32 index pairs (i in S_k, j in S_l).
    """

    index: int
    k: int
    l: int
    kind: int
    T: np.ndarray
    H: np.ndarray
    corr: np.ndarray


@dataclass
class Memory:
    """A memory read from disk (arrays memory-mapped) or assembled in RAM before writing.

    Use :meth:`from_scans` to assemble one, :meth:`save` to write it atomically and
    :func:`load_memory` to read it back.
    """

    points: np.ndarray
    scan_offsets: np.ndarray
    poses: np.ndarray
    edges: np.ndarray
    edge_kind: np.ndarray
    edge_T: np.ndarray
    edge_H: np.ndarray
    corr: np.ndarray
    corr_offsets: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_scans(
        cls,
        scans: list[np.ndarray],
        poses: np.ndarray,
        edges: list[tuple[int, int]],
        edge_kind: list[int],
        edge_T: list[np.ndarray],
        edge_H: list[np.ndarray],
        corr: list[np.ndarray],
        info: dict[str, Any] | None = None,
    ) -> "Memory":
        """Assemble a memory from per-scan point arrays and per-edge lists.

        Parameters
        ----------
        scans : list of (N_k, 3) arrays
            Stored points of every scan (LiDAR frame).
        poses : (K, 4, 4) array
            Optimised ``T_w_velo`` of every scan.
        edges, edge_kind, edge_T, edge_H, corr : lists of length E
            Per edge: ``(k, l)``, kind, T̂_kl ``(4, 4)``, information ``(6, 6)`` and
            ``(C_e, 2)`` correspondence index pairs.
        info : dict, optional
            Free-form JSON-serialisable metadata (round, channels, config...).
        """
        sizes = [len(s) for s in scans]
        n_corr = [len(c) for c in corr]
        mem = cls(
            points=np.concatenate([np.asarray(s, np.float32).reshape(-1, 3) for s in scans])
            if scans
            else np.zeros((0, 3), np.float32),
            scan_offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
            poses=np.asarray(poses, np.float64).reshape(-1, 4, 4),
            edges=np.asarray(edges, np.int64).reshape(-1, 2),
            edge_kind=np.asarray(edge_kind, np.uint8).reshape(-1),
            edge_T=np.asarray(edge_T, np.float64).reshape(-1, 4, 4),
            edge_H=np.asarray(edge_H, np.float64).reshape(-1, 6, 6),
            corr=np.concatenate([np.asarray(c, np.int32).reshape(-1, 2) for c in corr])
            if corr
            else np.zeros((0, 2), np.int32),
            corr_offsets=np.concatenate([[0], np.cumsum(n_corr)]).astype(np.int64),
            info=dict(info or {}),
        )
        mem.validate()
        return mem

    # ------------------------------------------------------------------ access
    @property
    def n_scans(self) -> int:
        """Number of scans K."""
        return len(self.scan_offsets) - 1

    @property
    def n_edges(self) -> int:
        """Number of scan pairs E."""
        return len(self.edges)

    @property
    def flagged_edges(self) -> frozenset[int]:
        """Numbers of the edges whose registration failed in SLAM (``info["flagged_edges"]``,
        :mod:`gr_graph.memory_builder`): their T̂ and correspondences come from the fallback
        guess. Numbers outside ``0 .. E-1`` are ignored."""
        return frozenset(int(e) for e in (self.info or {}).get("flagged_edges", []) if 0 <= int(e) < self.n_edges)

    def scans(self) -> list[np.ndarray]:
        """Every scan's points, as :meth:`scan` gives them (views: memory-mapped when loaded so, no copy)."""
        return [self.scan(k) for k in range(self.n_scans)]

    def scan(self, k: int) -> np.ndarray:
        """Points of scan ``k`` as a (memory-mapped) ``(N_k, 3)`` float32 view."""
        if not 0 <= k < self.n_scans:
            raise IndexError(f"scan {k} out of range for {self.n_scans} scans")
        return self.points[self.scan_offsets[k] : self.scan_offsets[k + 1]]

    def edge(self, e: int) -> Edge:
        """The ``e``-th scan pair with its pose, information and correspondences."""
        if not 0 <= e < self.n_edges:
            raise IndexError(f"edge {e} out of range for {self.n_edges} edges")
        k, l = (int(v) for v in self.edges[e])
        return Edge(
            index=e,
            k=k,
            l=l,
            kind=int(self.edge_kind[e]),
            T=np.array(self.edge_T[e]),
            H=np.array(self.edge_H[e]),
            corr=np.array(self.corr[self.corr_offsets[e] : self.corr_offsets[e + 1]]),
        )

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Check shapes, dtypes, offsets and index ranges; raise :class:`MemoryFormatError`."""
        for name, (dtype, shape) in _ARRAYS.items():
            arr = getattr(self, name)
            if arr.dtype != dtype:
                raise MemoryFormatError(f"{name}: dtype {arr.dtype}, expected {np.dtype(dtype)}")
            if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
                raise MemoryFormatError(f"{name}: shape {arr.shape}, expected {shape}")
        K, E = self.n_scans, self.n_edges
        if K < 0 or self.scan_offsets[0] != 0 or self.scan_offsets[-1] != len(self.points):
            raise MemoryFormatError("scan_offsets do not span points")
        if np.any(np.diff(self.scan_offsets) < 0):
            raise MemoryFormatError("scan_offsets are not non-decreasing")
        if len(self.poses) != K:
            raise MemoryFormatError(f"poses: {len(self.poses)} poses for {K} scans")
        for name in ("edge_kind", "edge_T", "edge_H"):
            if len(getattr(self, name)) != E:
                raise MemoryFormatError(f"{name}: {len(getattr(self, name))} rows for {E} edges")
        if len(self.corr_offsets) != E + 1 or self.corr_offsets[0] != 0 or self.corr_offsets[-1] != len(self.corr):
            raise MemoryFormatError("corr_offsets do not span corr")
        if np.any(np.diff(self.corr_offsets) < 0):
            raise MemoryFormatError("corr_offsets are not non-decreasing")
        if E and (self.edges.min() < 0 or self.edges.max() >= K):
            raise MemoryFormatError(f"edges reference scans outside 0..{K - 1}")
        sizes = np.diff(self.scan_offsets)
        for e in range(E):
            c = self.corr[self.corr_offsets[e] : self.corr_offsets[e + 1]]
            if len(c) == 0:
                continue
            k, l = self.edges[e]
            if c[:, 0].min() < 0 or c[:, 0].max() >= sizes[k] or c[:, 1].min() < 0 or c[:, 1].max() >= sizes[l]:
                raise MemoryFormatError(f"edge {e} ({k}, {l}): correspondence index out of range")
        for name in ("points", "poses", "edge_T", "edge_H"):
            arr = getattr(self, name)
            step = 1 << 18  # rows per check: no full-size temporary for a large memory-mapped array
            if not all(np.isfinite(arr[i:i + step]).all() for i in range(0, len(arr), step)):
                raise MemoryFormatError(f"{name}: non-finite values")

    # ------------------------------------------------------------------ I/O
    def save(self, directory: str | os.PathLike[str]) -> Path:
        """Write the memory atomically into ``directory`` (replacing an existing memory).

        The arrays are written into a temporary sibling directory which is then renamed
        into place; an existing memory is only removed after the new one is complete.
        """
        self.validate()
        with _atomic_directory(directory) as tmp:
            for name in _ARRAYS:
                np.save(tmp / f"{name}.npy", np.ascontiguousarray(getattr(self, name)))
            _write_meta(tmp, self.n_scans, self.n_edges, len(self.points), len(self.corr), self.info)
        return Path(directory)


@contextmanager
def _atomic_directory(directory: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary sibling of ``directory`` to fill; on success rename it into place (an
    existing directory is removed only after the new one is complete), on failure delete it."""
    target = Path(directory)
    target.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_siblings(target)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        tmp.chmod(default_mode(directory=True))  # mkdtemp makes 0700
        yield tmp
        for f in tmp.iterdir():  # on the disk before the rename: never a complete-looking memory of empty files
            fsync_file(f)
        fsync_directory(tmp)
        old = None
        if target.exists():  # a unique name: a folder left by a killed process may hold this pid's
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
            os.replace(target, old)
        try:
            os.replace(tmp, target)
        except BaseException:
            if old is not None:  # the earlier memory back in its place
                os.replace(old, target)
            raise
        fsync_directory(target.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


STALE_SIBLING_S = 3600.0
"""Temporary siblings (``.<name>.tmp-*``, ``.<name>.old-*``) of a memory older than this [s] are
left by a killed process (a memory is written in minutes at most) and removed at the next write."""


def _remove_stale_siblings(target: Path) -> None:
    """Delete the temporary siblings of ``target`` that a killed process left behind (up to a
    memory's size each), logged; an ``.old-*`` one is kept while ``target`` is missing (the kill
    came between the two renames: it holds the only copy)."""
    now = time.time()
    for kind in ("tmp", "old"):
        for p in target.parent.glob(f".{target.name}.{kind}-*"):
            try:
                stale = p.is_dir() and now - p.stat().st_mtime > STALE_SIBLING_S
            except FileNotFoundError:
                continue
            if stale and (kind == "tmp" or target.exists()):
                log.warning("%s: left by an interrupted write of %s; removed", p, target)
                shutil.rmtree(p, ignore_errors=True)


def _write_meta(directory: Path, n_scans: int, n_edges: int, n_points: int, n_corr: int,
                info: dict[str, Any]) -> None:
    meta = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "n_scans": int(n_scans), "n_edges": int(n_edges),
            "n_points": int(n_points), "n_correspondences": int(n_corr), "info": info}
    (directory / "meta.json").write_text(json.dumps(meta, indent=2))


def _write_concatenated(path: Path, parts: Sequence[np.ndarray], dtype: Any, width: int) -> np.ndarray:
    """Write ``parts`` (each ``(n_i, width)``) one after another into the ``.npy`` file ``path``
    without concatenating them in RAM; return the offsets ``(len(parts) + 1,)`` int64."""
    for k, p in enumerate(parts):
        if np.ndim(p) != 2 or np.shape(p)[1] != width:
            raise ValueError(f"{path.name}: part {k} has shape {np.shape(p)}, expected (n, {width})")
    sizes = [len(p) for p in parts]
    offsets = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)]).astype(np.int64)
    dt = np.dtype(dtype)
    header = {"descr": np.lib.format.dtype_to_descr(dt), "fortran_order": False, "shape": (int(offsets[-1]), width)}
    # written, not memory-mapped: a full disk is then an OSError (the memory's temporary folder is
    # removed), not a SIGBUS that kills the process
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        for p in parts:
            if len(p):
                fh.write(np.ascontiguousarray(np.asarray(p).reshape(-1, width), dtype=dt).tobytes())
    return offsets


def save_memory_from_scans(
    directory: str | os.PathLike[str],
    scans: Sequence[np.ndarray],
    poses: np.ndarray,
    edges: list[tuple[int, int]],
    edge_kind: list[int],
    edge_T: list[np.ndarray],
    edge_H: list[np.ndarray],
    corr: Sequence[np.ndarray],
    info: dict[str, Any] | None = None,
) -> "Memory":
    """Write a memory from per-scan and per-edge lists, streaming, atomically; read it back.

    Same arguments and result as ``Memory.from_scans(...).save(directory)``, but the points and
    correspondences go straight from the lists into the ``.npy`` files (plain writes): no
    concatenated copy of them is ever held in RAM (for a full KITTI sequence at 64 channels
    that copy is about 1 GB). The written memory is validated before it is renamed into place
    and returned memory-mapped (:func:`load_memory`).
    """
    with _atomic_directory(directory) as tmp:
        scan_offsets = _write_concatenated(tmp / "points.npy", scans, np.float32, 3)
        corr_offsets = _write_concatenated(tmp / "corr.npy", corr, np.int32, 2)
        small = {"scan_offsets": scan_offsets, "poses": np.asarray(poses, np.float64).reshape(-1, 4, 4),
                 "edges": np.asarray(edges, np.int64).reshape(-1, 2),
                 "edge_kind": np.asarray(edge_kind, np.uint8).reshape(-1),
                 "edge_T": np.asarray(edge_T, np.float64).reshape(-1, 4, 4),
                 "edge_H": np.asarray(edge_H, np.float64).reshape(-1, 6, 6), "corr_offsets": corr_offsets}
        for name, arr in small.items():
            np.save(tmp / f"{name}.npy", arr)
        _write_meta(tmp, len(scans), len(small["edges"]), int(scan_offsets[-1]), int(corr_offsets[-1]),
                    dict(info or {}))
        mem = load_memory(tmp)  # validates the files before they replace anything
    return mem  # its maps stay valid after the rename (POSIX)


def load_memory(directory: str | os.PathLike[str], mmap: bool = True) -> Memory:
    """Read a memory written by :meth:`Memory.save`; arrays are memory-mapped by default.

    Raises
    ------
    MemoryFormatError
        If the directory is missing, is not a gr_graph memory, or is inconsistent.
    """
    d = Path(directory)
    meta_path = d / "meta.json"
    if not meta_path.is_file():
        raise MemoryFormatError(f"{d}: not a gr_graph memory (no meta.json)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise MemoryFormatError(f"{meta_path}: unreadable JSON ({exc})") from exc
    if meta.get("format") != FORMAT_NAME or meta.get("version") != FORMAT_VERSION:
        raise MemoryFormatError(
            f"{meta_path}: format {meta.get('format')!r} v{meta.get('version')}, "
            f"expected {FORMAT_NAME!r} v{FORMAT_VERSION}"
        )
    arrays = {}
    for name in _ARRAYS:
        path = d / f"{name}.npy"
        if not path.is_file():
            raise MemoryFormatError(f"{d}: missing {path.name}")
        try:
            arrays[name] = np.load(path, mmap_mode="r" if mmap else None)
        except (ValueError, EOFError, OSError) as exc:  # EOFError: an empty file
            raise MemoryFormatError(f"{path}: unreadable ({type(exc).__name__}: {exc})") from exc
    mem = Memory(**arrays, info=meta.get("info", {}))
    mem.validate()
    if mem.n_scans != meta.get("n_scans") or mem.n_edges != meta.get("n_edges"):
        raise MemoryFormatError(f"{meta_path}: counts disagree with the arrays")
    return mem
