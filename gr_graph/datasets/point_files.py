"""Readers of single point-cloud files: ``.bin`` (KITTI-style float32), ``.pcd``, ``.ply``, ``.npy``.

Every reader returns a :class:`~gr_graph.datasets.pointcloud2.DecodedCloud` (x, y, z and, when
the file has them, intensity, per-point time and ring) or raises a
:class:`~gr_graph.datasets.base.DatasetError` naming the file.

- ``.bin``: headerless float32 x,y,z,intensity (or x,y,z with ``point_format="xyz"``), checked
  by :mod:`gr_graph.datasets.point_layout`. A file written as float64 (``tofile`` of a float64
  array) is refused with a message saying so and how to convert it: read as float32, a
  float64 file has absurd values (``|v| > 1e10``) in more than 1 % of its values while read as
  float64 it holds plausible coordinates
  (:func:`gr_graph.datasets.point_layout.float64_bin_problem`, also applied to KITTI roots).
- ``.pcd``: PCL's format, ``DATA ascii`` and ``binary`` read here with every field (e.g.
  ``intensity``, ``ring``, ``t``); ``binary_compressed`` through open3d (x, y, z, intensity).
- ``.ply``: the ``vertex`` element (it must be the file's first element) of ASCII or binary
  (either byte order) files, every scalar property.
- ``.npy``: an ``(N, 3)`` / ``(N, 4)`` numeric array (x, y, z[, intensity]) or a structured array
  with fields ``x``, ``y``, ``z`` (and optionally ``intensity``, ``t``/``time``/``timestamp``, ``ring``).

**Empty files.** A cloud without points (an empty ``.bin``, a PCD with ``POINTS 0``, a PLY with
``element vertex 0``, an empty ``.npy`` array, or a 0-byte ``.pcd``/``.ply``/``.npy``) is read as
an empty cloud, not an error: the sequence turns it into an empty frame, which the pipeline
marks unusable (:class:`~gr_graph.datasets.folder.FolderSequence` logs it). A truncated or
corrupt file (header cut off, fewer data bytes than the header promises) is still an error.

**Non-finite intensity.** Points with a non-finite coordinate or exactly at the origin (an organized
cloud's beam without a return) are dropped and counted, and a
non-finite intensity at a finite point is replaced by 0 with the count logged
(:func:`gr_graph.datasets.pointcloud2.decode_structured`, as for bags); non-finite per-point
times remain an error.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.pointcloud2 import DecodedCloud, decode_structured, empty_cloud

log = logging.getLogger(__name__)

POINT_FILE_SUFFIXES = (".bin", ".pcd", ".ply", ".npy")
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8",
              ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8"}
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_MAX_HEADER_LINES = 200


def read_point_file(path: str | Path, point_format: str = "xyzi") -> DecodedCloud:
    """Read one point file by its suffix (see the module docstring).

    Parameters
    ----------
    path : path
    point_format : {"xyzi", "xyz"}
        Layout of ``.bin`` files only.

    Returns
    -------
    DecodedCloud
        Empty (no points) for an empty or 0-byte file; non-finite intensities set to 0 (logged).

    Raises
    ------
    DatasetError
        Naming the file: missing, unknown suffix, truncated or corrupt, wrong field layout, a
        ``.bin`` in another layout (:mod:`~gr_graph.datasets.point_layout`) or written as float64.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise DatasetError(f"{path}: point file not found")
    try:
        if suffix in (".pcd", ".ply", ".npy") and path.stat().st_size == 0:
            return empty_cloud()  # a 0-byte file (e.g. a recorder that crashed): an empty frame
        if suffix == ".bin":
            from gr_graph.datasets.kitti import read_velodyne_bin

            raw = read_velodyne_bin(path, point_format).astype(np.float64)
            cloud = decode_structured(_columns(raw, ["x", "y", "z", "intensity"]), str(path))
            if point_format == "xyz":
                cloud = DecodedCloud(cloud.points, None, None, None, None, cloud.dropped_nonfinite)
            return cloud
        if suffix == ".pcd":
            return read_pcd(path)
        if suffix == ".ply":
            return read_ply(path)
        if suffix == ".npy":
            return read_npy(path)
    except DatasetError:
        raise
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: unreadable ({exc})") from exc
    except (ValueError, IndexError, KeyError) as exc:  # e.g. a header line without its value, "POINTS 1.0"
        raise DatasetError(f"{path}: malformed {suffix[1:].upper()} header or data ({type(exc).__name__}: "
                           f"{exc})") from exc
    raise DatasetError(f"{path}: unknown point file type {suffix!r} (supported: {', '.join(POINT_FILE_SUFFIXES)})")


