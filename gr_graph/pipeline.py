"""The SLAM pipeline F_SLAM and the reciprocal rounds around it (Algorithm 3 of the paper).

:class:`SlamPipeline` ``run()`` does everything: round 0 is SLAM on the raw scans
(odometry, loop closures, pose graph, marginals, memory); rounds r ≥ 1 (learning rounds:
train f_θ from the memory of round r−1 into ``round_<r>/training``, densify the scans with it
(:mod:`gr_graph.densify`), SLAM again on the densified scans) need the trainer and raise
:class:`LearningRoundsUnavailable` when it is not importable.

Output directory (``--out``)::

    config.yaml              the resolved configuration
    gt_poses_kitti.txt       ground truth of the run's frames, camera frame (when known)
    metrics.json             per round: trajectory metrics, loops, runtimes (rewritten per round)
    trajectory.png           last round against ground truth (top-down, LiDAR frame)
    round_<r>/poses_kitti.txt    optimised poses, camera frame, KITTI format (first = identity)
    round_<r>/poses_tum.txt      the same poses in the LiDAR frame, TUM format (timestamps)
    round_<r>/odometry_kitti.txt odometry-only poses (before loop closure), camera frame
    round_<r>/marginals.npz      see :data:`MARGINALS_KEYS`
    round_<r>/loops.json         every verified loop candidate (accepted or not) with figures
    round_<r>/memory/            the memory of the round (format: :mod:`gr_graph.memory`)
    round_<r>/training/          rounds r >= 1: the trainer's model.pt, checkpoint.pt, log, summary
    round_<r>/round.json         written last: the round's summary; marks the round finished

Every file is written atomically (temporary sibling, then rename).

``metrics.json`` = ``{"source", "n_frames", "channels", "rounds": {"<r>": summary}}``; a
round's summary (also its ``round.json``) holds counts (frames, odometry edges, flagged
edges, loops, loop candidates), ``slam`` and ``odometry`` (``gr_graph.metrics.
trajectory_metrics`` of the optimised and the odometry-only poses against the ground truth,
both in the camera frame: RPE over 300 frames mean/RMSE for consecutive and all pairs,
ATE, KITTI devkit %), ``loop_closure`` (precision/recall against ground truth, see
:func:`gr_graph.loop_closure.loop_precision_recall`), ``runtime_s`` per stage (``read`` is
time spent waiting for frames), ``frames_per_second`` and ``config_fingerprint``.

Memory edges: odometry edges are (k+1, k) (source P = S_{k+1}, target Q = S_k), loop edges
(i, j) with i the newer scan; T̂ comes from the optimised trajectory, ``edge_H`` is the
registration Hessian, correspondences are nearest stored target points within
``odometry.corr_max_distance`` under T̂; ``info.flagged_edges`` lists failed registrations.
In rounds r ≥ 1 the memory stores round 0's raw downsampled scans (not the densified ones:
Algorithm 2 returns M+ = (S_k, T̂+, C+)) with T̂ and correspondences from round r's trajectory.

Edge noise in rounds r ≥ 1 (``training.edge_noise``): ``"learned"`` (default) gives each ok
odometry edge the pose-likelihood Hessian H(C) of the network's covariances of the two
preprocessed scans (:class:`LearnedEdgeNoise`, reusing the covariances densification
predicted), floored by ``graph.min_information_eigenvalue``; fallbacks to the registration
information (failed registration, missing covariances, too few correspondences, non-finite
or degenerate H(C)) are logged and counted in the summary's ``edge_noise``. Loop edges and
round 0 keep the registration information.

Resume: a rerun with the same ``--out`` skips every round whose ``round.json`` exists and
whose ``config_fingerprint`` (:func:`round_fingerprint`: a hash of the options the round
depends on) equals the current one;
a round with a missing or different ``round.json`` is recomputed, with everything after
it. ``output.resume: false`` recomputes all rounds.
"""

from __future__ import annotations

