"""Learned edge noise: an edge's information from the network's covariances.

Learning rounds (``training.edge_noise: learned``, the default) give each ok odometry edge,
and each accepted loop edge (``training.learned_noise_edges: all``, the default), the
pose-likelihood Hessian H(C) of the network's covariances of its two preprocessed scans
instead of the registration information (:mod:`gr_graph.odometry`, :mod:`gr_graph.loop_closure`):

- :func:`learned_information` computes, for one edge, the WLS Gauss-Newton Hessian
  ``H(C) = sum_i J_i^T Lambda_i J_i`` at T̂ with ``Lambda_i = (2 C_qi)^-1`` on the
  nearest-neighbour pairs under T̂ (:func:`gr_graph.correspondences.nearest_correspondences`),
  scaled and floored by ``graph.min_information_eigenvalue``; with
  ``training.learned_noise_covariance: cluster_robust`` (opt-in) the information is instead the
  inverse of the cluster-robust ("sandwich") covariance ``H^-1 M H^-1`` of the same learned cost
  (:func:`learned_sandwich_information`): H(C)'s weights, but the spread over the six axes that
  the residuals show; ``cluster_robust_offset`` adds the squared offset of T̂ from the learned
  cost's minimum, axis by axis;
- :class:`LearnedEdgeNoise` applies it edge by edge during a SLAM run, reusing the
  covariances densification predicted (:meth:`gr_graph.densify.DensifiedSequence.prediction`;
  a loop's older scan, read long ago, is predicted again);
- after the graph is optimised, one scale for the information of every edge, odometry and
  loop alike, is estimated from the graph's residuals without ground truth
  (:mod:`gr_graph.noise_calibration`, ``training.learned_noise_calibration``) and the graph
  is solved again with it (:mod:`gr_graph.frame_loop`).

Fallbacks to the registration information (failed registration, missing covariances, too
few correspondences, non-finite or degenerate H(C); :data:`LEARNED_FALLBACK_REASONS`) are
logged and counted per edge kind (:meth:`LearnedEdgeNoise.summary`, stored in the round's
summary as ``edge_noise``). Round 0 keeps the registration information.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from factors.wls import WLSInputError, residual_information, wls_cost_gradient_hessian
from gr_graph.config import SlamConfig, TrainingConfig, option_choices
from gr_graph.correspondences import nearest_correspondences, target_tree
from gr_graph.odometry import RegistrationEdge

log = logging.getLogger(__name__)

__all__ = ["LEARNED_COVARIANCES", "LEARNED_FALLBACK_REASONS", "LearnedInformation", "learned_information",
           "learned_sandwich_information", "LearnedEdgeNoise", "registration_edge_noise_summary"]

#: what a learned edge's information is made of (``training.learned_noise_covariance``)
LEARNED_COVARIANCES = option_choices(TrainingConfig, "learned_noise_covariance")

#: why an edge did not get its learned information H(C) (counted per round, never silent)
LEARNED_FALLBACK_REASONS = {
    "registration_failed": "the registration was flagged: its fallback information is kept",
    "no_covariances": "the network gave no (finite) covariances for one of the two scans",
    "few_correspondences": "too few nearest-neighbour pairs within the distance",
    "nonfinite": "H(C) is not finite / not positive semi-definite",
    "degenerate": "H(C) is degenerate (degeneracy_report): the registration information is kept",
}


@dataclass
class LearnedInformation:
    """Result of :func:`learned_information` for one edge.

    Attributes
    ----------
    information : np.ndarray or None
        ``(6, 6)`` graph information: ``scale * H(C)`` with eigenvalues floored; None on fallback.
    hessian : np.ndarray or None
        ``(6, 6)`` raw ``H(C) = sum_i J_i^T (2 C_qi)^-1 J_i`` at T̂ (None if not computed).
    n_correspondences : int
    reason : str
        "" when ``information`` is set, else a key of :data:`LEARNED_FALLBACK_REASONS`.
    floored : bool
        Whether the eigenvalue floor raised any eigenvalue.
    detail : str
        Human-readable detail of a fallback (degenerate directions...).
    model : str
        What ``information`` was made from: ``"hessian"`` (``H(C)``), ``"cluster_robust"`` or
        ``"cluster_robust_offset"`` (the inverse sandwich covariance, without or with the offset of
        T̂) or ``"hessian_fallback"`` (the sandwich was asked for but not available: too few
        clusters, not positive definite; ``H(C)`` is used); ``""`` on fallback.
    """

    information: np.ndarray | None
    hessian: np.ndarray | None
    n_correspondences: int
    reason: str = ""
    floored: bool = False
    detail: str = ""
    model: str = ""


def learned_information(
    T: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    target_cov: np.ndarray,
    max_distance: float,
    min_correspondences: int = 50,
    min_eigenvalue: float | None = 1e-2,
    scale: float = 1.0,
    degeneracy_rel: float = 1e-4,
    tree: Any | None = None,
    num_threads: int = 1,
    covariance: str = "hessian",
    cluster_size: float = 12.0,
    min_clusters: int = 20,
) -> LearnedInformation:
    """Pose information of an edge from learned covariances: the pose-likelihood Hessian H(C).

    Correspondences: each source point ``p`` mapped by ``T`` (T̂_kl, source into target frame)
    is paired with its nearest target point ``q`` if closer than ``max_distance``. With
    ``Lambda_i = (2 C_qi)^-1`` (the paper's shared-geometry case,
    :func:`factors.wls.residual_information`), ``H(C) = sum_i J_i^T Lambda_i J_i`` is the
    Gauss-Newton Hessian of the WLS cost at ``T`` (:func:`factors.wls.wls_cost_gradient_hessian`),
    gtsam order ``[omega, v]``, right perturbation. It is scaled and floored by
    :func:`factors.noise.floored_information` (``min_eigenvalue``).

    With ``covariance="cluster_robust"`` (or ``"cluster_robust_offset"``) the information scaled and
    floored is instead the inverse of :func:`learned_sandwich_information`'s covariance on the same
    pairs (cubes of ``cluster_size``, at least ``min_clusters``; with the offset of T̂ from the learned
    minimum); where that is not available, ``H(C)`` is used and ``model`` says ``"hessian_fallback"``.

    Fallbacks (``information=None``, ``reason`` set, logged by the caller): fewer than
    ``min_correspondences`` pairs; non-finite / non-PSD ``H(C)``; degenerate ``H(C)``
    (:func:`factors.degeneracy.degeneracy_report` with ``rel_threshold=degeneracy_rel`` and
    rotations measured as arc length at 10 m).

    Parameters
    ----------
    T : (4, 4) array
        T̂_kl of the edge.
    source, target : (N, 3), (M, 3) arrays
        Points of scan k and scan l that the network predicted covariances for.
    target_cov : (M, 3, 3) array
        Predicted covariances of ``target``.
    tree : small_gicp.KdTree, optional
        :func:`gr_graph.correspondences.target_tree` of ``target`` (built if omitted).
    num_threads : int
        Threads of the nearest-neighbour search.
    covariance : {"hessian", "cluster_robust", "cluster_robust_offset"}
        ``training.learned_noise_covariance``.
    cluster_size, min_clusters : float, int
        ``graph.cluster_size`` and ``graph.min_clusters`` (the two cluster-robust forms only).
    """
    from factors.degeneracy import degeneracy_report
    from factors.noise import NoiseModelError, floored_information

    if covariance not in LEARNED_COVARIANCES:
        raise ValueError(f"learned_information: covariance must be one of {LEARNED_COVARIANCES}, got {covariance!r}")
    T = np.asarray(T, np.float64)
    src = np.asarray(source, np.float64)
    tgt = np.asarray(target, np.float64)
    cov = np.asarray(target_cov, np.float64)
    if cov.shape != (len(tgt), 3, 3):
        raise ValueError(f"learned_information: target_cov must be ({len(tgt)}, 3, 3), got {cov.shape}")
    if len(src) == 0 or len(tgt) == 0:
        return LearnedInformation(None, None, 0, "few_correspondences", detail="empty scan")
    if tree is None:
        tree = target_tree(tgt, num_threads)
    pairs = nearest_correspondences(src, tree, T, max_distance, num_threads)
    n = len(pairs)
    if n < min_correspondences:
        return LearnedInformation(None, None, n, "few_correspondences",
                                  detail=f"{n} < {min_correspondences} pairs within {max_distance} m")
    p, q = src[pairs[:, 0]], tgt[pairs[:, 1]]
    try:
        info = residual_information(cov[pairs[:, 1]])
        _, grad, H = wls_cost_gradient_hessian(T, p, q, info)
    except (WLSInputError, np.linalg.LinAlgError, FloatingPointError) as exc:
        return LearnedInformation(None, None, n, "nonfinite", detail=str(exc))
    if not np.all(np.isfinite(H)):
        return LearnedInformation(None, H, n, "nonfinite", detail="non-finite H(C)")
    rep = degeneracy_report(H, rel_threshold=degeneracy_rel, length_scale=10.0)
    if rep.is_degenerate:
        return LearnedInformation(None, H, n, "degenerate", detail=rep.describe())
    information, model = H, "hessian"
    if covariance != "hessian":
        try:
            sandwich = learned_sandwich_information(T, p, q, info, cluster_size, min_clusters,
                                                    include_offset=covariance == "cluster_robust_offset",
                                                    gradient_hessian=(grad, H))
        except (WLSInputError, np.linalg.LinAlgError, FloatingPointError, ValueError):  # e.g. a non-finite step
            sandwich = None
        information, model = (H, "hessian_fallback") if sandwich is None else (sandwich, covariance)
    try:
        out, nrep = floored_information(information, scale=scale, min_eigenvalue=min_eigenvalue)
    except NoiseModelError as exc:
        return LearnedInformation(None, H, n, "nonfinite", detail=str(exc))
    return LearnedInformation(out, H, n, "", floored=nrep.was_floored, model=model)


def learned_sandwich_information(T: np.ndarray, p: np.ndarray, q: np.ndarray, info: np.ndarray,
                                 cluster_size: float, min_clusters: int, include_offset: bool = False,
                                 gradient_hessian: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray | None:
    """Inverse cluster-robust covariance of the learned cost's pose estimate near ``T``.

    The learned cost ``1/2 sum_i d_i^T Lambda_i d_i`` (``Lambda_i = (2 C_qi)^-1``, the pairs found
    under T̂) is not at its minimum at T̂, which another cost (VGICP's) chose: the gradient terms
    are taken one Gauss-Newton step further, at ``T o Exp(-H^-1 g)`` with the same pairs, where
    their sum vanishes to first order. There, :func:`gr_graph.registration_covariance.
    cluster_robust_covariance` gives ``H^-1 M H^-1`` with ``M`` the outer products of the gradient
    sums over cubes of ``cluster_size`` (source frame). Residuals within a cube may be correlated
    arbitrarily; ``H(C)``'s shape over the six axes is replaced by what the residuals show (an
    error the whole scan shares stays invisible: measured in the README's NEES section). No ground
    truth is used.

    Parameters
    ----------
    T : (4, 4) array
        T̂ of the edge (source into target frame).
    p, q : (N, 3) arrays
        Paired source and target points.
    info : (N, 3, 3) array
        ``Lambda_i`` of each pair.
    cluster_size : float
        Side of the cubes [m].
    min_clusters : int
        Fewer cubes holding pairs: None.
    include_offset : bool
        Add ``diag(s^2)`` for the Gauss-Newton step ``s`` (``training.learned_noise_covariance:
        cluster_robust_offset``): the graph holds T̂, not the learned cost's minimum, and by the learned
        cost T̂ is off that minimum by ``s``; without it the covariance is that of the minimum. Each
        axis (roll, pitch, yaw, x, y, z of the source frame) gets its own squared offset; the
        rank-one ``s s^T`` (measured first, 2026-12-07) claimed correlations one draw cannot show
        and left the odometry edges over-confident (README).
    gradient_hessian : (grad, H), optional
        The learned cost's gradient and Hessian at ``T`` when the caller has them
        (:func:`factors.wls.wls_cost_gradient_hessian` of the same arguments); computed otherwise.

    Returns
    -------
    (6, 6) array or None
        The information (symmetric), or None when the covariance is not available (too few
        clusters, a Hessian or covariance that is not positive definite).
    """
    from factors.se3 import exp_se3
    from gr_graph.registration_covariance import sandwich_information

    grad, H = gradient_hessian if gradient_hessian is not None else wls_cost_gradient_hessian(T, p, q, info)[1:]
    try:
        step = -np.linalg.solve(H, grad)
    except np.linalg.LinAlgError:
        return None
    T_min = np.asarray(T, np.float64) @ exp_se3(step)
    _, _, H_min = wls_cost_gradient_hessian(T_min, p, q, info)
    # T̂ is off the learned cost's minimum by -step (first order, in T̂'s tangent space)
    offset = np.diag(step * step) if include_offset else None
    return sandwich_information(T_min, p, q, info, H_min, cluster_size, min_clusters, offset)[0]


#: ``predictions(frame_index)``: the points of a frame and the network's covariances of them, or None
Predictions = Callable[[int], "tuple[np.ndarray, np.ndarray] | None"]


class LearnedEdgeNoise:
    """Edge information from the network's covariances (``training.edge_noise: learned``).

    ``predictions(frame_index)`` returns ``(points, C)`` the network predicted for a frame
    (:meth:`gr_graph.densify.DensifiedSequence.prediction`) or None. :meth:`apply` replaces an
    ok edge's ``information`` by ``scale * H(C)`` (floored, :func:`learned_information`) and
    keeps the registration information otherwise, logging the reason; loop edges only with
    ``training.learned_noise_edges: all``. :meth:`summary` counts, per edge kind, edges with
    H(C), floored ones and fallbacks per reason, and holds the round's calibration
    (:attr:`calibration`, set by the frame loop).
    """

    def __init__(self, predictions: Predictions, cfg: SlamConfig) -> None:
        self.predictions = predictions
        self.cfg = cfg
        self.counts: dict[str, dict[str, Any]] = {
            kind: {"n_learned": 0, "n_floored": 0, "fallbacks": defaultdict(int), "models": defaultdict(int)}
            for kind in ("odometry", "loop")}
        self.hessians: dict[tuple[int, int], np.ndarray] = {}  # (source, target) -> raw H(C), for inspection
        self.calibration: dict[str, Any] | None = None
        #: set by a frame loop that deskews its frames: ``(frame_index, points, C) -> (points, C)`` moves a
        #: frame's predictions (made on the scan as read) as the frame was moved, to match the edges' T̂
        self.motion_correction: Callable[[int, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None

    @property
    def loops(self) -> bool:
        """Whether loop edges get H(C) too (``training.learned_noise_edges: all``)."""
        return self.cfg.training.learned_noise_edges == "all"

    @property
    def calibrate(self) -> bool:
        """Whether the frame loop scales every edge's information by the graph's variance factor."""
        return self.cfg.training.learned_noise_calibration == "graph_residuals"

    @property
    def n_learned(self) -> int:
        """Odometry edges with H(C)."""
        return int(self.counts["odometry"]["n_learned"])

    @property
    def fallbacks(self) -> dict[str, int]:
        """Odometry edges without H(C), per reason."""
        return dict(self.counts["odometry"]["fallbacks"])

    def apply(self, edge: RegistrationEdge, source_frame: int, target_frame: int) -> RegistrationEdge:
        """Set ``edge.information`` to the learned information when possible; return the edge.

        Loop edges are returned unchanged unless :attr:`loops`.
        """
        if edge.kind == "loop" and not self.loops:
            return edge
        tc = self.cfg.training
        counts = self.counts[edge.kind]
        reason, detail, res = "", "", None
        if not edge.ok:
            reason = "registration_failed"
        else:
            ps, pt = self._prediction(source_frame), self._prediction(target_frame)
            if ps is None or pt is None:
                reason = "no_covariances"
            else:
                res = learned_information(
                    edge.T, ps[0], pt[0], pt[1], max_distance=self.cfg.odometry.corr_max_distance,
                    min_correspondences=tc.learned_noise_min_correspondences,
                    min_eigenvalue=self.cfg.graph.min_information_eigenvalue, scale=tc.learned_noise_scale,
                    degeneracy_rel=tc.learned_noise_degeneracy_rel,
                    num_threads=self.cfg.odometry.num_threads, covariance=tc.learned_noise_covariance,
                    cluster_size=self.cfg.graph.cluster_size, min_clusters=self.cfg.graph.min_clusters,
                )
                reason, detail = res.reason, res.detail
                if res.hessian is not None:
                    self.hessians[(edge.source, edge.target)] = res.hessian
        if reason:
            counts["fallbacks"][reason] += 1
            log.warning("%s edge (%d, %d): no learned information H(C), %s%s; registration information kept",
                        edge.kind, edge.source, edge.target, LEARNED_FALLBACK_REASONS[reason],
                        f" ({detail})" if detail else "")
            edge.info["edge_noise"] = f"registration ({reason})"
            return edge
        assert res is not None and res.information is not None
        counts["n_learned"] += 1
        counts["n_floored"] += int(res.floored)
        counts["models"][res.model] += 1
        edge.information = res.information
        edge.info["edge_noise"] = "learned"
        edge.info["learned_noise_correspondences"] = res.n_correspondences
        return edge

    def _prediction(self, frame_index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """``predictions(frame_index)``, moved by :attr:`motion_correction` when set."""
        got = self.predictions(frame_index)
        if got is None or self.motion_correction is None:
            return got
        return self.motion_correction(frame_index, *got)

    def summary(self) -> dict[str, Any]:
        """``{"mode": "learned", "n_learned", "n_floored", "n_fallback", "fallbacks"}`` of the
        odometry edges (and ``"models"``, learned edges per :attr:`LearnedInformation.model`, with
        ``training.learned_noise_covariance: cluster_robust``), ``"loop"``: the same of the loop edges, ``"edges"``
        (``training.learned_noise_edges``) and ``"calibration"``
        (:meth:`gr_graph.noise_calibration.VarianceFactor.summary`, or ``{"method": "none"}``)."""
        def kind(k: str) -> dict[str, Any]:
            c = self.counts[k]
            out = {"n_learned": int(c["n_learned"]), "n_floored": int(c["n_floored"]),
                   "n_fallback": int(sum(c["fallbacks"].values())), "fallbacks": dict(c["fallbacks"])}
            if self.cfg.training.learned_noise_covariance != "hessian":  # what each learned edge's information is
                out["models"] = dict(sorted(c["models"].items()))
            return out

        return {"mode": "learned", **kind("odometry"), "loop": kind("loop"),
                "edges": self.cfg.training.learned_noise_edges,
                "calibration": self.calibration if self.calibration is not None else {"method": "none"}}


def registration_edge_noise_summary() -> dict[str, Any]:
    """The ``edge_noise`` summary of a learning round with ``training.edge_noise: registration``."""
    return {"mode": "registration", "n_learned": 0, "n_floored": 0, "n_fallback": 0, "fallbacks": {},
            "calibration": {"method": "none"}}
