"""What a SLAM run writes: a round's folder, its summary, ``metrics.json`` and the plot.

Output directory (``--out``)::

    config.yaml              the resolved configuration
    gt_poses_kitti.txt       ground truth of the run's frames, camera frame (when known)
    metrics.json             per round: trajectory metrics, loops, runtimes, acceptance (rewritten per round)
    poses_kitti.txt          the final trajectory (metrics.json "final_round": the last round of the
                             unbroken run of accepted rounds)
    poses_tum.txt            the same poses in TUM form, in the LiDAR frame (T_w_velo; the KITTI
                             file is in the camera frame, as KITTI's ground truth)
    trajectory.png           the final round against ground truth (top-down, LiDAR frame), with the
                             3-sigma position ellipses (magnified, the legend says by how much)
    rounds.png               with learning rounds: RPE and ATE per round (ground truth needed)
    round_<r>/poses_kitti.txt    optimised poses, camera frame, KITTI format (first = identity)
    round_<r>/poses_tum.txt      the same poses in the LiDAR frame, TUM format (timestamps)
    round_<r>/odometry_kitti.txt odometry-only poses (before loop closure), camera frame
    round_<r>/marginals.npz      see :data:`MARGINALS_KEYS`
    round_<r>/loops.json         every verified loop candidate (accepted or not) with figures
    round_<r>/map.ply            the round's scans placed with its optimised poses, voxel-downsampled
                                 (``output.map``; :mod:`gr_graph.map_export`)
    round_<r>/memory/            the memory of the round (:mod:`gr_graph.memory_builder`)
    round_<r>/training/          rounds r >= 1: the trainer's model.pt, checkpoint.pt, log, summary
    round_<r>/round.json         written last: the round's summary; marks the round finished
    frames/                  while learning rounds run on made (synthetic) frames: round 0's frames,
                             read back by later rounds; deleted at the end (:mod:`gr_graph.datasets.frame_cache`)

Every file is written atomically (temporary sibling, then rename).

``metrics.json`` = ``{"source", "n_frames", "data_fingerprint", "channels", "rounds": {"<r>": summary}}`` (and
``frame_cache``: frames read back, made, unreadable, not stored, when the cache was on); a
round's summary (also its ``round.json``, :func:`round_summary`) holds counts (frames,
odometry edges, flagged edges, loops, loop candidates), ``slam`` and ``odometry``
(:func:`gr_graph.metrics.trajectory_metrics` of the optimised and the odometry-only poses
against the ground truth, both in the camera frame: RPE over 300 frames mean/RMSE for
consecutive and all pairs, ATE, KITTI devkit %), ``loop_closure`` (precision/recall against
ground truth, :func:`gr_graph.loop_evaluation.loop_precision_recall`), ``runtime_s`` per stage
(``read`` is time spent waiting for frames), ``frames_per_second`` and
``config_fingerprint``, ``data_fingerprint`` (the input's identity, checked on resume:
:func:`gr_graph.pipeline.data_fingerprint`), ``n_unusable_scans``, ``marginals``
(:class:`gr_graph.pose_graph.MarginalsReport`: ``status`` "ok",
or how a graph gtsam could not marginalise was handled, which poses failed; None when disabled);
with ground truth and marginals, ``noise_consistency`` (NEES per edge kind and of the marginals,
:mod:`gr_graph.noise_consistency`); learning rounds add ``edge_noise``, ``densify``,
``covariance_failures`` (:mod:`gr_graph.covariance_health`) and ``runtime_s.training``, and every
round after the first ``trajectory_change``; ``map`` (points in, voxels out, voxel size) when the
map is written. Every round carries ``accepted`` (round 0: true); learning rounds ``acceptance``
(:mod:`gr_graph.round_acceptance`). The run adds ``final_round`` (and why), ``accepted_rounds``,
``rejected_rounds``, ``stopped`` (after a rejection) and ``marginals_fallback_rounds`` (rounds whose
marginals needed a fallback).

"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.atomic import atomic_save_npz, atomic_write_json, read_json_or_none
from gr_graph.datasets.base import velo_to_cam_poses
from gr_graph.frame_loop import SlamResult, not_converged_counts
from gr_graph.pose_graph import position_covariance_world
from gr_graph.trajectory import write_kitti_poses, write_tum_poses

__all__ = ["MARGINALS_KEYS", "round_dir", "write_round_results", "write_round_map", "round_summary",
           "write_round_summary", "read_round_summary", "read_round_poses", "write_metrics", "plot_round",
           "plot_metrics_rounds"]

MARGINALS_KEYS = {
    "frame_index": "(K,) int64 frame index of each pose in the sequence",
    "timestamps": "(K,) float64 seconds",
    "poses": "(K, 4, 4) optimised T_w_velo (world = LiDAR frame of the first scan)",
    "covariance": "(K, 6, 6) marginal covariance of each pose, gtsam order [omega, v], body frame, "
    "right perturbation P*Exp(xi)",
    "position_cov_world": "(K, 3, 3) world-frame position covariance R Sigma_vv R^T",
    "odometry_poses": "(K, 4, 4) odometry-only T_w_velo (before loop closure)",
    "gt_poses": "(K, 4, 4) ground-truth T_w_velo re-anchored to the first scan (absent without GT)",
    "edges": "(E, 2) int64 graph edges (k, l) as run positions: odometry (k+1, k), loops (i, j)",
    "edge_kind": "(E,) uint8 0 = odometry, 1 = loop",
    "edge_ok": "(E,) bool False for flagged (fallback) odometry edges",
    "edge_information": "(E, 6, 6) information of each graph factor (before the loop kernel), [omega, v]",
    "edge_T": "(E, 4, 4) measurement T̂_kl of each edge (maps scan k into the frame of scan l)",
}


def round_dir(out: Path, r: int) -> Path:
    """``out/round_<r>``."""
    return Path(out) / f"round_{r}"


def write_round_results(rd: Path, res: SlamResult, T_cam_velo: np.ndarray, gt: np.ndarray | None) -> None:
    """Poses (KITTI, TUM, odometry-only), ``marginals.npz`` and ``loops.json`` of a round into ``rd``.

    ``gt`` is the ground truth re-anchored to the first scan (LiDAR frame) or None.
    """
    write_kitti_poses(rd / "poses_kitti.txt", velo_to_cam_poses(res.poses, T_cam_velo))
    write_kitti_poses(rd / "odometry_kitti.txt", velo_to_cam_poses(res.odometry_poses, T_cam_velo))
    write_tum_poses(rd / "poses_tum.txt", res.timestamps, res.poses)
    arrays: dict[str, np.ndarray] = {
        "frame_index": res.frame_index,
        "timestamps": res.timestamps,
        "poses": res.poses,
        "odometry_poses": res.odometry_poses,
        "edges": np.asarray([(e.source, e.target) for e in res.edges], np.int64).reshape(-1, 2),
        "edge_kind": np.asarray([e.kind == "loop" for e in res.edges], np.uint8),
        "edge_ok": np.asarray([e.ok for e in res.edges], bool),
        "edge_information": np.asarray([e.information for e in res.edges], np.float64).reshape(-1, 6, 6),
        "edge_T": np.asarray([e.T for e in res.edges], np.float64).reshape(-1, 4, 4),
    }
    if res.covariances is not None:
        arrays["covariance"] = res.covariances
        arrays["position_cov_world"] = position_covariance_world(res.poses, res.covariances)
    if gt is not None:
        arrays["gt_poses"] = gt
    atomic_save_npz(rd / "marginals.npz", **arrays)
    atomic_write_json(rd / "loops.json", res.loop_attempts)


def write_round_map(rd: Path, res: SlamResult, voxel_size: float) -> dict[str, Any]:
    """``rd/map.ply``: the round's scans placed with its optimised poses, one point per voxel;
    returns the counts for the round's summary."""
    from gr_graph.map_export import map_path, write_map

    return write_map(map_path(rd), res.scans, res.poses, voxel_size)