import json
import logging
import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from gr_graph.atomic import atomic_save_npz, atomic_write_json
from gr_graph.config import SlamConfig, dump_config, loop_max_rmse
from gr_graph.datasets.base import LidarSequence, velo_to_cam_poses
from gr_graph.loop_closure import (
    ScanContextDatabase,
    loop_precision_recall,
    proximity_candidate,
    verify_loop,
)
from gr_graph.memory import EDGE_LOOP, EDGE_ODOMETRY, Memory
from gr_graph.odometry import LEARNED_FALLBACK_REASONS, RegistrationEdge, VgicpOdometry, learned_information
from gr_graph.pose_graph import PoseGraph, position_covariance_world
from gr_graph.preprocess import preprocess_scan, rebuild_scan

log = logging.getLogger(__name__)

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
}


class LearningRoundsUnavailable(NotImplementedError):
    """Rounds ≥ 1 were asked for but the trainer (or densification) is not importable."""


class StageTimer:
    """Accumulates wall time per named stage."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, name: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - t0


# ----------------------------------------------------------------------------- one SLAM run


def prefetch_frames(sequence: LidarSequence, ahead: int = 4):
    """Yield ``sequence[0..K-1]`` in order while a worker thread reads (renders) the next ones.

    Reading/rendering (file I/O, open3d ray casting, numpy) releases the GIL, so it overlaps
    with registration. ``ahead=0`` reads in the calling thread. Errors surface in order.
    """
    K = len(sequence)
    if ahead <= 0:
        for i in range(K):
            yield sequence[i]
        return
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="gr_graph-read") as pool:
        queue: deque = deque(pool.submit(sequence.__getitem__, i) for i in range(min(ahead, K)))
        nxt = len(queue)
        while queue:
            fut = queue.popleft()
            if nxt < K:
                queue.append(pool.submit(sequence.__getitem__, nxt))
                nxt += 1
            yield fut.result()


@dataclass
class SlamResult:
    """Everything one SLAM run (one round) produced."""

    frame_index: np.ndarray
    timestamps: np.ndarray
    poses: np.ndarray
    odometry_poses: np.ndarray
    covariances: np.ndarray | None
    scans: list[np.ndarray]
    edges: list[RegistrationEdge]
    loop_attempts: list[dict]
    checked: np.ndarray
    runtime: dict[str, float]
    graph_error: tuple[float, float] = (float("nan"), float("nan"))
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def loops(self) -> list[RegistrationEdge]:
        return [e for e in self.edges if e.kind == "loop"]


class LearnedEdgeNoise:
    """Odometry-edge information from the network's covariances (``training.edge_noise: learned``).

    ``predictions(frame_index)`` returns ``(points, C)`` the network predicted for a frame
    (:meth:`gr_graph.densify.DensifiedSequence.predicted`) or None. :meth:`apply` replaces an
    ok odometry edge's ``information`` by ``scale * H(C)`` (floored,
    :func:`gr_graph.odometry.learned_information`) and keeps the registration information
    otherwise, logging the reason. :meth:`summary` counts edges with H(C), floored ones and
    fallbacks per reason.
    """

    def __init__(self, predictions: Any, cfg: SlamConfig) -> None:
        self.predictions = predictions
        self.cfg = cfg
        self.n_learned = 0
        self.n_floored = 0
        self.fallbacks: dict[str, int] = defaultdict(int)
        self.hessians: dict[tuple[int, int], np.ndarray] = {}  # (source, target) -> raw H(C), for inspection
        self._trees: dict[int, Any] = {}

    def _tree(self, frame: int, points: np.ndarray) -> Any:
        from scipy.spatial import cKDTree

        if frame not in self._trees:
            if len(self._trees) > 4:
                self._trees.pop(next(iter(self._trees)))
            self._trees[frame] = cKDTree(points)
        return self._trees[frame]

    def apply(self, edge: RegistrationEdge, source_frame: int, target_frame: int) -> RegistrationEdge:
        """Set ``edge.information`` to the learned information when possible; return the edge."""
        tc = self.cfg.training
        reason, detail, res = "", "", None
        if not edge.ok:
            reason = "registration_failed"
        else:
            ps, pt = self.predictions(source_frame), self.predictions(target_frame)
            if ps is None or pt is None:
                reason = "no_covariances"
            else:
                res = learned_information(
                    edge.T, ps[0], pt[0], pt[1], max_distance=self.cfg.odometry.corr_max_distance,
                    min_correspondences=tc.learned_noise_min_correspondences,
                    min_eigenvalue=self.cfg.graph.min_information_eigenvalue, scale=tc.learned_noise_scale,
                    degeneracy_rel=tc.learned_noise_degeneracy_rel, target_tree=self._tree(target_frame, pt[0]),
                )
                reason, detail = res.reason, res.detail
                if res.hessian is not None:
                    self.hessians[(edge.source, edge.target)] = res.hessian
        if reason:
            self.fallbacks[reason] += 1
            log.warning("edge (%d, %d): no learned information H(C), %s%s; registration information kept",
                        edge.source, edge.target, LEARNED_FALLBACK_REASONS[reason], f" ({detail})" if detail else "")
            edge.info["edge_noise"] = f"registration ({reason})"
            return edge
        assert res is not None and res.information is not None
        self.n_learned += 1
        self.n_floored += int(res.floored)
        edge.information = res.information
        edge.info["edge_noise"] = "learned"
        edge.info["learned_noise_correspondences"] = res.n_correspondences
        return edge

    def summary(self) -> dict[str, Any]:
        return {"mode": "learned", "n_learned": self.n_learned, "n_floored": self.n_floored,
                "n_fallback": int(sum(self.fallbacks.values())), "fallbacks": dict(self.fallbacks)}


def run_slam(sequence: LidarSequence, cfg: SlamConfig, desc: str = "",
             edge_noise: LearnedEdgeNoise | None = None) -> SlamResult:
    """F_SLAM: odometry, loop closures, pose graph and marginals over ``sequence``.

    Frames are read (rendered) one at a time; only the downsampled scans are kept.
    ``edge_noise`` (learning rounds, ``training.edge_noise: learned``) replaces each odometry
    edge's information by the learned H(C) before it enters the graph.
    """
    timer = StageTimer()
    pc, oc, lc, gc = cfg.preprocess, cfg.odometry, cfg.loops, cfg.graph
    lc = lc.model_copy(update={"max_rmse": loop_max_rmse(lc, cfg.data.channels)})
    odo = VgicpOdometry(oc, gc)
    graph = PoseGraph(gc)
    scdb = ScanContextDatabase(lc)
    scans: list[np.ndarray] = []
    frame_index: list[int] = []
    edges: list[RegistrationEdge] = []
    attempts: list[dict] = []
    K = len(sequence)
    checked = np.zeros(K, dtype=bool)
    opt_poses = np.zeros((0, 4, 4))  # poses of the last optimisation (prefix of the run)
    pending_loops = 0
    last_opt = 0
    cooldown = 0
    n_flagged = 0
    n_dropped = 0

    def estimate(upto: int) -> np.ndarray:
        """Loop-corrected estimate of poses 0..upto-1."""
        odom = np.asarray(odo.poses[:upto])
        n = len(opt_poses)
        if n == 0:
            return odom
        if n >= upto:
            return opt_poses[:upto]
        corr = opt_poses[n - 1] @ np.linalg.inv(odom[n - 1])
        return np.concatenate([opt_poses, corr[None] @ odom[n:]])

    def estimate_one(i: int) -> np.ndarray:
        """Loop-corrected estimate of pose i."""
        n = len(opt_poses)
        if n == 0:
            return odo.poses[i]
        if i < n:
            return opt_poses[i]
        return opt_poses[n - 1] @ np.linalg.inv(odo.poses[n - 1]) @ odo.poses[i]

    frames = prefetch_frames(sequence, cfg.data.prefetch)
    bar = tqdm(range(K), desc=f"slam{desc}", unit="frame", disable=not cfg.output.progress, mininterval=1.0)
    for i in bar:
        with timer("read"):  # time spent waiting for the reader thread
            frame = next(frames)
        with timer("preprocess"):
            scan = preprocess_scan(frame.points, pc, index=int(frame.index), num_threads=oc.num_threads)
        n_dropped += scan.n_dropped
        with timer("odometry"):
            edge = odo.step(scan)
        scans.append(scan.points.astype(np.float32))
        frame_index.append(int(frame.index))
        graph.add_pose(estimate_one(i))
        if edge is not None:
            if edge_noise is not None:
                with timer("edge_noise"):
                    edge_noise.apply(edge, frame_index[edge.source], frame_index[edge.target])
            edges.append(edge)
            n_flagged += int(not edge.ok)
            graph.add_edge(edge.source, edge.target, edge.T, edge.information, loop=False)
        if not lc.enabled:
            continue
        with timer("loops"):
            if lc.use_scan_context:
                scdb.add(scan.points)
            if i % lc.check_every or i < lc.min_frame_gap or not scan.usable:
                continue
            if cooldown > 0:
                cooldown -= 1
                continue
            checked[i] = True
            est = estimate(i + 1)
            cands = []
            c = proximity_candidate(est, i, lc) if lc.use_proximity else None
            if c is not None:
                cands.append(c)
            if lc.use_scan_context:
                c = scdb.query(i)
                if c is not None and not any(abs(c.match - o.match) < 5 for o in cands):
                    cands.append(c)
            for cand in cands:
                target = rebuild_scan(scans[cand.match], pc, index=frame_index[cand.match], num_threads=oc.num_threads)
                le = verify_loop(scan, target, cand, lc, gc, num_threads=oc.num_threads)
                attempts.append(
                    {"query": i, "match": cand.match, "frame_query": frame_index[i],
                     "frame_match": frame_index[cand.match], "accepted": le.ok, "reason": le.reason,
                     "T": le.T, **le.info}
                )
                if le.ok:
                    edges.append(le)
                    graph.add_edge(le.source, le.target, le.T, le.information, loop=True)
                    pending_loops += 1
                    cooldown = lc.cooldown
                    log.debug("loop (%d, %d) accepted via %s", i, cand.match, cand.source)
                    break
            if pending_loops and i - last_opt >= lc.reoptimize_every:
                with timer("graph"):
                    graph.set_estimate(est)
                    opt_poses = graph.optimize(marginals=False).poses
                pending_loops, last_opt = 0, i
        bar.set_postfix(loops=sum(e.kind == "loop" for e in edges), flagged=n_flagged, refresh=False)
    bar.close()
    if n_flagged:
        log.warning("%d of %d odometry edges failed and were replaced by the constant-velocity guess",
                    n_flagged, max(K - 1, 0))
    odom_poses = np.asarray(odo.poses)
    with timer("graph"):
        graph.set_estimate(estimate(K))
        res = graph.optimize(marginals=False)
    covs = None
    if gc.marginals:
        with timer("marginals"):
            covs = graph.marginal_covariances()
    log.info("pose graph: error %.4g -> %.4g in %d iterations; %d loops", res.initial_error, res.final_error,
             res.iterations, sum(e.kind == "loop" for e in edges))
    return SlamResult(
        frame_index=np.asarray(frame_index, dtype=np.int64),
        timestamps=np.asarray(sequence.timestamps, dtype=np.float64)[:K],
        poses=res.poses,
        odometry_poses=odom_poses,
        covariances=covs,
        scans=scans,
        edges=edges,
        loop_attempts=attempts,
        checked=checked,
        runtime=dict(timer.seconds),
        graph_error=(res.initial_error, res.final_error),
        info={"n_flagged_odometry": n_flagged, "n_dropped_nonfinite": n_dropped},
    )


# ----------------------------------------------------------------------------- memory


def edge_correspondences(
    source: np.ndarray, target_tree: Any, T_st: np.ndarray, max_distance: float, num_threads: int = 1
) -> np.ndarray:
    """Index pairs (i, j): source point i and its nearest target point j within ``max_distance``.

    ``T_st`` maps source points into the target frame; ``target_tree`` is a small_gicp KdTree
    over the target's stored points.
    """
    if len(source) == 0 or target_tree is None:
        return np.zeros((0, 2), np.int32)
    p = np.asarray(source, np.float64) @ T_st[:3, :3].T + T_st[:3, 3]
    idx, d2 = target_tree.batch_nearest_neighbor_search(p, num_threads=num_threads)
    idx = np.asarray(idx, np.int64)
    ok = (idx >= 0) & (np.asarray(d2) <= max_distance**2)
    i = np.flatnonzero(ok)
    return np.column_stack([i, idx[ok]]).astype(np.int32)


def build_memory(result: SlamResult, cfg: SlamConfig, info: dict[str, Any] | None = None) -> Memory:
    """The memory of a SLAM run: stored scans, optimised poses, edges with T̂_kl from the
    optimised trajectory, registration information and correspondences under that T̂_kl."""
    import small_gicp

    poses = result.poses
    by_target: dict[int, list[int]] = defaultdict(list)
    for e, edge in enumerate(result.edges):
        by_target[edge.target].append(e)
    E = len(result.edges)
    Ts: list[np.ndarray] = [np.eye(4)] * E
    corr: list[np.ndarray] = [np.zeros((0, 2), np.int32)] * E
    for l in tqdm(sorted(by_target), desc="memory", unit="scan", disable=not cfg.output.progress, mininterval=1.0):
        pts = np.asarray(result.scans[l], np.float64)
        tree = small_gicp.KdTree(pts, num_threads=cfg.odometry.num_threads) if len(pts) else None
        for e in by_target[l]:
            edge = result.edges[e]
            T = np.linalg.inv(poses[edge.target]) @ poses[edge.source]
            Ts[e] = T
            corr[e] = edge_correspondences(result.scans[edge.source], tree, T, cfg.odometry.corr_max_distance,
                                           cfg.odometry.num_threads)
    H = [edge.H_raw if edge.ok else edge.information for edge in result.edges]
    return Memory.from_scans(
        scans=result.scans,
        poses=poses,
        edges=[(e.source, e.target) for e in result.edges],
        edge_kind=[EDGE_LOOP if e.kind == "loop" else EDGE_ODOMETRY for e in result.edges],
        edge_T=Ts,
        edge_H=H,
        corr=corr,
        info={"frame_index": result.frame_index.tolist(),
              "flagged_edges": [e for e, edge in enumerate(result.edges) if not edge.ok],
              **(info or {})},
    )


# ----------------------------------------------------------------------------- the pipeline


def _accepts(fn: Any, name: str) -> bool:
    """Whether ``fn`` takes a keyword argument ``name``."""
    import inspect

    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return name in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def round_fingerprint(cfg: SlamConfig, r: int) -> str:
    """Hash of the options round ``r``'s result depends on.

    Round 0 does not depend on the ``training`` section or the device; no round depends on
    the number of rounds or the convergence threshold (so ``--rounds 2`` after ``--rounds 1``
    reuses both finished rounds), nor on output options.
    """
    import hashlib

    if r == 0:
        d = cfg.model_dump(mode="json", exclude={"output": True, "data": {"prefetch"}, "training": True,
                                                 "device": True})
    else:
        d = cfg.model_dump(mode="json", exclude={"output": True, "data": {"prefetch"},
                                                 "training": {"rounds", "convergence_delta"}})
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]



class SlamPipeline:
    """``python -m gr_graph.slam`` as an object: ``SlamPipeline(cfg).run()``.

    Parameters
    ----------
    cfg : SlamConfig
    sequence : LidarSequence, optional
        Use this sequence instead of opening ``cfg.data`` (tests, notebooks).
    source_description : str, optional
        One line saying where the data come from (logged and stored in metrics.json).

    See the module docstring for the outputs and the resume rule.
    """

    def __init__(self, cfg: SlamConfig, sequence: LidarSequence | None = None,
                 source_description: str | None = None) -> None:
        self.cfg = cfg
        self.out = Path(cfg.output.out_dir)
        if sequence is None:
            from gr_graph.datasets.registry import open_sequence

            sequence, source_description = open_sequence(
                seq=cfg.data.seq, data_root=cfg.data.data_root, channels=cfg.data.channels,
                frames=cfg.data.frames, synthetic_seed=cfg.seed,
                route_seed=cfg.data.route_seed, trajectory=cfg.data.trajectory,
                synthetic_preset=cfg.data.synthetic_preset,
            )
        self.sequence = sequence
        self.source_description = source_description or getattr(sequence, "name", "sequence")
        self.gt = self._anchored_gt()

    # -------------------------------------------------------------- helpers
    def _anchored_gt(self) -> np.ndarray | None:
        gt = getattr(self.sequence, "gt_poses", None)
        if gt is None:
            return None
        gt = np.asarray(gt, np.float64)[: len(self.sequence)]
        return np.linalg.inv(gt[0]) @ gt

    def round_dir(self, r: int) -> Path:
        return self.out / f"round_{r}"

    def _finished(self, r: int) -> dict | None:
        p = self.round_dir(r) / "round.json"
        if not (self.cfg.output.resume and p.is_file()):
            return None
        try:
            summary = json.loads(p.read_text())
        except json.JSONDecodeError:
            return None
        if summary.get("config_fingerprint") != round_fingerprint(self.cfg, r):
            log.info("round %d: existing results were made with another configuration; recomputing", r)
            return None
        return summary

    def _check_learning_available(self) -> None:
        """Fail fast (before round 0) when a learning round could not run."""
        missing = []
        try:
            from training.train import train_from_memory  # noqa: F401
        except ImportError as exc:
            missing.append(f"the trainer training.train.train_from_memory ({exc})")
        try:
            from gr_graph.densify import densified_sequence  # type: ignore[import-not-found]  # noqa: F401
        except ImportError as exc:
            missing.append(f"densification gr_graph.densify.densified_sequence ({exc})")
        if missing:
            raise LearningRoundsUnavailable(
                "learning rounds need " + " and ".join(missing) + ", which arrive with their own issues; "
                "run with --rounds 0"
            )
        if not self.cfg.output.write_memory:
            raise ValueError("learning rounds train on the memory of the previous round: output.write_memory must be true")
        from training.trainer import TrainConfig

        # unknown keys in training.trainer fail here, before round 0, not after it
        TrainConfig.from_dict(self.cfg.training.trainer_config(self.cfg.device, False), strict=True)

    # -------------------------------------------------------------- run
    def run(self) -> dict[str, Any]:
        """Run round 0 and the learning rounds; write every output; return the metrics dict."""
        cfg = self.cfg
        rounds = cfg.training.rounds
        if rounds > 0:
            self._check_learning_available()
        self.out.mkdir(parents=True, exist_ok=True)
        dump_config(cfg, self.out / "config.yaml")
        # One line on where the data comes from; a fallback to synthetic data is a warning.
        is_synthetic = "synthetic" in self.source_description
        log.log(logging.WARNING if is_synthetic else logging.INFO, "data: %s", self.source_description)
        if self.gt is not None:
            from gr_graph.trajectory import write_kitti_poses

            write_kitti_poses(self.out / "gt_poses_kitti.txt", velo_to_cam_poses(self.gt, self.sequence.T_cam_velo))
        metrics: dict[str, Any] = {"source": self.source_description, "n_frames": len(self.sequence),
                                   "channels": cfg.data.channels, "rounds": {}}
        prev_poses = None
        recompute = False
        for r in range(rounds + 1):
            summary = None if recompute else self._finished(r)
            if summary is not None:
                log.info("round %d: already finished in %s; skipped (resume)", r, self.round_dir(r))
            else:
                prev_recomputed, recompute = recompute, True
                if r == 0:
                    summary = self.slam_round(0, self.sequence)
                else:
                    t0 = time.perf_counter()
                    seq = self._learning_round_sequence(r, resume_training=cfg.output.resume and not prev_recomputed)
                    summary = self.slam_round(r, seq, train_seconds=time.perf_counter() - t0)
            metrics["rounds"][str(r)] = summary
            atomic_write_json(self.out / "metrics.json", metrics)
            poses = self._read_round_poses(r)
            if prev_poses is not None:
                change = float(np.mean(np.linalg.norm(poses[:, :3, 3] - prev_poses[:, :3, 3], axis=1)))
                summary["trajectory_change"] = change
                if change < cfg.training.convergence_delta:
                    log.info("round %d: trajectory moved %.4f m < delta: converged", r, change)
                    break
            prev_poses = poses
        atomic_write_json(self.out / "metrics.json", metrics)
        if cfg.output.plot:
            last = max(int(k) for k in metrics["rounds"])
            self._plot(last)
        return metrics

    def _read_round_poses(self, r: int) -> np.ndarray:
        with np.load(self.round_dir(r) / "marginals.npz") as z:
            return np.array(z["poses"])

    def _learning_round_sequence(self, r: int, resume_training: bool = True) -> LidarSequence:
        """Algorithm 3, one iteration, up to the SLAM call: train f_θ on the memory of round
        r−1 (Algorithm 1), then densify every scan with it (Algorithm 2, lines 3-9).

        Training goes to ``round_<r>/training`` (``model.pt``, ``checkpoint.pt``, log); rounds
        r ≥ 2 start from round r−1's ``model.pt`` (``training.warm_start``). An existing
        checkpoint is resumed only if round r−1 was not recomputed in this run
        (``resume_training``); otherwise training restarts (the memory changed).
        """
        self._check_learning_available()
        from gr_graph.densify import densified_sequence
        from training.train import train_from_memory

        tc = self.cfg.training
        rd = self.round_dir(r)
        init = None
        if r >= 2 and tc.warm_start:
            init = self.round_dir(r - 1) / "training" / "model.pt"
            if not init.is_file():
                raise FileNotFoundError(f"round {r}: warm start needs {init} (round {r - 1}'s model)")
        train_cfg = tc.trainer_config(self.cfg.device, self.cfg.output.progress, init)
        # stand-ins with the bare contract (memory_dir, out_dir, config) / (sequence, ckpt, config, device) still work
        train_kw = {"resume": resume_training} if _accepts(train_from_memory, "resume") else {}
        try:
            ckpt = train_from_memory(self.round_dir(r - 1) / "memory", rd / "training", train_cfg, **train_kw)
        except RuntimeError as exc:  # training.trainer.TrainingError: a checkpoint of another configuration
            if not (train_kw.get("resume") and "different configuration" in str(exc)):
                raise
            log.warning("round %d: %s; training restarts from scratch", r, exc)
            ckpt = train_from_memory(self.round_dir(r - 1) / "memory", rd / "training", train_cfg, resume=False)
        dens_kw = {"preprocess": self.cfg.preprocess} if _accepts(densified_sequence, "preprocess") else {}
        return densified_sequence(self.sequence, ckpt, tc, device=self.cfg.device, **dens_kw)

    def slam_round(self, r: int, sequence: LidarSequence, train_seconds: float | None = None) -> dict[str, Any]:
        """Run F_SLAM on ``sequence`` and write round ``r``'s outputs; return its summary.

        Rounds r ≥ 1 (``sequence`` densified): SLAM preprocesses with
        ``training.slam_voxel_size`` if set, and the memory stores the raw downsampled scans of
        round 0 (Algorithm 2 returns M+ = (S_k, T̂+, C+): the original scans, so that the next
        training sees the same input as densification), with T̂ and correspondences recomputed
        from this round's trajectory. The summary gets ``densify`` (fallback counts, points)
        and ``runtime_s.training``.
        """
        from gr_graph.trajectory import write_kitti_poses, write_tum_poses

        cfg = self.cfg
        rd = self.round_dir(r)
        rd.mkdir(parents=True, exist_ok=True)
        (rd / "round.json").unlink(missing_ok=True)
        t0 = time.perf_counter()
        slam_cfg = cfg
        if r > 0 and cfg.training.slam_voxel_size is not None:
            slam_cfg = cfg.model_copy(update={"preprocess": cfg.preprocess.model_copy(
                update={"voxel_size": cfg.training.slam_voxel_size})})
        edge_noise = None
        if r > 0 and cfg.training.edge_noise == "learned":
            if hasattr(sequence, "predicted"):
                sequence.keep_predictions = max(getattr(sequence, "keep_predictions", 0), cfg.data.prefetch + 8)
                edge_noise = LearnedEdgeNoise(sequence.predicted, cfg)
            else:
                log.warning("round %d: training.edge_noise is 'learned' but the sequence has no predicted "
                            "covariances; every odometry edge keeps its registration information", r)
        res = run_slam(sequence, slam_cfg, desc=f" round {r}", edge_noise=edge_noise)
        mean_points = float(np.mean([len(s) for s in res.scans])) if res.scans else 0.0
        if r > 0 and cfg.output.write_memory:
            from gr_graph.memory import load_memory

            raw = load_memory(self.round_dir(0) / "memory")
            if raw.n_scans != len(res.scans):
                raise RuntimeError(f"round {r}: round 0 memory has {raw.n_scans} scans, this round {len(res.scans)}")
            res.scans = [np.array(raw.scan(k)) for k in range(raw.n_scans)]
            del raw
        timer = StageTimer()
        T_cv = np.asarray(sequence.T_cam_velo, np.float64)
        with timer("output"):
            write_kitti_poses(rd / "poses_kitti.txt", velo_to_cam_poses(res.poses, T_cv))
            write_kitti_poses(rd / "odometry_kitti.txt", velo_to_cam_poses(res.odometry_poses, T_cv))
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
            }
            if res.covariances is not None:
                arrays["covariance"] = res.covariances
                arrays["position_cov_world"] = position_covariance_world(res.poses, res.covariances)
            if self.gt is not None:
                arrays["gt_poses"] = self.gt
            atomic_save_npz(rd / "marginals.npz", **arrays)
            atomic_write_json(rd / "loops.json", res.loop_attempts)
        if cfg.output.write_memory:
            with timer("memory"):
                mem = build_memory(res, cfg, info={"round": r, "channels": cfg.data.channels,
                                                   "source": self.source_description,
                                                   "edge_H": "registration Hessian (small_gicp, unscaled); "
                                                             "flagged edges (info.flagged_edges, failed "
                                                             "registrations): the fallback information"})
                mem.save(rd / "memory")
                del mem
        summary: dict[str, Any] = {
            "round": r,
            "config_fingerprint": round_fingerprint(cfg, r),
            "n_frames": len(res.poses),
            "n_odometry_edges": sum(e.kind == "odometry" for e in res.edges),
            "n_flagged_odometry_edges": res.info["n_flagged_odometry"],
            "n_loops": len(res.loops),
            "n_loop_candidates": len(res.loop_attempts),
            "graph_error": list(res.graph_error),
            "mean_points_per_scan": mean_points,
        }
        if hasattr(sequence, "stats"):
            summary["densify"] = sequence.stats()
        if r > 0:
            n_odo = summary["n_odometry_edges"]
            if edge_noise is not None:
                summary["edge_noise"] = edge_noise.summary()
            elif cfg.training.edge_noise == "learned":  # no predicted covariances at all (logged above)
                summary["edge_noise"] = {"mode": "learned", "n_learned": 0, "n_floored": 0, "n_fallback": n_odo,
                                         "fallbacks": {"no_covariances": n_odo}}
            else:
                summary["edge_noise"] = {"mode": "registration", "n_learned": 0, "n_floored": 0, "n_fallback": 0,
                                         "fallbacks": {}}
            en = summary["edge_noise"]
            log.info("round %d: %d odometry edges with learned information H(C) (%d floored), %d fallbacks %s",
                     r, en["n_learned"], en["n_floored"], en["n_fallback"], en["fallbacks"])
        if self.gt is not None:
            summary.update(self._trajectory_metrics(res, T_cv))
        runtime = {**res.runtime, **timer.seconds}
        runtime["total"] = time.perf_counter() - t0
        if train_seconds is not None:
            runtime["training"] = train_seconds  # not in "total" (the SLAM round); densification is in "read"
        summary["runtime_s"] = runtime
        summary["frames_per_second"] = len(res.poses) / max(runtime["total"], 1e-9)
        atomic_write_json(rd / "round.json", summary)
        return summary

    def _trajectory_metrics(self, res: SlamResult, T_cv: np.ndarray) -> dict[str, Any]:
        from gr_graph.metrics import trajectory_metrics

        gt_cam = velo_to_cam_poses(self.gt, T_cv)
        out: dict[str, Any] = {}
        if len(res.poses) >= 2:
            out["slam"] = trajectory_metrics(velo_to_cam_poses(res.poses, T_cv), gt_cam, delta=300)
            out["odometry"] = trajectory_metrics(velo_to_cam_poses(res.odometry_poses, T_cv), gt_cam, delta=300)
        loops = [(e.source, e.target, e.T) for e in res.loops]
        out["loop_closure"] = loop_precision_recall(loops, self.gt, res.checked, self.cfg.loops.min_frame_gap)
        return out

    def _plot(self, r: int) -> None:
        from gr_graph.plots import plot_trajectory

        with np.load(self.round_dir(r) / "marginals.npz") as z:
            poses = np.array(z["poses"])
            odom = np.array(z["odometry_poses"]) if "odometry_poses" in z.files else None
            edges, kind = np.array(z["edges"]), np.array(z["edge_kind"])
        loops = edges[kind == 1]
        name = getattr(self.sequence, "name", "sequence")
        plot_trajectory(self.out / "trajectory.png", poses, self.gt, loops=loops, odometry=odom,
                        title=f"gr_graph round {r}: {name}, {len(poses)} frames, {self.cfg.data.channels} channels")
