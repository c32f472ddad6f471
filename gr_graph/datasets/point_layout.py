"""Which float32 layout a headerless point file holds: 16-byte x,y,z,intensity or 12-byte x,y,z.

A KITTI ``.bin`` is a flat array of float32 with no header, so the number of values per
point cannot be read from the file. A 12-byte x,y,z file of N points has 12N bytes, a
multiple of 16 whenever N is a multiple of 4: read 16 bytes a point it gives garbage
"points" without any error. Two cheap tests on the data tell the layouts apart:

**Mixed columns** (needs no point order). Read with the wrong number of values per point,
value ``k`` of row ``r`` is field ``(s·r + k) mod s_true`` of the real points: every column
holds x, y, z (and intensity) in turn, so all columns have *the same distribution*. Read
correctly, the columns differ (z spans a few metres where x and y span tens; intensity is
not a coordinate). The statistic is the largest two-sample Kolmogorov-Smirnov distance
between any two columns: 0.41-0.46 (x,y,z) and 0.75-1.0 (x,y,z,intensity) at the right
layout on real KITTI 00 and synthetic frames, at most 0.02 at a wrong one (``MIXED_KS``
= 0.15 separates them; ``benchmarks/bench_point_layout.py`` measures it).

**Scan order** (needs the points in scan order, as LiDAR drivers write them). At the right
layout consecutive points are neighbours on a scan line: the median step between
consecutive rows is about 0.002-0.004 of the median distance between rows far apart in the
file. At a wrong layout consecutive rows are cyclic permutations of coordinates (x,y,z then
y,z,x, ...), and this ratio is 0.58-0.98; shuffled files give about 1 at every layout
(``ORDERED_LOCALITY`` = 0.1).

:func:`check_point_layout` refuses a file whose declared layout fails either test and says
which layout the data look like instead.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gr_graph.datasets.base import DatasetError

log = logging.getLogger(__name__)

FLOAT32_ABSURD = 1e10
"""A float32 value of a LiDAR scan above this magnitude is absurd (1e10 m; 10 000 km even in millimetres)."""
FLOAT64_SUSPECT_FRACTION = 0.01
"""Fraction of absurd float32 values above which a ``.bin`` is examined as float64. Real float32
scans (KITTI) have none; float64 data read as float32 give about 12 % (float32 values converted
to float64: the low words are 0, +-1.1e-19, +-2 or +-3.7e19) to 40 % (full-precision float64)."""
FLOAT64_PLAUSIBLE = 1e6
"""Read as float64, a file is plausible coordinates when all but 0.1 % of its finite values are
below this magnitude (float32 scans read as float64 have about 12 % above it)."""

#: Float32 values per point of the layouts the loader reads.
POINT_FORMATS: dict[str, int] = {"xyzi": 4, "xyz": 3}
#: Layouts tried when explaining what a refused file holds (5: e.g. nuScenes x,y,z,intensity,ring).
CANDIDATE_STRIDES: tuple[int, ...] = (3, 4, 5)
#: Largest column-to-column KS distance below which the columns count as the same distribution.
MIXED_KS = 0.15
#: Consecutive-step / far-pair distance ratio below which rows count as in scan order.
ORDERED_LOCALITY = 0.1
#: Fewer usable rows than this: too few to judge, the declared layout is trusted. (On excerpts
#: of 400 points of real and synthetic frames the test refused no valid file and caught every
#: contiguous and about 98% of shuffled 12-byte excerpts; see the benchmark.)
MIN_ROWS = 256
_BLOCKS = 4
_BLOCK_ROWS = 1024

_LAYOUT_NAMES = {3: "12-byte x,y,z", 4: "16-byte x,y,z,intensity", 5: "20-byte (5 float32, e.g. x,y,z,intensity,ring)"}

_HOW_TO_READ = {
    "xyz": "read x,y,z-only files with point_format='xyz' "
           "(command line --point-format xyz, config data.point_format: xyz)",
    "xyzi": "read x,y,z,intensity files with point_format='xyzi' (the default; --point-format xyzi)",
}


@dataclass(frozen=True)
class StrideEvidence:
    """How a flat float32 array looks when read ``stride`` values a point.

    Attributes
    ----------
    stride : int
        Float32 values per point assumed.
    n_rows : int
        Rows examined (finite, not x = y = z = 0), up to ``4 x 1024``.
    locality : float
        Median distance between consecutive rows / median distance between rows half the
        sample apart (x,y,z of each row). Small: the rows are in scan order.
    column_ks : float
        Largest two-sample Kolmogorov-Smirnov distance between any two columns. Small: the
        columns have one distribution, as when each column holds x, y, z in turn.
    """

    stride: int
    n_rows: int
    locality: float
    column_ks: float

    @property
    def judged(self) -> bool:
        """Enough rows to trust the two statistics."""
        return self.n_rows >= MIN_ROWS

    @property
    def ordered(self) -> bool:
        return self.judged and self.locality < ORDERED_LOCALITY

    @property
    def mixed(self) -> bool:
        return self.judged and self.column_ks < MIXED_KS

    def describe(self) -> str:
        return (f"read {4 * self.stride} bytes a point: columns {'alike' if self.mixed else 'distinct'} "
                f"(largest KS distance {self.column_ks:.3f}), consecutive points "
                f"{'close' if self.ordered else 'not close'} (step/spread {self.locality:.3f})")


def _largest_ks_distance(columns: np.ndarray, grid_per_column: int = 128) -> float:
    """Largest two-sample Kolmogorov-Smirnov distance between any two columns of ``columns``.

    The empirical CDFs are compared at ``grid_per_column`` evenly spaced order statistics of
    every column, which under-estimates the exact statistic by at most ``1 / grid_per_column``.
    """
    sorted_cols = np.sort(columns, axis=0)
    n, k = sorted_cols.shape
    ranks = np.linspace(0, n - 1, min(grid_per_column, n)).astype(np.int64)
    grid = np.sort(sorted_cols[ranks].ravel())
    cdfs = np.stack([np.searchsorted(sorted_cols[:, c], grid, side="right") for c in range(k)]) / n
    return float(max(np.max(np.abs(cdfs[i] - cdfs[j])) for i in range(k) for j in range(i + 1, k)))


def stride_evidence(values: np.ndarray, stride: int) -> StrideEvidence:
    """Measure :class:`StrideEvidence` of the flat float32 ``values`` read ``stride`` values a point.

    Four evenly spaced blocks of 1024 consecutive rows are examined (a few milliseconds for
    any file size). Rows with a non-finite value or with x = y = z = 0
    (no-return padding of organised clouds) are left out.
    """
    flat = np.asarray(values, dtype=np.float32).ravel()
    n = len(flat) // stride
    rows = flat[: n * stride].reshape(n, stride)
    starts = np.linspace(0, max(n - _BLOCK_ROWS, 0), _BLOCKS).astype(np.int64)
    steps, blocks = [], []
    for start in np.unique(starts):
        block = rows[start:start + _BLOCK_ROWS].astype(np.float64)
        keep = np.all(np.isfinite(block), axis=1) & np.any(block[:, :3] != 0.0, axis=1)
        block = block[keep]
        if len(block) > 1:
            steps.append(np.linalg.norm(np.diff(block[:, :3], axis=0), axis=1))
            blocks.append(block)
    if not blocks:
        return StrideEvidence(stride, 0, float("nan"), float("nan"))
    sample = np.concatenate(blocks)
    far = np.linalg.norm(sample[:, :3] - np.roll(sample[:, :3], len(sample) // 2, axis=0), axis=1)
    far_median = float(np.median(far))
    step_median = float(np.median(np.concatenate(steps)))
    locality = step_median / far_median if far_median > 0 else float("nan")
    column_ks = _largest_ks_distance(sample)
    return StrideEvidence(stride, len(sample), locality, column_ks)


def layout_is_wrong(declared: StrideEvidence, others: list[StrideEvidence]) -> bool:
    """The decision rule: the declared layout fails the column test, or another layout is in
    scan order while the declared one is not."""
    if not declared.judged:
        return False
    return declared.mixed or (not declared.ordered and any(o.ordered and not o.mixed for o in others))


def _fourth_column_note(values: np.ndarray) -> str:
    rows = np.asarray(values, np.float32).ravel()
    rows = rows[: len(rows) // 4 * 4].reshape(-1, 4)
    col = rows[:, 3][np.isfinite(rows[:, 3])]
    if not len(col):
        return ""
    return (f"; its 'intensity' column is {100 * np.mean(col < 0):.0f}% negative and spans "
            f"{col.min():.1f}..{col.max():.1f} (intensity is >= 0: 0-1 in KITTI, 0-255 elsewhere)")


def check_point_layout(values: np.ndarray, point_format: str, path: str | Path) -> None:
    """Refuse ``values`` (a file's flat float32 contents) if they do not look like ``point_format``.

    Parameters
    ----------
    values : (M,) float32 array
        The whole file; its length is a multiple of the declared stride.
    point_format : {"xyzi", "xyz"}
    path : path
        Named in the error.

    Raises
    ------
    DatasetError
        Naming the file, the layout the data look like and the statistics that showed it.
    """
    stride = POINT_FORMATS[point_format]
    declared = stride_evidence(values, stride)
    if declared.judged and declared.ordered and not declared.mixed:
        return  # the common case costs one stride's statistics
    others = [stride_evidence(values, s) for s in CANDIDATE_STRIDES if s != stride and len(values) >= s * MIN_ROWS]
    if not layout_is_wrong(declared, others):
        return
    fitting = [o for o in others if not o.mixed and (o.ordered or not any(x.ordered for x in others))]
    fitting.sort(key=lambda o: (not o.ordered, o.locality))
    evidence = "; ".join(e.describe() for e in [declared, *fitting[:1]])
    if fitting:
        best = fitting[0]
        found = f"looks like {_LAYOUT_NAMES[best.stride]} points, not {_LAYOUT_NAMES[stride]}"
        fmt = next((name for name, s in POINT_FORMATS.items() if s == best.stride), None)
        advice = _HOW_TO_READ[fmt] if fmt else "this loader reads only x,y,z,intensity and x,y,z files"
    else:
        found = f"does not look like {_LAYOUT_NAMES[stride]} points"
        advice = "the file is not a LiDAR scan in a layout this loader reads (x,y,z,intensity or x,y,z float32)"
    note = _fourth_column_note(values) if stride == 4 else ""
    raise DatasetError(f"{path}: {found} ({evidence}{note}); {advice}")


def size_error(path: str | Path, size: int, point_format: str, values: np.ndarray | None = None) -> DatasetError:
    """The error for a file whose size is not a multiple of the declared point size.

    When the size fits the other layout, the message suggests it, and says whether the data
    read that way look like a LiDAR scan (``values``: the file's float32 contents, if the size
    is a multiple of 4).
    """
    stride = POINT_FORMATS[point_format]
    msg = (f"{path}: size {size} bytes is not a multiple of {4 * stride} "
           f"({stride} float32 a point, point_format={point_format!r})")
    for other, other_stride in POINT_FORMATS.items():
        if other == point_format or size % (4 * other_stride):
            continue
        msg += f" but is a multiple of {4 * other_stride}"
        if values is not None and len(values) >= other_stride * MIN_ROWS:
            ev = stride_evidence(values, other_stride)
            looks = ev.ordered and not ev.mixed
            msg += (f", and read that way it {'looks' if looks else 'does not look'} like a LiDAR scan "
                    f"({ev.describe()})")
        return DatasetError(f"{msg}: {_HOW_TO_READ[other]}")
    return DatasetError(f"{msg}; the file is truncated or not a KITTI-style scan")


def check_bin_sizes(files: Sequence[Path], point_format: str) -> None:
    """Refuse, when a sequence opens, a ``.bin`` scan whose size is not a multiple of the point
    size (a file cut short by a full disk or a copy that stopped): otherwise the run would stop at
    that frame, after SLAM had spent its time on the frames before it.

    Raises
    ------
    DatasetError
        :func:`size_error` of the first such file, with how many of the files are affected.
    """
    stride_bytes = 4 * POINT_FORMATS[point_format]
    bad = [(f, size) for f in files if (size := Path(f).stat().st_size) % stride_bytes]
    if bad:
        path, size = bad[0]
        err = size_error(path, size, point_format, np.fromfile(path, np.float32) if size % 4 == 0 else None)
        raise DatasetError(f"{err} ({len(bad)} of the {len(files)} scans to read have such a size"
                           f"{'' if len(bad) == 1 else ', e.g. ' + ', '.join(Path(f).name for f, _ in bad[1:4])})")


def float64_bin_problem(path: str | Path, values: np.ndarray | None = None) -> str | None:
    """Why a ``.bin`` looks like float64 rather than float32 data, or None.

    The file is read as float32; when more than :data:`FLOAT64_SUSPECT_FRACTION` of its finite
    values exceed :data:`FLOAT32_ABSURD` and, read as float64, all but 0.1 % of its finite values
    are below :data:`FLOAT64_PLAUSIBLE` (and not all 0), the message names the file, the
    evidence, the layout the float64 values look like and how to convert the file. A file with
    absurd float32 values that does not read as float64 either is let through with a warning
    (the layout check and the pipeline's range crop deal with it). ``values``: the file read as
    float32 already (else it is read here).
    """
    path = Path(path)
    size = path.stat().st_size
    if size == 0 or size % 4:
        return None  # empty, or the size check of the reader explains it
    values = np.fromfile(path, dtype=np.float32) if values is None else values
    finite = values[np.isfinite(values)]
    if not len(finite):
        return None
    absurd = float(np.mean(np.abs(finite) > FLOAT32_ABSURD))
    if absurd <= FLOAT64_SUSPECT_FRACTION:
        return None
    as64 = np.fromfile(path, dtype=np.float64) if size % 8 == 0 else np.zeros(0)
    finite64 = as64[np.isfinite(as64)]
    plausible = (len(finite64) > 0 and np.any(finite64 != 0.0)
                 and float(np.mean(np.abs(finite64) > FLOAT64_PLAUSIBLE)) <= 1e-3)
    if not plausible:
        log.warning("%s: %.1f%% of the values read as float32 exceed %g in magnitude (and the file does not "
                    "read as float64 either): not a LiDAR scan?", path, 100 * absurd, FLOAT32_ABSURD)
        return None
    layout = ""
    for stride, name, fmt in ((4, "x,y,z,intensity", "xyzi"), (3, "x,y,z", "xyz")):
        if len(as64) % stride == 0:
            ev = stride_evidence(as64.astype(np.float32), stride)
            if ev.ordered and not ev.mixed:
                layout = (f"; read as float64 it looks like {name} points (point_format={fmt!r} after "
                          "converting)")
                break
    return (f"{path}: looks like float64 data, not float32: read as float32 {100 * absurd:.1f}% of the values "
            f"are absurd (|v| > {FLOAT32_ABSURD:g}, e.g. {np.max(np.abs(finite)):.3g}), read as float64 the "
            f"values are plausible coordinates (largest {np.max(np.abs(finite64)):.3g}){layout}; .bin scans must "
            "be float32: convert with np.fromfile(path, dtype=np.float64).astype(np.float32).tofile(path)")
