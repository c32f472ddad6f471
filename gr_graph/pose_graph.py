"""The gtsam pose graph: one Pose3 per scan, a prior on the first, odometry and loop factors.

Edges follow the memory convention: an edge (k, l) holds T̂_kl = T_w_l⁻¹ T_w_k (maps scan k
into the frame of scan l) and becomes ``BetweenFactorPose3(X(l), X(k), T̂_kl)``
(gtsam's between(a, b) = a⁻¹b). Noise models come from ``factors.noise`` (information → Gaussian;
loop factors get a robust kernel).

Marginal covariances (``gtsam.Marginals``) are 6x6 in the tangent space of each pose,
gtsam order [ω, v], right perturbation (P ∘ Exp(ξ)); the world-frame position covariance
is R Σ_vv Rᵀ.

Graphs gtsam cannot marginalise (``IndeterminateLinearSystemException``: a part of the graph
not tied to the prior, or a system too poorly conditioned to factor) never lose a run:
:meth:`PoseGraph.marginals_with_fallback` reports the failing variable and the connected
components, then retries (1) with every unanchored component's first pose anchored like pose 0
(those poses' covariances are relative to that pose), (2) with a weak regularising prior on every
pose (:data:`REGULARISING_SIGMA`); poses whose covariances come from a retry are
listed; if every retry fails the covariances are NaN (:class:`MarginalsReport`).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from factors.noise import information_noise_model, robust_noise_model
from gr_graph.config import GraphConfig

log = logging.getLogger(__name__)


def edge_noise_model(
    information: np.ndarray, cfg: GraphConfig, loop: bool = False
) -> gtsam.noiseModel.Base:
    """Noise model of an edge from its 6x6 information (``factors.noise``); robust for loops."""
    H = np.asarray(information, dtype=np.float64)
    if H.shape != (6, 6) or not np.all(np.isfinite(H)):
        raise ValueError(f"edge information must be a finite 6x6 matrix, got shape {H.shape}")
    if loop and cfg.loop_kernel != "none":
        model, _ = robust_noise_model(
            H, kernel=cfg.loop_kernel, k=cfg.loop_kernel_k, min_eigenvalue=cfg.min_information_eigenvalue
        )
    else:
        model, _ = information_noise_model(H, min_eigenvalue=cfg.min_information_eigenvalue)
    return model


@dataclass
class GraphResult:
    """Optimised poses and (optionally) marginal covariances.

    Attributes
    ----------
    poses : (K, 4, 4) array
        Optimised T_w_k.
    covariances : (K, 6, 6) array or None
        Marginal covariance of every pose, gtsam order [ω, v], body frame.
    initial_error, final_error : float
        Graph error before and after optimisation.
    iterations : int
    """

    poses: np.ndarray
    covariances: np.ndarray | None
    initial_error: float
    final_error: float
    iterations: int


@dataclass
class MarginalsReport:
    """How the marginal covariances of a graph were obtained (``round.json["marginals"]``).

    Attributes
    ----------
    status : str
        ``"ok"`` (plain ``gtsam.Marginals``), ``"anchored"`` (after anchoring unanchored
        components), ``"regularised"`` (after a weak prior on every pose) or ``"failed"``
        (covariances are NaN).
    error : str or None
        The first line of gtsam's message naming the variable it failed near.
    failed_near_pose : int or None
        Pose index of that variable.
    n_components : int
        Connected components of the graph's variables (1 for a connected graph).
    unanchored_components : list of [int, int, int]
        ``[first pose, last pose, number of poses]`` of every component without the prior.
    fallback_poses : int
        Poses whose covariances come from a retry (0 when ``status == "ok"``).
    regularising_sigma : float or None
        Sigma of the regularising prior when it was used.
    """

    status: str = "ok"
    error: str | None = None
    failed_near_pose: int | None = None
    n_components: int = 1
    unanchored_components: list[list[int]] = field(default_factory=list)
    fallback_poses: int = 0
    regularising_sigma: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: Sigma [rad, m] of the weak prior put on every pose by the last retry of
#: :meth:`PoseGraph.marginals_with_fallback`: information 1e-4, far below any edge's (the
#: information floor is ``graph.min_information_eigenvalue``, 1e-2 by default).
REGULARISING_SIGMA = 100.0

_NEAR_SYMBOL = re.compile(r"Symbol:\s*x(\d+)")


def _indeterminate(exc: RuntimeError) -> bool:
    return "ndetermina" in str(exc)


class PoseGraph:
    """Builds and optimises the pose graph.

    Parameters
    ----------
    cfg : GraphConfig
    """

    def __init__(self, cfg: GraphConfig) -> None:
        self.cfg = cfg
        self.graph = gtsam.NonlinearFactorGraph()  # the final graph (loops robust)
        self.values = gtsam.Values()
        self.n_poses = 0
        self._gaussian = gtsam.NonlinearFactorGraph()  # same factors, loops without kernel
        self.n_loops = 0

    def add_pose(self, T: np.ndarray) -> int:
        """Add the initial estimate of the next pose; the first one gets the prior."""
        i = self.n_poses
        self.values.insert(X(i), gtsam.Pose3(np.asarray(T, dtype=np.float64)))
        if i == 0:
            noise = gtsam.noiseModel.Isotropic.Sigma(6, self.cfg.prior_sigma)
            f = gtsam.PriorFactorPose3(X(0), gtsam.Pose3(np.asarray(T, dtype=np.float64)), noise)
            self.graph.add(f)
            self._gaussian.add(f)
        self.n_poses += 1
        return i

    def add_edge(self, k: int, l: int, T_kl: np.ndarray, information: np.ndarray, loop: bool = False) -> None:
        """Add ``BetweenFactorPose3(X(l), X(k), T̂_kl)`` with the given information (robust if loop)."""
        if not (0 <= k < self.n_poses and 0 <= l < self.n_poses):
            raise IndexError(f"edge ({k}, {l}) references a pose outside 0..{self.n_poses - 1}")
        T_kl = np.asarray(T_kl, dtype=np.float64)
        if T_kl.shape != (4, 4) or not np.all(np.isfinite(T_kl)):
            raise ValueError(f"edge ({k}, {l}): the measured transform must be a finite 4x4 matrix "
                             f"(shape {T_kl.shape}, {int(np.size(T_kl) - np.isfinite(T_kl).sum())} non-finite entries)")
        T = gtsam.Pose3(T_kl)
        model = edge_noise_model(information, self.cfg, loop)
        self.graph.add(gtsam.BetweenFactorPose3(X(l), X(k), T, model))
        if loop:
            self.n_loops += 1
            model = edge_noise_model(information, self.cfg, loop=False)
        self._gaussian.add(gtsam.BetweenFactorPose3(X(l), X(k), T, model))

    def set_estimate(self, poses: np.ndarray) -> None:
        """Replace the initial estimate of every pose."""
        for i, T in enumerate(np.asarray(poses)):
            self.values.update(X(i), gtsam.Pose3(T))

    def _lm(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> tuple[gtsam.Values, int]:
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.cfg.max_iterations)
        params.setRelativeErrorTol(self.cfg.relative_error_tol)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        return result, int(opt.iterations())

    def optimize(self, marginals: bool | None = None) -> GraphResult:
        """Levenberg-Marquardt from the current estimate; marginals if asked (default: config).

        With loops and a robust kernel, two stages: first with Gaussian loop factors (a
        robust kernel would ignore loops whose initial error is large, e.g. after drift or
        a failed odometry edge), then from that solution with the robust loop factors.
        """
        e0 = float(self.graph.error(self.values))
        values, it = self.values, 0
        if self.n_loops and self.cfg.loop_kernel != "none":
            values, it = self._lm(self._gaussian, values)
        result, it2 = self._lm(self.graph, values)
        e1 = float(self.graph.error(result))
        poses = np.stack([result.atPose3(X(i)).matrix() for i in range(self.n_poses)])
        self.values = result
        covs = None
        want = self.cfg.marginals if marginals is None else marginals
        if want:
            covs, _ = self.marginals_with_fallback()
        return GraphResult(poses, covs, e0, e1, it + it2)

    def marginal_covariances(self) -> np.ndarray:
        """(K, 6, 6) marginal covariances at the current estimate, gtsam order [ω, v].

        Raises gtsam's ``RuntimeError`` on an indeterminate graph; see
        :meth:`marginals_with_fallback`.
        """
        return self._marginals(self.graph)

    def _marginals(self, graph: gtsam.NonlinearFactorGraph) -> np.ndarray:
        m = gtsam.Marginals(graph, self.values)
        return np.stack([m.marginalCovariance(X(i)) for i in range(self.n_poses)])

    def components(self) -> list[np.ndarray]:
        """Connected components of the poses (through the graph's factors), each sorted, the
        component of pose 0 first."""
        parent = np.arange(self.n_poses)

        def find(a: int) -> int:
            while parent[a] != a:
                parent[a] = parent[parent[a]]
                a = int(parent[a])
            return a

        for i in range(self.graph.size()):
            f = self.graph.at(i)
            if f is None:
                continue
            keys = [gtsam.Symbol(k).index() for k in f.keys()]
            for k in keys[1:]:
                ra, rb = find(keys[0]), find(k)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
        roots = np.array([find(i) for i in range(self.n_poses)])
        return [np.flatnonzero(roots == r) for r in np.unique(roots)]

    def marginals_with_fallback(self) -> tuple[np.ndarray, MarginalsReport]:
        """Marginal covariances that never raise on an indeterminate graph (module docstring).

        Returns
        -------
        covariances : (K, 6, 6) array
            NaN for the poses no retry could marginalise.
        report : MarginalsReport
        """
        try:
            return self._marginals(self.graph), MarginalsReport()
        except RuntimeError as exc:
            if not _indeterminate(exc):
                raise
            message = " ".join(str(exc).split())
        near = _NEAR_SYMBOL.search(message)
        comps = self.components()
        report = MarginalsReport(status="failed", error=message.split(". Thrown")[0][:300],
                                 failed_near_pose=int(near.group(1)) if near else None, n_components=len(comps),
                                 unanchored_components=[[int(c[0]), int(c[-1]), len(c)] for c in comps[1:]])
        log.warning("marginals: gtsam could not marginalise the graph (near pose %s; %d connected components, "
                    "unanchored: %s); retrying", report.failed_near_pose, len(comps), report.unanchored_components)
        prior = gtsam.noiseModel.Isotropic.Sigma(6, self.cfg.prior_sigma)
        anchored = gtsam.NonlinearFactorGraph(self.graph)
        for c in comps[1:]:
            k = int(c[0])
            anchored.add(gtsam.PriorFactorPose3(X(k), self.values.atPose3(X(k)), prior))
        retries = [("anchored", anchored, None)] if len(comps) > 1 else []
        sigma = REGULARISING_SIGMA
        regularised = gtsam.NonlinearFactorGraph(anchored)
        weak = gtsam.noiseModel.Isotropic.Sigma(6, sigma)
        for i in range(self.n_poses):
            regularised.add(gtsam.PriorFactorPose3(X(i), self.values.atPose3(X(i)), weak))
        retries.append(("regularised", regularised, sigma))
        for status, graph, used_sigma in retries:
            try:
                covs = self._marginals(graph)
            except RuntimeError as exc:
                if not _indeterminate(exc):
                    raise
                continue
            report.status, report.regularising_sigma = status, used_sigma
            report.fallback_poses = (sum(len(c) for c in comps[1:]) if status == "anchored" else self.n_poses)
            log.warning("marginals: computed %s (%d poses flagged)", status, report.fallback_poses)
            return covs, report
        log.error("marginals: every retry failed; covariances are NaN, the poses are kept")
        report.fallback_poses = self.n_poses
        return np.full((self.n_poses, 6, 6), np.nan), report

    def current_poses(self) -> np.ndarray:
        """(K, 4, 4) poses of the current estimate."""
        return np.stack([self.values.atPose3(X(i)).matrix() for i in range(self.n_poses)])


def build_pose_graph(cfg: GraphConfig, poses: np.ndarray,
                     edges: Iterable[tuple[int, int, np.ndarray, np.ndarray, bool]]) -> PoseGraph:
    """A pose graph with ``poses`` ``(K, 4, 4)`` as estimate (the prior on the first) and one factor per
    ``(k, l, T̂_kl, information, is_loop)`` of ``edges`` (:meth:`PoseGraph.add_edge`)."""
    graph = PoseGraph(cfg)
    for T in poses:
        graph.add_pose(T)
    for k, l, T, H, loop in edges:
        graph.add_edge(int(k), int(l), T, H, loop=bool(loop))
    return graph


def position_covariance_world(poses: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """World-frame position covariance R Σ_vv Rᵀ of each pose, ``(K, 3, 3)``."""
    R = poses[:, :3, :3]
    return R @ covs[:, 3:, 3:] @ np.transpose(R, (0, 2, 1))
