"""How real a LiDAR sequence looks: per-frame local-geometry statistics of KITTI-layout folders.

``python -m gr_graph.datasets.realism DIR_A DIR_B ... [--seq 00] [--max-frames 50] [--out realism.json]``
prints a table with one column per folder and writes the same numbers as JSON. Each folder
is a KITTI odometry root (``sequences/<seq>/velodyne/*.bin``), e.g. the real frames of
``../shared/data/kitti`` and a synthetic export (``python -m gr_graph.datasets.synthetic
--out DIR``).

Statistics, per frame, then the mean over frames (the definitions of issue 9):

- crop to 2.5-100 m, 0.5 m voxel downsampling (small_gicp);
- PCA of each downsampled point's 10 nearest downsampled neighbours (the point included,
  covariance normalised by 10), eigenvalues ``l_min <= l_mid <= l_max``;
- ``thickness_cm``: median ``sqrt(l_min)`` in cm; ``a90`` / ``a99``: fraction of points with
  anisotropy ``1 - l_min / l_max`` above 0.9 / 0.99;
- ``points_per_frame``: downsampled points; ``median_range_m`` of those points;
  ``frac_beyond_40m``: the fraction of them farther than 40 m.

A held-out check, not used to tune anything: ``vgicp_inlier_rmse_cm``, the RMSE of the
nearest-neighbour distances below 1 m after VGICP (small_gicp, 1 m voxels) aligns each
chosen frame onto the frame after it, starting from the identity.

Real scans are "thick" (range noise, beam divergence, calibration, motion) and messy; a
synthetic world that is much thinner or more planar than them makes every figure measured
on it optimistic.
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from gr_graph.atomic import atomic_write_json
from gr_graph.cli_common import add_log_level, add_no_progress, add_point_format, make_parser, setup_logging
from gr_graph.datasets.base import DatasetError

log = logging.getLogger(__name__)

MIN_RANGE_M = 2.5
MAX_RANGE_M = 100.0
VOXEL_SIZE_M = 0.5
NEIGHBOURS = 10
FAR_RANGE_M = 40.0
VGICP_VOXEL_M = 1.0
INLIER_DISTANCE_M = 1.0

STATISTICS = {
    "thickness_cm": "median sqrt(lambda_min) [cm]",
    "a90": "fraction with anisotropy > 0.9",
    "a99": "fraction with anisotropy > 0.99",
    "points_per_frame": "downsampled points per frame",
    "median_range_m": "median range of downsampled points [m]",
    "frac_beyond_40m": "fraction beyond 40 m",
}
HELD_OUT = {"vgicp_inlier_rmse_cm": "VGICP inlier RMSE, consecutive frames [cm] (held out)"}


@dataclass(frozen=True)
class FrameStatistics:
    """The statistics of one frame (see the module docstring)."""

    thickness_cm: float
    a90: float
    a99: float
    points_per_frame: float
    median_range_m: float
    frac_beyond_40m: float


def downsample(points: np.ndarray) -> np.ndarray:
    """Crop to [2.5, 100] m and voxel-downsample at 0.5 m (small_gicp); ``(M, 3)`` float64."""
    import small_gicp

    p = np.asarray(points, np.float64)[:, :3]
    r = np.linalg.norm(p, axis=1)
    p = np.ascontiguousarray(p[(r >= MIN_RANGE_M) & (r <= MAX_RANGE_M)])
    if len(p) == 0:
        return p.reshape(0, 3)
    return np.asarray(small_gicp.voxelgrid_sampling(p, VOXEL_SIZE_M).points())[:, :3].copy()


def local_eigenvalues(points: np.ndarray, k: int = NEIGHBOURS) -> np.ndarray:
    """``(M, 3)`` ascending eigenvalues of each point's k-nearest-neighbour covariance (normalised by k)."""
    if len(points) < k:
        raise ValueError(f"{len(points)} points are too few for {k}-neighbour PCA")
    _, idx = cKDTree(points).query(points, k=k)
    nb = points[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", centred, centred) / k
    return np.linalg.eigvalsh(cov)


def frame_statistics(points: np.ndarray) -> FrameStatistics:
    """Statistics of one frame's raw points (LiDAR frame, any count of columns >= 3)."""
    return downsampled_statistics(downsample(points))


def downsampled_statistics(ds: np.ndarray) -> FrameStatistics:
    """:func:`frame_statistics` of points already passed through :func:`downsample`."""
    ev = np.maximum(local_eigenvalues(ds), 0.0)
    anisotropy = 1.0 - ev[:, 0] / np.maximum(ev[:, 2], 1e-300)
    rng = np.linalg.norm(ds, axis=1)
    return FrameStatistics(
        thickness_cm=float(100.0 * np.median(np.sqrt(ev[:, 0]))),
        a90=float(np.mean(anisotropy > 0.9)),
        a99=float(np.mean(anisotropy > 0.99)),
        points_per_frame=float(len(ds)),
        median_range_m=float(np.median(rng)),
        frac_beyond_40m=float(np.mean(rng > FAR_RANGE_M)),
    )


def vgicp_inlier_rmse(source: np.ndarray, target: np.ndarray) -> float:
    """RMSE [m] of source-to-target distances below 1 m after VGICP aligns source onto target."""
    return downsampled_vgicp_inlier_rmse(downsample(source), downsample(target))


def downsampled_vgicp_inlier_rmse(src: np.ndarray, tgt: np.ndarray) -> float:
    """:func:`vgicp_inlier_rmse` of points already passed through :func:`downsample`."""
    import small_gicp

    result = small_gicp.align(tgt, src, registration_type="VGICP", voxel_resolution=VGICP_VOXEL_M,
                              max_correspondence_distance=INLIER_DISTANCE_M, num_threads=1)
    T = np.asarray(result.T_target_source)
    moved = src @ T[:3, :3].T + T[:3, 3]
    d, _ = cKDTree(tgt).query(moved, k=1)
    inl = d[d < INLIER_DISTANCE_M]
    return float(np.sqrt(np.mean(inl**2))) if len(inl) else float("nan")


def pair_statistics(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Every statistic of frame ``a`` and the held-out VGICP inlier RMSE [cm] of ``a`` onto ``b``
    (each frame downsampled once)."""
    ds_a = downsample(a)
    row = asdict(downsampled_statistics(ds_a))
    row["vgicp_inlier_rmse_cm"] = 100.0 * downsampled_vgicp_inlier_rmse(ds_a, downsample(b))
    return row


def chosen_frames(n_frames: int, max_frames: int) -> np.ndarray:
    """Up to ``max_frames`` frame indices spread evenly over ``n_frames`` (each with a successor)."""
    if n_frames < 2:
        raise DatasetError(f"need at least 2 frames, found {n_frames}")
    last = n_frames - 2  # every chosen frame has a next frame for the held-out check
    count = min(max_frames, last + 1)
    return np.unique(np.round(np.linspace(0, last, count)).astype(np.int64))


def folder_statistics(root: str | Path, seq: str = "00", max_frames: int = 50,
                      progress: bool = True, point_format: str = "xyzi") -> dict[str, object]:
    """Mean (and spread) of every statistic over frames of one KITTI-layout folder
    (``point_format``: layout of its ``.bin`` files, see :class:`gr_graph.datasets.kitti.KittiSequence`).

    Returns
    -------
    dict
        ``{"folder", "frames", "mean": {stat: value}, "std": {stat: value}}``; ``mean``
        and ``std`` include the held-out ``vgicp_inlier_rmse_cm``.
    """
    from tqdm import tqdm

    from gr_graph.datasets.kitti import KittiSequence

    seq_obj = KittiSequence(root, seq, recover_ring_index=False, point_format=point_format)
    frames = chosen_frames(len(seq_obj), max_frames)
    rows: list[dict[str, float]] = []
    for i in tqdm(frames, desc=f"realism {Path(root).name}", unit="frame", disable=not progress):
        rows.append(pair_statistics(seq_obj[int(i)].points, seq_obj[int(i) + 1].points))
    keys = list(STATISTICS) + list(HELD_OUT)
    table = np.array([[r[k] for k in keys] for r in rows])
    return {
        "folder": str(root),
        "frames": [int(i) for i in frames],
        "mean": dict(zip(keys, np.nanmean(table, axis=0).tolist())),
        "std": dict(zip(keys, np.nanstd(table, axis=0).tolist())),
    }


def format_table(results: list[dict[str, object]]) -> str:
    """A Markdown table: one row per statistic, one column per folder; the first folder is the
    reference, later columns show their relative difference to it."""
    names = [Path(str(r["folder"])).name or str(r["folder"]) for r in results]
    lines = ["| statistic | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    ref = results[0]["mean"]
    for key, label in {**STATISTICS, **HELD_OUT}.items():
        cells = []
        for j, r in enumerate(results):
            v = r["mean"][key]  # type: ignore[index]
            cell = f"{v:,.3g}" if abs(v) < 1000 else f"{v:,.0f}"
            if j > 0 and ref[key]:  # type: ignore[index]
                cell += f" ({100.0 * (v / ref[key] - 1.0):+.0f} %)"  # type: ignore[index]
            cells.append(cell)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


EXAMPLES = (
    "python -m gr_graph.datasets.realism ../shared/data/kitti runs/synthetic_kitti --max-frames 50 --out realism.json",
    "python -m gr_graph.datasets.realism /data/kitti /data/xyz_only --point-format xyz --no-progress",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m gr_graph.datasets.realism``."""
    parser = make_parser("python -m gr_graph.datasets.realism",
                         "Local-geometry statistics of KITTI-layout LiDAR folders (the first is the reference).",
                         EXAMPLES)
    parser.add_argument("folders", nargs="+", type=Path, help="KITTI odometry roots (sequences/<seq>/velodyne)")
    parser.add_argument("--seq", default="00", help="sequence inside every folder")
    add_point_format(parser, help="layout of the .bin files of every folder: float32 x,y,z,intensity "
                                  "(16 bytes a point) or x,y,z (12 bytes a point)")
    parser.add_argument("--max-frames", type=int, default=50, metavar="N", help="frames per folder, spread evenly")
    parser.add_argument("--out", default=None, metavar="FILE", help="write the results as JSON here")
    add_no_progress(parser)
    add_log_level(parser, default="WARNING")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level)
    if args.max_frames < 1:
        print("error: --max-frames must be >= 1", file=sys.stderr)
        return 2
    try:
        results = [folder_statistics(f, args.seq, args.max_frames, not args.no_progress, args.point_format)
                   for f in args.folders]
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(format_table(results))
    if args.out is not None:
        atomic_write_json(args.out, {"definitions": {**STATISTICS, **HELD_OUT}, "results": results})
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