def _columns(values: np.ndarray, names: list[str]) -> np.ndarray:
    """A structured view of an ``(N, len(names))`` array."""
    out = np.zeros(len(values), dtype=[(n, values.dtype) for n in names])
    for k, n in enumerate(names):
        out[n] = values[:, k]
    return out


def _read_header(path: Path, first: bytes, end: tuple[bytes, ...]) -> tuple[list[str], int]:
    """Header lines (decoded) up to and including the line starting with one of ``end``, and the
    byte offset of the data after it."""
    lines: list[str] = []
    offset = 0
    with path.open("rb") as fh:
        for _ in range(_MAX_HEADER_LINES):
            raw = fh.readline()
            if not raw:
                break
            offset += len(raw)
            # comments may hold any text (a user's name, a place); the rest of a header is ASCII
            comment = raw.lstrip().startswith((b"#", b"comment", b"obj_info"))
            text = raw.decode("ascii", errors="replace" if comment else "strict").strip()
            lines.append(text)
            if any(text.encode().startswith(e) for e in end):
                return lines, offset
    raise DatasetError(f"{path}: no end of header ({' / '.join(e.decode() for e in end)}) "
                       f"within {_MAX_HEADER_LINES} lines: not a {first.decode()} file")


@dataclass(frozen=True)
class _PcdLayout:
    """What a PCD header says: the points' dtype, their count, the DATA mode and where the data start."""

    dtype: np.dtype
    n_points: int
    mode: str
    offset: int
    unique: list[str]
    counts: list[int]


def _pcd_layout(path: Path) -> _PcdLayout:
    """Parse the header of the PCD file ``path`` (DatasetError naming it when malformed)."""
    try:
        lines, offset = _read_header(path, b"PCD", (b"DATA",))
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: binary bytes in the header: not a PCD file") from exc
    header: dict[str, list[str]] = {}
    for line in lines:
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
    for key in ("FIELDS", "SIZE", "TYPE", "POINTS", "DATA"):
        if key not in header:
            raise DatasetError(f"{path}: PCD header has no {key} line")
    names = header["FIELDS"]
    sizes = [int(s) for s in header["SIZE"]]
    types = [t.upper() for t in header["TYPE"]]
    counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise DatasetError(f"{path}: PCD FIELDS/SIZE/TYPE/COUNT have different lengths "
                           f"({len(names)}/{len(sizes)}/{len(types)}/{len(counts)}): wrong field layout")
    n_points = int(header["POINTS"][0])
    mode = header["DATA"][0].lower()
    if n_points < 0:
        raise DatasetError(f"{path}: PCD header says POINTS {n_points}")
    formats = []
    for name, size, typ, count in zip(names, sizes, types, counts):
        if (typ, size) not in _PCD_TYPES:
            raise DatasetError(f"{path}: field {name!r} has unsupported TYPE {typ} SIZE {size}")
        base = np.dtype("<" + _PCD_TYPES[(typ, size)])
        formats.append(base if count == 1 else np.dtype((base, (count,))))
    unique = [n if n != "_" else f"_pad{k}" for k, n in enumerate(names)]
    return _PcdLayout(np.dtype({"names": unique, "formats": formats}), n_points, mode, offset, unique, counts)


