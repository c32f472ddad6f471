"""Trajectory metrics: RPE and ATE through evo's Python API, and the KITTI devkit errors.

All functions take poses as ``(K, 4, 4)`` arrays (or :class:`~gr_graph.trajectory.Trajectory`)
with ``est[i]`` and ``ref[i]`` describing the same frame ``i``; both must be expressed in
the same convention (for KITTI: camera-0 poses, like the official ground truth).

- :func:`rpe_translation`: evo ``RPE`` on the translation part of the relative error over
  ``delta`` frames, consecutive windows (``all_pairs=False``: pairs (0, d), (d, 2d), ...) or
  all pairs (``(i, i + d)`` for every ``i``). Identical to
  ``evo_rpe kitti ref est --delta d --delta_unit f --pose_relation trans_part [--all_pairs]``.
- :func:`ate`: evo ``APE`` on the translation part after Umeyama alignment (SE(3), or
  Sim(3) with ``correct_scale``).
- :func:`kitti_devkit_errors`: the KITTI odometry benchmark metric, written from the
  devkit's algorithm: for every first frame ``f = 0, step, 2 step, ...`` and every segment
  length ``L`` in ``lengths``, the last frame is the first ``l`` whose ground-truth path
  length from ``f`` exceeds ``L``; the error pose is ``E = (est_f^-1 est_l)^-1 (ref_f^-1
  ref_l)``; translation error ``|t(E)| / L`` and rotation error ``angle(R(E)) / L``
  averaged over all segments, reported in % and deg / 100 m. (The angle is computed with
  atan2 instead of the devkit's acos: same value, no precision loss near zero.)
- :func:`ate_by_axis`: that ATE split into height and the horizontal plane.
- :func:`trajectory_metrics`: all of the above as a JSON-serialisable dict.

Inputs that cannot give a value (fewer than ``delta + 1`` frames, a path shorter than the
shortest segment) raise :class:`InsufficientTrajectoryError` in the single-metric functions;
:func:`trajectory_metrics` turns that into ``None`` and a log line.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from factors.se3 import check_poses, rotation_angle
from factors.wls import umeyama
from gr_graph.trajectory import Trajectory, to_evo_path

logger = logging.getLogger(__name__)

KITTI_LENGTHS: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
KITTI_STEP = 10


class InsufficientTrajectoryError(ValueError):
    """The trajectory is too short for the requested metric (e.g. fewer than delta+1 frames)."""


class DegenerateAlignmentError(InsufficientTrajectoryError):
    """Umeyama alignment is undetermined (e.g. all reference positions on one line)."""


@dataclass(frozen=True)
class RPEStats:
    """Statistics of the translational RPE (metres) over ``n`` pose pairs."""

    mean: float
    rmse: float
    median: float
    max: float
    min: float
    std: float
    n: int
    delta: int
    all_pairs: bool

    def as_dict(self) -> dict[str, Any]:
        """Return the fields as a plain dict."""
        return asdict(self)


@dataclass(frozen=True)
class ATEStats:
    """Statistics of the absolute translation error (metres) after alignment."""

    rmse: float
    mean: float
    median: float
    max: float
    min: float
    std: float
    n: int
    aligned: bool
    scale: float

    def as_dict(self) -> dict[str, Any]:
        """Return the fields as a plain dict."""
        return asdict(self)


# ----------------------------------------------------------------------------- inputs


def _as_poses(x: np.ndarray | Trajectory, name: str) -> np.ndarray:
    if isinstance(x, Trajectory):
        return x.poses
    return check_poses(x, name)


#: two timed trajectories are paired frame by frame only where their timestamps agree within this [s]
TIMESTAMP_TOLERANCE = 1e-3


def _pair(est: np.ndarray | Trajectory, ref: np.ndarray | Trajectory) -> tuple[np.ndarray, np.ndarray]:
    e = _as_poses(est, "est")
    r = _as_poses(ref, "ref")
    if len(e) != len(r):
        raise ValueError(
            f"est has {len(e)} poses but ref has {len(r)}: trajectories must be associated "
            "frame by frame (same length)"
        )
    if len(e) == 0:
        raise ValueError("empty trajectories")
    if isinstance(est, Trajectory) and isinstance(ref, Trajectory):  # both timed: the times must agree too
        gap = np.abs(est.timestamps - ref.timestamps)
        if gap.max() > TIMESTAMP_TOLERANCE:
            k = int(np.argmax(gap > TIMESTAMP_TOLERANCE))
            raise ValueError(
                f"est and ref are paired frame by frame, but their timestamps differ by up to {gap.max():.6g} s "
                f"(first at pose {k}: {est.timestamps[k]!r} against {ref.timestamps[k]!r}); associate them by "
                "time first (e.g. evo's associate_trajectories) or pass the pose arrays")
    return e, r


def _stats(error: np.ndarray) -> dict[str, float]:
    return {
        "mean": float(np.mean(error)),
        "rmse": float(math.sqrt(np.mean(np.square(error)))),
        "median": float(np.median(error)),
        "max": float(np.max(error)),
        "min": float(np.min(error)),
        "std": float(np.std(error)),
    }


# ----------------------------------------------------------------------------- RPE / ATE


def rpe_translation(
    est: np.ndarray | Trajectory,
    ref: np.ndarray | Trajectory,
    delta: int = 300,
    all_pairs: bool = False,
) -> RPEStats:
    """Translational relative pose error over ``delta`` frames, via ``evo.core.metrics.RPE``.

    Parameters
    ----------
    est, ref : (K, 4, 4) array or Trajectory
        Estimated and reference poses, associated by index.
    delta : int
        Window length in frames.
    all_pairs : bool
        False: consecutive windows (0, d), (d, 2d), ...; True: every (i, i + d).

    Returns
    -------
    RPEStats
        mean, rmse, median, max, min, std (metres) and the number of pairs ``n``.

    Raises
    ------
    ValueError
        Mismatched lengths or invalid poses.
    InsufficientTrajectoryError
        Fewer than ``delta + 1`` poses.
    """
    from evo.core import metrics as evo_metrics

    e, r = _pair(est, ref)
    delta = int(delta)
    if delta < 1:
        raise ValueError(f"delta must be a positive number of frames, got {delta}")
    if len(e) <= delta:
        raise InsufficientTrajectoryError(
            f"RPE over {delta} frames needs at least {delta + 1} poses, got {len(e)}"
        )
    metric = evo_metrics.RPE(
        evo_metrics.PoseRelation.translation_part,
        delta=delta,
        delta_unit=evo_metrics.Unit.frames,
        all_pairs=all_pairs,
        pairs_from_reference=False,
    )
    metric.process_data((to_evo_path(r), to_evo_path(e)))
    err = np.asarray(metric.error, dtype=np.float64)
    return RPEStats(**_stats(err), n=int(err.size), delta=delta, all_pairs=bool(all_pairs))


def _aligned_paths(est: np.ndarray | Trajectory, ref: np.ndarray | Trajectory, align: bool = True,
                   correct_scale: bool = False) -> tuple[Any, Any, float]:
    """evo paths of ``ref`` and ``est`` with ``est`` Umeyama-aligned to ``ref`` (SE(3), or Sim(3)
    with ``correct_scale``; with ``align=False`` and ``correct_scale``: scale only), and the scale."""
    e, r = _pair(est, ref)
    ref_path, est_path = to_evo_path(r), to_evo_path(e)
    scale = 1.0
    if align or correct_scale:
        if len(e) < 3:
            raise InsufficientTrajectoryError(f"alignment needs at least 3 poses, got {len(e)}")
        from evo.core.geometry import GeometryException

        try:
            _, _, s = est_path.align(
                ref_path, correct_scale=correct_scale, correct_only_scale=correct_scale and not align
            )
        except GeometryException as exc:
            if correct_scale:  # the scale is undetermined as well: no fallback
                raise DegenerateAlignmentError(
                    f"Umeyama alignment is not possible ({exc}); the {_degenerate_side(e, r)} positions are "
                    "collinear or coincident"
                ) from exc
            # a straight or stationary path (e.g. a run that failed): the best rigid fit is not unique,
            # but its error is; evo refuses the rank-deficient case, factors.wls.umeyama takes one of them
            est_path.transform(umeyama(est_path.positions_xyz, ref_path.positions_xyz))
            s = 1.0
        scale = float(s)
    return ref_path, est_path, scale


def _degenerate_side(est: np.ndarray, ref: np.ndarray) -> str:
    """Which positions make an alignment degenerate: 'estimated', 'reference' or 'estimated and reference'."""
    def flat(P: np.ndarray) -> bool:
        x = P[:, :3, 3] - P[:, :3, 3].mean(axis=0)
        sv = np.linalg.svd(x, compute_uv=False)
        return bool(sv[1] <= 1e-9 * max(sv[0], 1e-300))
    sides = [name for name, P in (("estimated", est), ("reference", ref)) if flat(P)]
    return " and ".join(sides) or "estimated and reference"


def ate(
    est: np.ndarray | Trajectory,
    ref: np.ndarray | Trajectory,
    align: bool = True,
    correct_scale: bool = False,
) -> ATEStats:
    """Absolute trajectory error on the translation, via ``evo.core.metrics.APE``.

    Parameters
    ----------
    est, ref : (K, 4, 4) array or Trajectory
        Estimated and reference poses, associated by index.
    align : bool
        Umeyama-align ``est`` to ``ref`` first (SE(3); Sim(3) with ``correct_scale``).
    correct_scale : bool
        Also estimate a scale (with ``align=False``: scale only, as evo's ``-s``).

    Returns
    -------
    ATEStats
        rmse, mean, median, max, min, std (metres), ``n`` and the alignment scale.

    Raises
    ------
    ValueError
        Mismatched lengths or invalid poses.
    InsufficientTrajectoryError
        Alignment requested with fewer than 3 poses.
    DegenerateAlignmentError
        A scale asked for but undetermined (collinear or coincident positions). Without a scale a
        straight or stationary path is aligned by the best rigid fit (its rotation about the line
        is not unique, its error is).
    """
    from evo.core import metrics as evo_metrics

    ref_path, est_path, scale = _aligned_paths(est, ref, align, correct_scale)
    metric = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    metric.process_data((ref_path, est_path))
    err = np.asarray(metric.error, dtype=np.float64)
    return ATEStats(**_stats(err), n=int(err.size), aligned=bool(align), scale=scale)


def ate_by_axis(est: np.ndarray | Trajectory, ref: np.ndarray | Trajectory, vertical_axis: int = 1) -> dict[str, float]:
    """The SE(3)-aligned ATE split into height and the horizontal plane.

    ``est`` is Umeyama-aligned to ``ref`` as in :func:`ate`; the position errors are then split
    along axis ``vertical_axis`` of the frame ``ref``'s positions are expressed in (its world
    frame: for KITTI camera poses the first camera frame, whose y axis points down; 2 for LiDAR /
    TUM-style poses, z up) and the other two axes. That axis is the vertical only as far as the
    first frame stood level (on KITTI within about a degree).

    Returns
    -------
    dict
        ``rmse`` (equal to ``ate(est, ref).rmse``), ``vertical_rmse`` and ``horizontal_rmse``
        (metres; ``vertical_rmse**2 + horizontal_rmse**2 == rmse**2``).

    Raises
    ------
    ValueError
        Mismatched lengths, invalid poses, or ``vertical_axis`` not 0, 1 or 2.
    InsufficientTrajectoryError
        Fewer than 3 poses.

    Notes
    -----
    With collinear or coincident positions the aligning rotation about the line is not unique:
    ``rmse`` is, the split between height and plane is that of one best fit.
    """
    if vertical_axis not in (0, 1, 2):
        raise ValueError(f"vertical_axis must be 0, 1 or 2, got {vertical_axis}")
    ref_path, est_path, _ = _aligned_paths(est, ref)
    err = np.asarray(est_path.positions_xyz) - np.asarray(ref_path.positions_xyz)
    vertical = err[:, vertical_axis]
    horizontal = np.delete(err, vertical_axis, axis=1)
    return {"rmse": float(math.sqrt(np.mean(np.sum(err**2, axis=1)))),
            "vertical_rmse": float(math.sqrt(np.mean(vertical**2))),
            "horizontal_rmse": float(math.sqrt(np.mean(np.sum(horizontal**2, axis=1))))}


# ----------------------------------------------------------------------------- KITTI devkit


def path_distances(poses: np.ndarray) -> np.ndarray:
    """Cumulative path length ``(K,)`` along ``poses`` (0 at frame 0): ``(K, 4, 4)`` poses (their
    translations) or ``(K, 3)`` positions."""
    poses = np.asarray(poses)
    positions = poses[:, :3, 3] if poses.ndim == 3 else poses
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


@dataclass(frozen=True)
class KittiSegments:
    """Per-segment KITTI devkit errors.

    Attributes
    ----------
    first, last : np.ndarray
        ``(S,)`` int frame indices of each segment.
    length : np.ndarray
        ``(S,)`` nominal segment length L (metres).
    t_err : np.ndarray
        ``(S,)`` translation error divided by L (dimensionless).
    r_err : np.ndarray
        ``(S,)`` rotation error divided by L (rad / m).
    """

    first: np.ndarray
    last: np.ndarray
    length: np.ndarray
    t_err: np.ndarray
    r_err: np.ndarray


def kitti_devkit_segments(
    est: np.ndarray | Trajectory,
    ref: np.ndarray | Trajectory,
    lengths: tuple[float, ...] = KITTI_LENGTHS,
    step: int = KITTI_STEP,
) -> KittiSegments:
    """Per-segment errors of the KITTI odometry devkit (see :func:`kitti_devkit_errors`)."""
    e, r = _pair(est, ref)
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    dist = path_distances(r)
    K = len(r)
    firsts = np.arange(0, K, int(step))
    fs, ls, Ls = [], [], []
    for L in lengths:
        # First index whose GT path length from `first` strictly exceeds L (devkit rule).
        last = np.searchsorted(dist, dist[firsts] + float(L), side="right")
        ok = last < K
        fs.append(firsts[ok])
        ls.append(last[ok])
        Ls.append(np.full(int(ok.sum()), float(L)))
    # Order segments like the devkit: by first frame, then by length.
    first = np.concatenate(fs)
    last = np.concatenate(ls)
    length = np.concatenate(Ls)
    order = np.lexsort((length, first))
    first, last, length = first[order], last[order], length[order]
    if first.size == 0:
        return KittiSegments(first, last, length, np.zeros(0), np.zeros(0))
    d_ref = np.linalg.inv(r[first]) @ r[last]
    d_est = np.linalg.inv(e[first]) @ e[last]
    err = np.linalg.inv(d_est) @ d_ref
    t_err = np.linalg.norm(err[:, :3, 3], axis=1)
    # Rotation angle of R(E): the devkit's acos((tr R - 1) / 2), computed without acos's loss
    # of precision near 0 (factors.se3.rotation_angle).
    r_err = rotation_angle(err[:, :3, :3])
    return KittiSegments(first, last, length, t_err / length, r_err / length)


def kitti_devkit_errors(
    est: np.ndarray | Trajectory,
    ref: np.ndarray | Trajectory,
    lengths: tuple[float, ...] = KITTI_LENGTHS,
    step: int = KITTI_STEP,
) -> tuple[float, float]:
    """KITTI odometry benchmark errors: translation (%) and rotation (deg / 100 m).

    Parameters
    ----------
    est, ref : (K, 4, 4) array or Trajectory
        Estimated and ground-truth poses (same frame, associated by index).
    lengths : tuple of float
        Segment lengths in metres (devkit: 100, 200, ..., 800).
    step : int
        Frames between segment starts (devkit: 10).

    Returns
    -------
    t_err_percent : float
        Mean over all segments of ``|t(E)| / L``, times 100.
    r_err_deg_per_100m : float
        Mean over all segments of ``angle(R(E)) / L``, in degrees per 100 m.

    Raises
    ------
    InsufficientTrajectoryError
        No segment fits (ground-truth path shorter than the shortest length).
    """
    seg = kitti_devkit_segments(est, ref, lengths, step)
    if seg.first.size == 0:
        total = float(path_distances(_as_poses(ref, "ref"))[-1])
        raise InsufficientTrajectoryError(
            f"KITTI devkit metric: reference path is {total:.1f} m, shorter than the "
            f"shortest segment length {min(lengths):g} m"
        )
    return float(np.mean(seg.t_err) * 100.0), float(np.degrees(np.mean(seg.r_err)) * 100.0)


# ----------------------------------------------------------------------------- bundle


def trajectory_metrics(
    est: np.ndarray | Trajectory,
    ref: np.ndarray | Trajectory,
    delta: int = 300,
) -> dict[str, Any]:
    """All trajectory metrics as a JSON-serialisable dict (for ``metrics.json``).

    Keys (``{d}`` is ``delta``): ``n_frames``, ``rpe_delta_frames``,
    ``rpe{d}_consecutive_{mean,rmse,median,max,n}``, ``rpe{d}_all_pairs_{mean,rmse,median,max,n}``,
    ``ate_rmse``, ``ate_mean``, ``ate_median``, ``ate_max`` (SE(3)-aligned),
    ``ate_sim3_rmse`` (Sim(3)-aligned), ``ate_sim3_scale``,
    ``kitti_t_err_percent``, ``kitti_r_err_deg_per_100m``, ``kitti_n_segments``.
    Values that cannot be computed (trajectory too short) are ``None`` and logged.

    Raises
    ------
    ValueError
        Mismatched lengths or invalid poses.
    """
    e, r = _pair(est, ref)
    out: dict[str, Any] = {"n_frames": int(len(e)), "rpe_delta_frames": int(delta)}
    for label, all_pairs in (("consecutive", False), ("all_pairs", True)):
        prefix = f"rpe{int(delta)}_{label}"
        try:
            s = rpe_translation(e, r, delta=delta, all_pairs=all_pairs)
            vals: dict[str, Any] = {"mean": s.mean, "rmse": s.rmse, "median": s.median, "max": s.max, "n": s.n}
        except InsufficientTrajectoryError as exc:
            logger.warning("%s: %s; reporting None", prefix, exc)
            vals = {"mean": None, "rmse": None, "median": None, "max": None, "n": 0}
        out.update({f"{prefix}_{k}": v for k, v in vals.items()})
    try:
        a = ate(e, r, align=True, correct_scale=False)
        out.update(ate_rmse=a.rmse, ate_mean=a.mean, ate_median=a.median, ate_max=a.max)
    except InsufficientTrajectoryError as exc:
        logger.warning("ATE: %s; reporting None", exc)
        out.update(ate_rmse=None, ate_mean=None, ate_median=None, ate_max=None)
    try:  # a straight or stationary path has an SE(3) ATE but no scale
        a7 = ate(e, r, align=True, correct_scale=True)
        out.update(ate_sim3_rmse=a7.rmse, ate_sim3_scale=a7.scale)
    except InsufficientTrajectoryError as exc:
        logger.warning("ATE with scale (Sim(3)): %s; reporting None", exc)
        out.update(ate_sim3_rmse=None, ate_sim3_scale=None)
    seg = kitti_devkit_segments(e, r)
    if seg.first.size:
        out["kitti_t_err_percent"] = float(np.mean(seg.t_err) * 100.0)
        out["kitti_r_err_deg_per_100m"] = float(np.degrees(np.mean(seg.r_err)) * 100.0)
    else:
        logger.warning(
            "KITTI devkit metric: reference path %.1f m is shorter than %g m; reporting None",
            float(path_distances(r)[-1]),
            min(KITTI_LENGTHS),
        )
        out["kitti_t_err_percent"] = None
        out["kitti_r_err_deg_per_100m"] = None
    out["kitti_n_segments"] = int(seg.first.size)
    return out
