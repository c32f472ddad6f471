"""Read and write single point clouds: ``.bin`` (KITTI float32), ``.pcd``, ``.ply``, ``.npy``.

The format is chosen by the file's extension (:data:`CLOUD_SUFFIXES`).

Reading (:func:`read_cloud`) gives ``(points (N, 3) float64, intensity (N,) float32 or None)``
through the dataset loaders' reader (:func:`gr_graph.datasets.point_files.read_point_file`).

Writing (:func:`write_cloud`, atomic) stores ``x,y,z`` as float32 and, when given, the
intensity; ``.ply`` files can also carry one covariance per point as six float64 properties
``cov_xx, cov_xy, cov_xz, cov_yy, cov_yz, cov_zz`` (m^2). PLY is written by this module
(binary little endian, the layout of the PLY specification), PCD through open3d, ``.bin`` as
KITTI float32 ``x,y,z,intensity`` (intensity 0 without one), ``.npy`` as float32 ``(N, 3)`` or
``(N, 4)``. :func:`read_ply_covariances` reads the covariance properties back.

Every error names the file: a :class:`gr_graph.datasets.base.DatasetError` for what is read, a
``ValueError`` (bad arguments) or ``OSError`` (the disk) for what is written. Points without a
return (non-finite, or exactly at the origin) are dropped when read, logged with their count.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from gr_graph.atomic import atomic_path
from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.pointcloud2 import has_return

__all__ = ["CLOUD_SUFFIXES", "COVARIANCE_PROPERTIES", "check_suffix", "read_cloud", "read_cloud_counted",
           "write_cloud", "write_ply", "read_ply_covariances"]

log = logging.getLogger(__name__)

CLOUD_SUFFIXES: tuple[str, ...] = (".bin", ".pcd", ".ply", ".npy")
#: PLY property names of the upper triangle of a covariance, and their (row, column).
COVARIANCE_PROPERTIES: dict[str, tuple[int, int]] = {
    "cov_xx": (0, 0), "cov_xy": (0, 1), "cov_xz": (0, 2), "cov_yy": (1, 1), "cov_yz": (1, 2), "cov_zz": (2, 2)}

PathLike = str | os.PathLike[str]


def check_suffix(path: Path) -> str:
    """The lower-case extension of ``path``; a DatasetError naming the file when it is not a cloud format."""
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise DatasetError(f"{path}: unknown point cloud format {suffix or '(no extension)'!r}; "
                           f"use one of {', '.join(CLOUD_SUFFIXES)}")
    return suffix


def read_cloud(path: PathLike, point_format: str = "xyzi") -> tuple[np.ndarray, np.ndarray | None]:
    """Points ``(N, 3)`` float64 and intensity ``(N,)`` float32 (or None) of one cloud file:
    :func:`read_cloud_counted` without the count of dropped points."""
    points, intensity, _ = read_cloud_counted(path, point_format)
    return points, intensity


def read_cloud_counted(path: PathLike, point_format: str = "xyzi") -> tuple[np.ndarray, np.ndarray | None, int]:
    """Points ``(N, 3)`` float64, intensity ``(N,)`` float32 (or None) and the number of points dropped
    (no return: non-finite, or exactly at the origin; logged) of one cloud file, read by
    :func:`gr_graph.datasets.point_files.read_point_file`.

    Parameters
    ----------
    path : path
        A ``.bin``, ``.pcd``, ``.ply`` or ``.npy`` file.
    point_format : {"xyzi", "xyz"}
        Layout of a ``.bin`` file (ignored for the other formats).

    Raises
    ------
    DatasetError
        Naming the file: missing, unknown extension, unreadable, wrong layout, no points.
    """
    from gr_graph.datasets.point_files import read_point_file

    p = Path(path)
    check_suffix(p)
    cloud = read_point_file(p, point_format)
    if len(cloud.points) == 0:
        raise DatasetError(f"{p}: the file holds no (finite) points")
    if cloud.dropped_nonfinite:
        log.warning("%s: dropped %d points without a return (non-finite, or exactly at the origin) of %d",
                    p, cloud.dropped_nonfinite, cloud.dropped_nonfinite + len(cloud.points))
    intensity = None if cloud.intensity is None else np.asarray(cloud.intensity, np.float32).reshape(-1)
    return np.asarray(cloud.points, np.float64), intensity, int(cloud.dropped_nonfinite)


def write_cloud(path: PathLike, points: np.ndarray, intensity: np.ndarray | None = None,
                covariances: np.ndarray | None = None) -> Path:
    """Write a cloud in the format of ``path``'s extension, atomically; return the path.

    Parameters
    ----------
    path : path
        ``.bin``, ``.pcd``, ``.ply`` or ``.npy``.
    points : (N, 3) array
    intensity : (N,) array, optional
    covariances : (N, 3, 3) array, optional
        Only for ``.ply`` (six properties per point, see the module docstring).

    Raises
    ------
    ValueError
        Naming the file: no points, intensities or covariances not one per point, covariances
        for another format than ``.ply``.
    """
    p = Path(path)
    suffix = check_suffix(p)
    xyz = np.asarray(points, np.float32).reshape(-1, 3)
    inten = None if intensity is None else np.asarray(intensity, np.float32).reshape(-1)
    if inten is not None and len(inten) != len(xyz):
        raise ValueError(f"{p}: {len(inten)} intensities for {len(xyz)} points")
    if len(xyz) == 0:  # read_cloud refuses such a file: not written in any format (open3d's PCD writer fails)
        raise ValueError(f"{p}: no points to write")
    if covariances is not None and suffix != ".ply":
        raise ValueError(f"{p}: per-point covariances can be stored in .ply files only (or separately as .npy)")
    if suffix == ".ply":
        return write_ply(p, xyz, inten, covariances)
    with atomic_path(p) as tmp:
        if suffix == ".bin":
            np.column_stack([xyz, np.zeros(len(xyz), np.float32) if inten is None else inten]).tofile(tmp)
        elif suffix == ".npy":
            with open(tmp, "wb") as fh:  # a handle: np.save would append ".npy" to a name ending in ".NPY"
                np.save(fh, xyz if inten is None else np.column_stack([xyz, inten]))
        else:
            import open3d as o3d

            cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
            if inten is not None:
                cloud.point.intensity = o3d.core.Tensor(inten.reshape(-1, 1))
            if not o3d.t.io.write_point_cloud(str(tmp), cloud):
                raise OSError(f"{p}: open3d could not write the file")
    return p


def write_ply(path: PathLike, points: np.ndarray, intensity: np.ndarray | None = None,
              covariances: np.ndarray | None = None, extra: dict[str, np.ndarray] | None = None) -> Path:
    """Binary little-endian PLY: float32 ``x, y, z`` [+ ``intensity``] [+ six float64 ``cov_*``]
    [+ ``extra`` properties, one value per point, their own dtype], written atomically."""
    xyz = np.asarray(points, np.float32).reshape(-1, 3)
    n = len(xyz)
    fields: list[tuple[str, np.ndarray]] = [("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])]
    if intensity is not None:
        fields.append(("intensity", np.asarray(intensity, np.float32).reshape(-1)))
    if covariances is not None:
        C = np.asarray(covariances, np.float64)
        if C.shape != (n, 3, 3):
            raise ValueError(f"{path}: covariances must be ({n}, 3, 3), got {C.shape}")
        fields += [(name, C[:, i, j]) for name, (i, j) in COVARIANCE_PROPERTIES.items()]
    for name, values in (extra or {}).items():
        fields.append((name, np.asarray(values).reshape(-1)))
    ply_types = {"f4": "float", "f8": "double", "i4": "int", "u4": "uint", "u1": "uchar", "i2": "short",
                 "u2": "ushort", "i1": "char"}
    dtype = np.dtype([(name, "<" + v.dtype.str[1:]) for name, v in fields])
    for name, v in fields:
        if len(v) != n:
            raise ValueError(f"{path}: property {name} has {len(v)} values for {n} points")
        if v.dtype.str[1:] not in ply_types:
            raise ValueError(f"{path}: property {name}: dtype {v.dtype} has no PLY type")
    rows = np.empty(n, dtype)
    for name, v in fields:
        rows[name] = v
    header = ["ply", "format binary_little_endian 1.0", "comment written by gr_graph", f"element vertex {n}"]
    header += [f"property {ply_types[v.dtype.str[1:]]} {name}" for name, v in fields]
    header.append("end_header")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rows.tobytes())
    return Path(path)


def read_ply_covariances(path: PathLike) -> np.ndarray:
    """The ``(N, 3, 3)`` covariances stored as ``cov_*`` properties in a PLY file, one a point that
    :func:`read_cloud` returns: rows of points it drops (a non-finite coordinate, or exactly the
    origin) are dropped here too, so the two stay row-aligned. Read with the same reader (a
    truncated file is an error naming it, as for :func:`read_cloud`)."""
    from gr_graph.datasets.point_files import read_ply_vertices

    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"{p}: point file not found")
    if p.suffix.lower() != ".ply":
        raise DatasetError(f"{p}: not a PLY file (covariances are stored as PLY properties)")
    vertices = read_ply_vertices(p)
    names = vertices.dtype.names or ()
    missing = [k for k in (*COVARIANCE_PROPERTIES, "x", "y", "z") if k not in names]
    if missing:
        raise DatasetError(f"{p}: no properties {missing}")
    xyz = np.stack([vertices[c].astype(np.float64) for c in "xyz"], axis=1)
    kept = has_return(xyz)  # the rows read_cloud keeps
    C = np.empty((len(xyz), 3, 3), np.float64)
    for name, (i, j) in COVARIANCE_PROPERTIES.items():
        C[:, i, j] = C[:, j, i] = vertices[name].astype(np.float64)
    return C[kept]