def read_pcd(path: str | Path) -> DecodedCloud:
    """Read a PCD file (``DATA ascii`` or ``binary`` with any fields; ``binary_compressed`` via open3d).

    ``POINTS 0`` gives an empty cloud; fewer data than ``POINTS`` promises is an error.
    """
    path = Path(path)
    layout = _pcd_layout(path)
    dtype, n_points, mode, offset = layout.dtype, layout.n_points, layout.mode, layout.offset
    unique, counts = layout.unique, layout.counts
    if n_points == 0:  # POINTS 0: an empty cloud (its fields are still checked)
        return decode_structured(np.zeros(0, dtype=dtype), str(path))
    if mode == "binary":
        data = np.fromfile(path, dtype=np.uint8, offset=offset)
        need = n_points * dtype.itemsize
        if len(data) < need:
            raise DatasetError(f"{path}: {len(data)} data bytes, header promises {n_points} points x "
                               f"{dtype.itemsize} bytes = {need}: truncated or wrong field layout")
        arr = data[:need].view(dtype)
    elif mode == "ascii":
        with path.open("rb") as fh:
            fh.seek(offset)
            try:
                table = np.loadtxt(fh, dtype=np.float64, ndmin=2)
            except ValueError as exc:
                raise DatasetError(f"{path}: unreadable ASCII PCD data ({exc})") from exc
        n_cols = sum(counts)
        if table.shape != (n_points, n_cols):
            raise DatasetError(f"{path}: ASCII data is {table.shape[0]} x {table.shape[1]}, header says "
                               f"{n_points} points x {n_cols} values: wrong field layout")
        arr = np.zeros(n_points, dtype=dtype)
        col = 0
        for name, count in zip(unique, counts):
            arr[name] = table[:, col] if count == 1 else table[:, col:col + count]
            col += count
    elif mode == "binary_compressed":
        return _read_with_open3d(path)
    else:
        raise DatasetError(f"{path}: unknown PCD DATA mode {mode!r} (ascii, binary, binary_compressed)")
    return decode_structured(arr, str(path))


def _read_with_open3d(path: Path) -> DecodedCloud:
    """x, y, z and every other one-value-a-point attribute (intensity, time, ring, ...) with its
    type, through open3d's tensor reader (a binary_compressed PCD)."""
    import open3d as o3d

    pcd = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pcd.point or len(pcd.point.positions) == 0:
        raise DatasetError(f"{path}: open3d read no points")
    xyz = pcd.point.positions.numpy().astype(np.float64)
    cols: dict[str, np.ndarray] = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    for name in pcd.point:
        values = pcd.point[name].numpy()
        if name == "positions" or values.ndim != 2 or values.shape[1] != 1 or name in cols:
            continue
        cols[name] = values[:, 0]
    out = np.zeros(len(xyz), dtype=[(n, v.dtype) for n, v in cols.items()])
    for n, v in cols.items():
        out[n] = v
    return decode_structured(out, str(path))


def read_ply(path: str | Path) -> DecodedCloud:
    """Read the ``vertex`` element of a PLY file (ASCII or binary), every scalar property
    (``element vertex 0``: an empty cloud)."""
    return decode_structured(read_ply_vertices(path), str(Path(path)))


def _ply_layout(path: Path) -> tuple[str, int, list[tuple[str, str]], int]:
    """Parse the header of the PLY file ``path``: its format, vertex count, vertex properties (name,
    numpy type code) and where the data start (DatasetError naming it when malformed)."""
    with path.open("rb") as fh:
        if fh.read(3) != b"ply":
            raise DatasetError(f"{path}: does not start with 'ply': not a PLY file")
    try:
        lines, offset = _read_header(path, b"PLY", (b"end_header",))
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: binary bytes in the header: not a PLY file") from exc
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ")), None)
    elements = [ln.split() for ln in lines if ln.startswith("element ")]
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DatasetError(f"{path}: unknown PLY format {fmt!r}")
    if not elements or elements[0][1] != "vertex":
        raise DatasetError(f"{path}: the first PLY element is not 'vertex' (elements: "
                           f"{[e[1] for e in elements]})")
    n_points = int(elements[0][2])
    props: list[tuple[str, str]] = []
    in_vertex = False
    for ln in lines:
        if ln.startswith("element "):
            in_vertex = ln.split()[1] == "vertex"
        elif ln.startswith("property ") and in_vertex:
            parts = ln.split()
            if parts[1] == "list":
                raise DatasetError(f"{path}: vertex property {parts[-1]!r} is a list: wrong field layout")
            if parts[1] not in _PLY_TYPES:
                raise DatasetError(f"{path}: vertex property {parts[2]!r} has unknown type {parts[1]!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    return fmt, n_points, props, offset


def read_ply_vertices(path: str | Path) -> np.ndarray:
    """The ``vertex`` element of a PLY file (ASCII or binary) as a structured array with every scalar
    property, as stored (ASCII values as float64); a DatasetError naming the file when the header is
    malformed or the data are fewer than the header promises."""
    path = Path(path)
    fmt, n_points, props, offset = _ply_layout(path)
    if n_points == 0:  # element vertex 0: an empty cloud (its properties are still checked)
        return np.zeros(0, dtype=[(name, "<" + code) for name, code in props])
    if fmt == "ascii":
        with path.open("rb") as fh:
            fh.seek(offset)
            try:
                table = np.loadtxt(fh, dtype=np.float64, ndmin=2, max_rows=n_points)
            except ValueError as exc:
                raise DatasetError(f"{path}: unreadable ASCII PLY data ({exc})") from exc
        if table.shape != (n_points, len(props)):
            raise DatasetError(f"{path}: ASCII vertices are {table.shape}, header says {n_points} x {len(props)}")
        return _columns(table, [p[0] for p in props])
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(name, order + code) for name, code in props])
    data = np.fromfile(path, dtype=np.uint8, offset=offset)
    need = n_points * dtype.itemsize
    if len(data) < need:
        raise DatasetError(f"{path}: {len(data)} data bytes, header promises {n_points} vertices x "
                           f"{dtype.itemsize} bytes = {need}: truncated or wrong field layout")
    return data[:need].view(dtype)