def round_summary(r: int, res: SlamResult, fingerprint: str, mean_points_per_scan: float,
                  data_fingerprint: dict[str, Any] | None = None) -> dict[str, Any]:
    """The counts of a round's summary (the caller adds metrics, edge noise, runtimes).

    ``data_fingerprint`` (:func:`gr_graph.pipeline.data_fingerprint`) is the identity of the
    input the round was made from, checked when a rerun resumes.
    """
    return {
        "round": r,
        "config_fingerprint": fingerprint,
        "data_fingerprint": data_fingerprint,
        "n_frames": len(res.poses),
        # scans with fewer than preprocess.min_points points: their odometry edges are guesses
        "n_unusable_scans": res.info.get("n_unusable_scans"),
        "n_odometry_edges": sum(e.kind == "odometry" for e in res.edges),
        "n_flagged_odometry_edges": res.info["n_flagged_odometry"],
        # accepted edges whose registration did not pass small_gicp's convergence test (kept)
        **{f"n_{kind}_edges_not_converged": n for kind, n in not_converged_counts(res.edges).items()},
        "n_loops": len(res.loops),
        "n_loop_candidates": len(res.loop_attempts),
        "graph_error": list(res.graph_error),
        "mean_points_per_scan": mean_points_per_scan,
        "deskew": res.info.get("deskew"),
        # frame stamps off the sensor's beat, moved onto it for the odometry's guess and the deskewing
        "stamp_gaps": res.info.get("stamp_gaps"),
        "sensor": res.info.get("sensor"),
        "marginals": res.info.get("marginals"),
        "loop_variance": res.info.get("loop_variance"),
        # graph.ground_tilt_offset (only when on): scans without a ground plane, edges widened, RMS offsets
        **({"ground_tilt_offset": res.info["ground_tilt_offset"]} if res.info.get("ground_tilt_offset") else {}),
        # usable scans that did not enter the odometry's map (odometry.map_keyframe_*; 0 by default)
        "scans_left_out_of_map": res.info.get("scans_left_out_of_map"),
        # the information each accepted edge entered the graph with: the registration's model
        # (graph.registration_covariance; "scaled_hessian_fallback" where the cluster-robust covariance was not
        # available) or "learned" where the learned edge noise replaced it
        "registration_covariance": dict(Counter(
            "learned" if e.info.get("edge_noise") == "learned" else str(e.info.get("covariance", "none"))
            for e in res.edges if e.ok)),
    }


