"""The gtsam pose graph: one Pose3 per scan, a prior on the first, odometry and loop factors.

Edges follow the memory convention: an edge (k, l) holds T̂_kl = T_w_l⁻¹ T_w_k (maps scan k
into the frame of scan l) and becomes ``BetweenFactorPose3(X(l), X(k), T̂_kl)``
(gtsam's between(a, b) = a⁻¹b). Noise models come from ``factors.noise`` (information → Gaussian;
loop factors get a robust kernel).

Marginal covariances (``gtsam.Marginals``) are 6x6 in the tangent space of each pose,
gtsam order [ω, v], right perturbation (P ∘ Exp(ξ)); the world-frame position covariance
is R Σ_vv Rᵀ.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

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
        T = gtsam.Pose3(np.asarray(T_kl, dtype=np.float64))
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
            covs = self.marginal_covariances()
        return GraphResult(poses, covs, e0, e1, it + it2)

    def marginal_covariances(self) -> np.ndarray:
        """(K, 6, 6) marginal covariances at the current estimate, gtsam order [ω, v]."""
        m = gtsam.Marginals(self.graph, self.values)
        return np.stack([m.marginalCovariance(X(i)) for i in range(self.n_poses)])

    def current_poses(self) -> np.ndarray:
        """(K, 4, 4) poses of the current estimate."""
        return np.stack([self.values.atPose3(X(i)).matrix() for i in range(self.n_poses)])


def position_covariance_world(poses: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """World-frame position covariance R Σ_vv Rᵀ of each pose, ``(K, 3, 3)``."""
    R = poses[:, :3, :3]
    return R @ covs[:, 3:, 3:] @ np.transpose(R, (0, 2, 1))
