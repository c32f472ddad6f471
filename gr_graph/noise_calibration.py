"""One scale for every edge's information, from the optimised graph's own residuals (no ground truth).

The learned information ``H(C)`` of an edge (:mod:`gr_graph.edge_noise`) is the Hessian of
a likelihood whose point residuals are treated as independent; they are not (neighbouring
points share the surface and the sensor's errors), so ``H(C)`` is right in shape but not in
size. The size is estimated here from the graph itself, the a-posteriori variance factor of a
least-squares adjustment (variance component estimation with a single group)::

    r_e     = Log(T̂_kl^-1 X_l^-1 X_k)           (gtsam's BetweenFactorPose3 error, [omega, v])
    chi2_e  = r_e^T Lambda_e r_e                 at the optimised poses X
    sigma0^2 = sum_e chi2_e / redundancy,   redundancy = 6 (E - K + 1)

(``E`` edges, ``K`` poses, a prior fixing the first: every loop adds 6 independent
observations). If every ``Lambda_e`` is right up to one common factor ``s``,
``E[sum chi2] = redundancy / s``, so the calibrated information is ``Lambda_e / sigma0^2``,
the same factor for odometry and loop edges. A chain without loops has no redundancy (every
residual is zero at the optimum): no calibration is possible, and the scale stays 1 (the
result says so).

Flagged odometry edges (``ok=False``: a failed registration replaced by the constant-velocity
guess with the weak ``graph.fallback_sigmas``) are not measurements of the kind being
calibrated: their residual (often the whole error of the failure, repaired by loops) would
dominate the sum. They are left out of the sum and of the redundancy, which becomes
``6 (E_ok - K + c)`` with ``c`` the connected components of the graph of the other edges.
Their information is scaled with the rest, so that it stays as weak relative to the others
as it was (and the least-squares optimum does not move).

Ground truth is not used; :mod:`gr_graph.noise_consistency` checks the result against it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from gr_graph.odometry import RegistrationEdge

__all__ = ["between_residuals", "VarianceFactor", "variance_factor"]


def between_residuals(poses: np.ndarray, edges: Sequence[RegistrationEdge]) -> np.ndarray:
    """``(E, 6)`` errors ``Log(T̂_kl^-1 X_l^-1 X_k)`` ([omega, v]) of the edges at ``poses`` ``(K, 4, 4)``.

    The error of ``BetweenFactorPose3(X(l), X(k), T̂_kl)`` (:mod:`gr_graph.pose_graph`).
    """
    poses = np.asarray(poses, np.float64)
    out = np.zeros((len(edges), 6))
    for i, e in enumerate(edges):
        rel = gtsam.Pose3(np.linalg.inv(poses[e.target]) @ poses[e.source])
        out[i] = gtsam.Pose3.Logmap(gtsam.Pose3(np.asarray(e.T, np.float64)).between(rel))
    return out


@dataclass
class VarianceFactor:
    """Result of :func:`variance_factor`.

    Attributes
    ----------
    sigma0_sq : float or None
        ``sum chi2 / redundancy``; None without redundancy.
    scale : float
        The factor for every edge's information: ``1 / sigma0_sq`` (1 without redundancy).
    redundancy : int
        ``6 (E - K + 1)``.
    chi2 : dict
        Sum of ``chi2_e`` per edge kind (``"odometry"``, ``"loop"``), before the scale.
    n_edges : dict
        Edges per kind (flagged ones left out).
    n_flagged : int
        Flagged odometry edges left out (their information is not scaled).
    """

    sigma0_sq: float | None
    scale: float
    redundancy: int
    chi2: dict[str, float]
    n_edges: dict[str, int]
    n_flagged: int = 0

    def summary(self) -> dict[str, Any]:
        """JSON-ready dict (stored in the round summary as ``edge_noise.calibration``)."""
        return {"method": "graph_residuals", "sigma0_sq": self.sigma0_sq, "scale": self.scale,
                "redundancy": self.redundancy, "chi2": self.chi2, "n_edges": self.n_edges,
                "n_flagged_left_out": self.n_flagged}


def variance_factor(poses: np.ndarray, edges: Sequence[RegistrationEdge]) -> VarianceFactor:
    """The a-posteriori variance factor of the graph of ``edges`` at the optimised ``poses``.

    Parameters
    ----------
    poses : (K, 4, 4) array
        Optimised poses (the graph's solution with the edges' current information).
    edges : sequence of RegistrationEdge
        Every edge of the graph (odometry and loops), with the information the graph used;
        flagged ones (``ok=False``) are left out (module docstring).
    """
    K = len(poses)
    ok = [e for e in edges if e.ok]
    r = between_residuals(poses, ok)
    chi2 = {"odometry": 0.0, "loop": 0.0}
    n = {"odometry": 0, "loop": 0}
    for e, re in zip(ok, r):
        info = np.asarray(e.information, np.float64)
        chi2[e.kind] += float(re @ (0.5 * (info + info.T)) @ re)
        n[e.kind] += 1
    redundancy = 6 * (len(ok) - K + _components(K, ok))
    total = chi2["odometry"] + chi2["loop"]
    if redundancy <= 0 or not np.isfinite(total) or total <= 0.0:
        return VarianceFactor(None, 1.0, max(redundancy, 0), chi2, n, len(edges) - len(ok))
    s2 = total / redundancy
    return VarianceFactor(s2, 1.0 / s2, redundancy, chi2, n, len(edges) - len(ok))


def _components(n_nodes: int, edges: Sequence[RegistrationEdge]) -> int:
    """Connected components of the graph of ``edges`` over ``n_nodes`` poses (union-find)."""
    parent = list(range(n_nodes))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for e in edges:
        a, b = root(e.source), root(e.target)
        if a != b:
            parent[a] = b
    return sum(root(i) == i for i in range(n_nodes))