def trajectory_summary(res: SlamResult, gt: np.ndarray, T_cam_velo: np.ndarray,
                       min_frame_gap: int, min_path_length: float = 0.0) -> dict[str, Any]:
    """``slam``, ``odometry`` (trajectory metrics in the camera frame) and ``loop_closure``
    (precision/recall) of a round against the re-anchored ground truth ``gt``."""
    from gr_graph.loop_evaluation import loop_precision_recall
    from gr_graph.metrics import trajectory_metrics

    gt_cam = velo_to_cam_poses(gt, T_cam_velo)
    out: dict[str, Any] = {}
    if len(res.poses) >= 2:
        out["slam"] = trajectory_metrics(velo_to_cam_poses(res.poses, T_cam_velo), gt_cam, delta=300)
        out["odometry"] = trajectory_metrics(velo_to_cam_poses(res.odometry_poses, T_cam_velo), gt_cam, delta=300)
    loops = [(e.source, e.target, e.T) for e in res.loops]
    out["loop_closure"] = loop_precision_recall(loops, gt, res.checked, min_frame_gap,
                                                min_path_length=min_path_length)
    return out


def write_round_summary(rd: Path, summary: dict[str, Any]) -> None:
    """``round.json``: written last, it marks the round as finished."""
    atomic_write_json(rd / "round.json", summary)


def read_round_summary(rd: Path) -> dict[str, Any] | None:
    """The summary of a finished round, or None (no ``round.json``, or an unreadable one)."""
    return read_json_or_none(rd / "round.json")


def read_round_poses(rd: Path) -> np.ndarray:
    """The optimised poses ``(K, 4, 4)`` of a finished round."""
    with np.load(rd / "marginals.npz") as z:
        return np.array(z["poses"])


def write_metrics(out: Path, metrics: dict[str, Any]) -> None:
    """``metrics.json`` of the run."""
    atomic_write_json(Path(out) / "metrics.json", metrics)


def plot_round(rd: Path, png: Path, gt: np.ndarray | None, title: str) -> None:
    """Top-down plot of a round's poses, odometry and loops against the ground truth."""
    from gr_graph.plots import plot_trajectory

    with np.load(rd / "marginals.npz") as z:
        poses = np.array(z["poses"])
        odom = np.array(z["odometry_poses"]) if "odometry_poses" in z.files else None
        edges, kind = np.array(z["edges"]), np.array(z["edge_kind"])
        cov = np.array(z["position_cov_world"]) if "position_cov_world" in z.files else None
    plot_trajectory(png, poses, gt, loops=edges[kind == 1], odometry=odom, title=title, position_cov=cov)


def plot_metrics_rounds(out: Path, metrics: dict[str, Any], title: str) -> Path:
    """``out/rounds.png``: RPE and ATE per round (:func:`gr_graph.plots.plot_rounds`)."""
    from gr_graph.plots import plot_rounds

    return plot_rounds(Path(out) / "rounds.png", metrics, title=title)