def data_shortfall(path: str | Path) -> str | None:
    """Why the scan ``path`` holds fewer data bytes than its header promises (a binary PCD or PLY,
    a ``.npy``), or None: complete, empty (0 bytes: an empty frame), or a kind whose size says
    nothing without reading it (ASCII, ``binary_compressed``). Reads the header only.

    Raises
    ------
    DatasetError
        A malformed header, naming the file.
    """
    path = Path(path)
    suffix, size = path.suffix.lower(), path.stat().st_size
    if size == 0:
        return None
    if suffix == ".pcd":
        layout = _pcd_layout(path)
        if layout.mode != "binary":
            return None
        n, item, what, offset = layout.n_points, layout.dtype.itemsize, "points", layout.offset
    elif suffix == ".ply":
        fmt, n, props, offset = _ply_layout(path)
        if fmt == "ascii":
            return None
        item, what = np.dtype([(name, "<" + code) for name, code in props]).itemsize, "vertices"
    elif suffix == ".npy":
        try:
            with path.open("rb") as fh:
                version = np.lib.format.read_magic(fh)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(fh)
                offset = fh.tell()
        except (ValueError, OSError) as exc:
            raise DatasetError(f"{path}: not a plain .npy array ({exc})") from exc
        if dtype.hasobject:
            return None
        n, item, what = int(np.prod(shape)), dtype.itemsize, f"values of shape {tuple(shape)}"
    else:
        return None
    need, have = n * item, size - offset
    if have >= need:
        return None
    return (f"{path}: {have} data bytes, header promises {n} {what} x {item} bytes = {need}: cut short "
            "(a recorder or a copy that stopped)")


def check_scan_sizes(files: Sequence[Path]) -> None:
    """Refuse, when a folder of PCD / PLY / NPY scans opens, a scan holding fewer data than its header
    promises (:func:`data_shortfall`): otherwise the run would stop only when SLAM reaches it.

    Raises
    ------
    DatasetError
        The first such file's problem, with how many of the files are affected.
    """
    bad = [(f, msg) for f in files if (msg := data_shortfall(f)) is not None]
    if bad:
        more = "" if len(bad) == 1 else ", e.g. " + ", ".join(Path(f).name for f, _ in bad[1:4])
        raise DatasetError(f"{bad[0][1]} ({len(bad)} of the {len(files)} scans to read are cut short{more}; "
                           "--frames runs a range without them)")


def read_npy(path: str | Path) -> DecodedCloud:
    """Read an ``(N, 3)``/``(N, 4)`` array or a structured array with fields x, y, z (...); an empty
    array (``(0,)``, ``(0, 3)``, ``(0, 4)`` or structured) is an empty cloud."""
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except ValueError as exc:
        raise DatasetError(f"{path}: not a plain .npy array ({exc})") from exc
    if arr.dtype.names:
        return decode_structured(arr, str(path))  # an empty one gives an empty cloud
    if arr.size == 0 and np.issubdtype(arr.dtype, np.number) and (arr.ndim == 1 or arr.shape[1:] in ((3,), (4,))):
        return empty_cloud()
    real = np.issubdtype(arr.dtype, np.number) and not np.issubdtype(arr.dtype, np.complexfloating)
    if arr.ndim != 2 or arr.shape[1] not in (3, 4) or not real:  # complex: its imaginary part would be lost
        raise DatasetError(f"{path}: array of shape {arr.shape} and dtype {arr.dtype}; expected (N, 3) x,y,z or "
                           "(N, 4) x,y,z,intensity real numbers, or a structured array with fields x, y, z")
    return decode_structured(_columns(arr.astype(np.float64), ["x", "y", "z", "intensity"][: arr.shape[1]]),
                             str(path))
