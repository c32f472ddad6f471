"""Decoding of ``sensor_msgs/PointCloud2`` messages (ROS1 and ROS2) into point arrays.

A PointCloud2 is a byte buffer of ``height x width`` points, each ``point_step`` bytes, rows
``row_step`` bytes apart (a row may end with padding), with named fields at given offsets
(``sensor_msgs/PointField``: name, offset, datatype, count). This module builds a numpy
structured dtype from the fields, so any field order, padding and byte order (``is_bigendian``)
is read without copying point by point.

Fields read: ``x``, ``y``, ``z`` (required), ``intensity`` (optional; also ``scalar_intensity``,
``reflectance``), the per-point time
``t`` / ``time`` / ``timestamp`` (optional, the first present in that order) and ``ring``
(optional). Points with a non-finite coordinate (organized clouds mark missing returns with
NaN) are dropped and counted. Anything else is a :class:`~gr_graph.datasets.base.DatasetError`
whose message names where the message came from (``source``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from gr_graph.datasets.base import DatasetError

log = logging.getLogger(__name__)

POINTFIELD_DTYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
"""``sensor_msgs/PointField`` datatype constants (INT8 .. FLOAT64) -> numpy type codes."""
TIME_FIELDS = ("t", "time", "timestamp", "offset_time")
"""Names of the per-point time field, in order of preference (Ouster ``t``, Velodyne ``time``,
Hesai/Livox ``timestamp``, Livox converters' ``offset_time``); matched as :func:`field_named` says."""
RING_FIELDS = ("ring",)
INTENSITY_FIELDS = ("intensity", "scalar_intensity", "reflectance")
"""Names of the intensity field, in order of preference; matched as :func:`field_named` says."""
EXPORTER_PREFIX = "scalar_"
"""What CloudCompare puts before a scalar field's name (``scalar_Intensity``, ``scalar_t``)."""


def field_named(names: tuple[str, ...] | list[str], preferred: tuple[str, ...]) -> str | None:
    """The field of ``names`` that holds one of ``preferred`` (in their order): a name as written
    first, else one differing only in case or by CloudCompare's :data:`EXPORTER_PREFIX`
    (``scalar_Intensity``, ``Time``, ``scalar_ring``; of several such, the first in ``names``).
    None when there is none."""
    exact = next((n for n in preferred if n in names), None)
    if exact is not None:
        return exact
    loose: dict[str, str] = {}
    for n in reversed(list(names)):
        key = n.lower()
        loose[key[len(EXPORTER_PREFIX):] if key.startswith(EXPORTER_PREFIX) else key] = n
    return next((loose[n] for n in preferred if n in loose), None)


@dataclass(frozen=True)
class DecodedCloud:
    """The fields of one point cloud.

    Attributes
    ----------
    points : (N, 3) float64
        Finite x, y, z.
    intensity : (N,) float32 or None
    time : (N,) float64 or None
        The raw per-point time field, in the unit it was stored in.
    time_field : str or None
        Which field ``time`` came from.
    ring : (N,) int64 or None
    dropped_nonfinite : int
        Points removed because a coordinate was not finite or the point was exactly the origin
        (no return).
    """

    points: np.ndarray
    intensity: np.ndarray | None
    time: np.ndarray | None
    time_field: str | None
    ring: np.ndarray | None
    dropped_nonfinite: int


def structured_dtype(fields: list[tuple[str, int, int, int]], point_step: int, bigendian: bool,
                     source: str) -> np.dtype:
    """The numpy dtype of one point from ``(name, offset, datatype, count)`` fields.

    Raises
    ------
    DatasetError
        Unknown datatype, a field reaching past ``point_step``, or duplicate names.
    """
    order = ">" if bigendian else "<"
    names, formats, offsets = [], [], []
    for name, offset, datatype, count in fields:
        if datatype not in POINTFIELD_DTYPES:
            raise DatasetError(f"{source}: field {name!r} has unknown PointField datatype {datatype} "
                               f"(known: {sorted(POINTFIELD_DTYPES)})")
        if name in names:
            raise DatasetError(f"{source}: field {name!r} appears twice")
        base = np.dtype(order + POINTFIELD_DTYPES[datatype])
        fmt = base if count <= 1 else np.dtype((base, (int(count),)))
        if offset < 0 or offset + fmt.itemsize > point_step:
            raise DatasetError(f"{source}: field {name!r} (offset {offset}, {fmt.itemsize} bytes) does not fit "
                               f"in point_step {point_step}: wrong field layout")
        names.append(name or f"_unnamed{len(names)}")
        formats.append(fmt)
        offsets.append(int(offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(point_step)})


def empty_cloud() -> DecodedCloud:
    """A cloud without points (and without intensity, time or ring fields)."""
    return DecodedCloud(np.zeros((0, 3)), None, None, None, None, 0)


def has_return(xyz: np.ndarray) -> np.ndarray:
    """Which rows of ``(N, 3)`` coordinates are returns: finite, and not exactly the origin (how organized
    clouds, e.g. Ouster's, mark a beam without a return; kept, such points would pull a ring's elevation
    to 0 and its times into the sweep)."""
    return np.all(np.isfinite(xyz), axis=1) & np.any(xyz != 0.0, axis=1)


def finite_intensity(intensity: np.ndarray, source: str, field: str = "intensity") -> np.ndarray:
    """``intensity`` (of points with a return) with its non-finite values replaced by 0, the count logged
    naming ``source`` and the ``field`` (SLAM does not use intensity; the point is kept). The same array
    when every value is finite."""
    bad = ~np.isfinite(intensity)
    if not bad.any():
        return intensity
    log.warning("%s: %d non-finite %s values at finite points replaced by 0", source, int(bad.sum()), field)
    return np.where(bad, np.zeros((), intensity.dtype), intensity)


def decode_structured(arr: np.ndarray, source: str) -> DecodedCloud:
    """Read x, y, z (+ intensity, time, ring) from a structured array of points.

    Points with a non-finite coordinate, and points exactly at the origin (no return), are dropped
    (counted in ``dropped``); a non-finite
    intensity at a finite point is replaced by 0 and the count logged (SLAM does not use
    intensity); non-finite per-point times and negative rings are errors naming ``source``.

    Parameters
    ----------
    arr : structured np.ndarray
        Any shape (organized clouds are flattened).
    source : str
        Named in errors.
    """
    names = arr.dtype.names or ()
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise DatasetError(f"{source}: no field {'/'.join(missing)} (fields: {', '.join(names) or 'none'}): "
                           "wrong field layout")
    flat = arr.reshape(-1)
    for c in "xyz":
        if flat.dtype[c].shape:
            raise DatasetError(f"{source}: field {c!r} has count {flat.dtype[c].shape}, expected 1")
    xyz = np.stack([flat[c].astype(np.float64) for c in "xyz"], axis=1)
    finite = has_return(xyz)
    dropped = int(len(xyz) - finite.sum())
    if dropped:
        xyz = xyz[finite]
        flat = flat[finite]
    intensity_field = field_named(names, INTENSITY_FIELDS)
    intensity = flat[intensity_field].astype(np.float32) if intensity_field else None
    time_field = field_named(names, TIME_FIELDS)
    time = flat[time_field].astype(np.float64) if time_field else None
    ring_field = field_named(names, RING_FIELDS)
    ring = flat[ring_field].astype(np.int64) if ring_field else None
    if intensity is not None:
        intensity = finite_intensity(intensity, source, intensity_field)
    if time is not None and not np.all(np.isfinite(time)):
        raise DatasetError(f"{source}: non-finite per-point times ({time_field!r}) at finite points")
    if ring is not None and len(ring) and ring.min() < 0:
        raise DatasetError(f"{source}: negative ring index {int(ring.min())}")
    return DecodedCloud(xyz, intensity, time, time_field, ring, dropped)


def decode_pointcloud2(msg: Any, source: str) -> DecodedCloud:
    """Decode a deserialized ``sensor_msgs/PointCloud2`` (ROS1 or ROS2, as ``rosbags`` gives it).

    Parameters
    ----------
    msg : object
        With ``height``, ``width``, ``fields`` (``name``, ``offset``, ``datatype``, ``count``),
        ``is_bigendian``, ``point_step``, ``row_step`` and ``data`` (bytes or uint8 array).
    source : str
        Where the message comes from (bag file, topic, message number), named in errors.
        An empty message (no points) is an empty cloud, logged.

    Raises
    ------
    DatasetError
        A buffer whose size does not match ``height x row_step``, a row
        shorter than ``width x point_step``, or a field layout without x/y/z.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    data = np.frombuffer(memoryview(msg.data).cast("B"), dtype=np.uint8) if not isinstance(msg.data, np.ndarray) \
        else msg.data.view(np.uint8).reshape(-1)
    if height * width == 0 or len(data) == 0:
        # a sensor's warm-up message, a dropped sweep: an empty frame (the odometry marks it unusable)
        log.warning("%s: empty message (height %d, width %d, %d data bytes): an empty frame", source, height, width,
                    len(data))
        fields = [(str(f.name), int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]
        if not fields or point_step <= 0:
            return empty_cloud()
        return decode_structured(np.zeros(0, dtype=structured_dtype(fields, point_step, bool(msg.is_bigendian),
                                                                    source)), source)
    if point_step <= 0:
        raise DatasetError(f"{source}: point_step {point_step} <= 0: wrong field layout")
    if row_step < width * point_step:
        raise DatasetError(f"{source}: row_step {row_step} < width {width} x point_step {point_step}: "
                           "wrong field layout")
    if len(data) != height * row_step:
        raise DatasetError(f"{source}: {len(data)} data bytes, expected height {height} x row_step {row_step} = "
                           f"{height * row_step}")
    fields = [(str(f.name), int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]
    dtype = structured_dtype(fields, point_step, bool(msg.is_bigendian), source)
    rows = data.reshape(height, row_step)[:, : width * point_step]
    points = np.ascontiguousarray(rows).view(dtype).reshape(height * width)
    return decode_structured(points, source)
