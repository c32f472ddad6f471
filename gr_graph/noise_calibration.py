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

A wrong loop that passed verification would inflate ``sigma0^2`` (its residual at full weight in
the Gaussian graph), weaken every edge and, through the weakened whitening, slip past the loops'
robust kernel. Loops failing a deletion F test (what each adds to the chi-square against the
variance factor of the rest: :func:`outlying_loop`, ``training.learned_noise_outlier_alpha``) are
therefore left out of the estimate one at a time, worst first, the Gaussian graph solved again
without each; they stay in the robust graph, where the kernel weighs them.

Loop edges alone (:func:`loop_variance_factor`, ``graph.loop_variance: estimated``): a second
variance component, for the loops only, with the odometry edges' information held fixed
(Förstner's variance component estimation with one group estimated)::

    r_loops    = 6 n_loops - tr(N^-1 N_loops)     redundancy of the loop rows (N = J^T J, whitened
                                                  Jacobian of the Gaussian graph at its optimum)
    sigma_L^2  = sum_{loops} chi2_e / r_loops;   Lambda_loop /= sigma_L^2;  solve again;  repeat

A registration Hessian describes the random error of an alignment, not a bias such as a
miscalibrated beam elevation that tilts every revisit of a place the same way; the loops'
residuals against the odometry show it. Estimating both groups from residuals instead fails:
the odometry edges' own residuals are small wherever loops are weak (their drift is not
observable), so their factor collapses (``benchmarks/nees_variance_components.py``).

Then per axis (:func:`loop_axis_variance_factors`, ``graph.loop_variance: estimated_axes``): the
common factor weakens every axis of a loop alike, while a 16-ring scan pair misses part of a
pitch or roll difference (``benchmarks/ring_pattern_study.py``) and is precise in the other axes.
On the loops scaled by the common factor, six more factors (one per tangent axis, shared by all
loops) are estimated from the same residuals split by axis, and only ever weaken a loop.

Ground truth is not used; :mod:`gr_graph.noise_consistency` checks the result against it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from gr_graph.odometry import RegistrationEdge

__all__ = ["between_residuals", "VarianceFactor", "variance_factor", "LoopVarianceFactor", "loop_variance_factor",
           "LoopAxisVarianceFactors", "loop_axis_variance_factors", "factor_redundancies"]


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
        Flagged odometry edges left out of the estimate (their information is scaled all the same).
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


#: memory for the dense right-hand sides of one solve in :func:`outlying_loop` [bytes]
SOLVE_CHUNK_BYTES = 2e8


def outlying_loop(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, edges: Sequence[RegistrationEdge],
                  alpha: float) -> tuple[int, float, float] | None:
    """The loop edge least consistent with the rest of the graph, if it fails a deletion F test.

    A loop's own residual in the adjusted graph says little: the odometry edges between its two
    frames absorb most of a wrong loop's error. The test statistic is instead what the loop adds
    to the graph's chi-square, ``T_i = w_i^T R_i^+ w_i`` (``w_i`` the loop's whitened residual,
    ``R_i = I - J_i N^-1 J_i^T`` its block of the redundancy matrix: exact for the linearised
    graph; ``rank R_i`` is the loop's redundancy), set against the variance factor of the rest,
    ``s2 = (sum chi2 - T_i) / (redundancy - rank R_i)``. Under the model (every edge's information
    right up to one common factor) ``(T_i / rank R_i) / s2`` is F(rank R_i, redundancy - rank R_i)
    distributed. A loop failing it at level ``alpha`` (a wrong loop that passed verification)
    would inflate :func:`variance_factor`, weaken every edge and, through the weakened whitening,
    slip past the robust kernel of the loops.

    Parameters
    ----------
    graph, values : gtsam graph and its optimum
        The Gaussian pose graph (loops without a robust kernel) of ``edges``: a prior first, then
        one factor per edge in order.
    edges : sequence of RegistrationEdge
        The graph's edges (flagged ones are left out of the sum and the redundancy, as in
        :func:`variance_factor`).
    alpha : float
        False-alarm probability of the test per loop; 0: never a loop.

    Returns
    -------
    tuple or None
        ``(index into edges, F statistic, threshold)`` of the loop with the smallest p-value when it
        is below ``alpha``; None when no loop fails, without loops, or with no redundancy left
        without it. RuntimeError (from the factorisation) for a singular normal matrix.
    """
    loops = [i for i, e in enumerate(edges) if e.ok and e.kind == "loop"]
    if alpha <= 0.0 or not loops:
        return None
    from scipy.stats import f as f_dist

    K = int(values.size())
    ok = [e for e in edges if e.ok]
    redundancy = 6 * (len(ok) - K + _components(K, ok))
    total = sum(2.0 * graph.at(1 + i).error(values) for i, e in enumerate(edges) if e.ok)
    J, lu = _whitened_jacobian(graph, values)
    # the 6x6 blocks J_i N^-1 J_i^T, a few loops at a time: the dense right-hand sides of the solve are
    # unknowns x 6 loops, ~90 MB for 69 loops over 4,541 poses; at most ~200 MB a chunk
    chunk = max(1, int(SOLVE_CHUNK_BYTES // (8 * 6 * J.shape[1])))
    blocks: list[np.ndarray] = []
    for c in range(0, len(loops), chunk):
        Jc = J[_factor_rows([1 + i for i in loops[c:c + chunk]])].toarray()
        G = Jc @ lu.solve(np.ascontiguousarray(Jc.T))
        blocks += [G[6 * k:6 * k + 6, 6 * k:6 * k + 6] for k in range(len(loops[c:c + chunk]))]
    best: tuple[float, int, float, float] | None = None
    for i, Gi in zip(loops, blocks):
        R = np.eye(6) - 0.5 * (Gi + Gi.T)
        w = np.asarray(graph.at(1 + i).whitenedError(values), np.float64)
        vals, vecs = np.linalg.eigh(R)
        keep = vals > 1e-6
        rank = int(keep.sum())
        rest = redundancy - rank
        if rank == 0 or rest <= 0:
            continue
        proj = vecs[:, keep].T @ w
        T = float(np.sum(proj**2 / vals[keep]))
        s2 = (total - T) / rest
        if not (np.isfinite(T) and s2 > 0.0):
            continue
        stat = (T / rank) / s2
        p_value = float(f_dist.sf(stat, rank, rest))
        if best is None or p_value < best[0]:
            best = (p_value, i, stat, float(f_dist.isf(alpha, rank, rest)))
    if best is None or not best[0] < alpha:
        return None
    return best[1], best[2], best[3]


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


def factor_redundancies(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                        factor_groups: Sequence[Sequence[int]]) -> list[float]:
    """Redundancy ``rows_g - tr(N^-1 J_g^T J_g)`` of each group of factors of a Gaussian ``graph``.

    ``J`` is the whitened Jacobian at ``values`` (rows of factor ``f`` are ``6 f .. 6 f + 5``:
    every factor of a pose graph is 6-dimensional), ``N = J^T J``, factorised once; ``J_g`` its
    rows of group ``g``. The redundancies of all factors add up to ``rows - unknowns``.
    """
    J, lu = _whitened_jacobian(graph, values)
    out = []
    for group in factor_groups:
        rows = _factor_rows(group)
        if len(rows) == 0:
            out.append(0.0)
            continue
        Jg = J[rows].toarray()
        out.append(float(len(rows) - np.trace(Jg @ lu.solve(np.ascontiguousarray(Jg.T)))))
    return out


def _factor_rows(factors: Sequence[int]) -> np.ndarray:
    """Rows of the factors ``factors`` in a pose graph's Jacobian (six per factor, in order)."""
    return (6 * np.asarray(factors, np.int64)[:, None] + np.arange(6)).ravel()


def _axis_scaled(information: np.ndarray, axis_scale: np.ndarray) -> np.ndarray:
    """``diag(sqrt d) Lambda diag(sqrt d)``: ``information`` with axis ``j`` scaled by ``d_j``."""
    root = np.sqrt(np.asarray(axis_scale, np.float64))
    return root[:, None] * np.asarray(information, np.float64) * root[None, :]


def _whitened_jacobian(graph: gtsam.NonlinearFactorGraph,
                       values: gtsam.Values) -> tuple[sp.csr_matrix, spl.SuperLU]:
    """The whitened Jacobian ``J`` of a pose graph at ``values`` (factor ``f``'s rows ``6 f .. 6 f + 5``)
    and the LU factorisation of ``N = J^T J`` (RuntimeError when ``N`` is singular)."""
    ijs = graph.linearize(values).sparseJacobian_()  # 1-based (row, column, value); last column: rhs
    r, c, v = ijs[0].astype(int) - 1, ijs[1].astype(int) - 1, ijs[2]
    n = int(values.size()) * 6
    keep = c < n
    J = sp.csr_matrix((v[keep], (r[keep], c[keep])), shape=(6 * int(graph.size()), n))
    return J, spl.splu((J.T @ J).tocsc())


@dataclass
class LoopVarianceFactor:
    """Result of :func:`loop_variance_factor`.

    Attributes
    ----------
    scale : float
        The factor for the loops' information (1 when nothing was estimated: ``reason`` set).
    sigma_sq : list of float
        ``sum chi2_loops / r_loops`` of every iteration (the last near 1 when it converged).
    redundancy : float or None
        ``r_loops`` at the last iteration.
    n_loops : int
    iterations : int
    converged : bool
    reason : str or None
        Why nothing was estimated (no loops, no loop redundancy, zero residuals).
    """

    scale: float
    sigma_sq: list[float]
    redundancy: float | None
    n_loops: int
    iterations: int
    converged: bool
    reason: str | None = None

    def scaled_information(self, information: np.ndarray) -> np.ndarray:
        """A loop edge's ``(6, 6)`` information with the factor applied."""
        return self.scale * np.asarray(information, np.float64)

    def summary(self) -> dict[str, Any]:
        """JSON-ready dict (the round summary's ``loop_variance``)."""
        return {"method": "loop_variance_component", "scale": self.scale, "sigma_sq": self.sigma_sq,
                "redundancy": self.redundancy, "n_loops": self.n_loops, "iterations": self.iterations,
                "converged": self.converged, "reason": self.reason}


def loop_variance_factor(solve: Callable[[list[np.ndarray]], tuple[gtsam.NonlinearFactorGraph, gtsam.Values]],
                         edges: Sequence[RegistrationEdge], max_iterations: int = 10,
                         tol: float = 1e-3) -> LoopVarianceFactor:
    """The loops' variance factor with the odometry edges' information held fixed (module docstring).

    Parameters
    ----------
    solve : callable
        ``informations -> (graph, values)``: builds the Gaussian pose graph (prior first, then one
        factor per edge of ``edges`` in order, with the given ``(6, 6)`` informations) and returns
        it with its optimum (:meth:`gr_graph.frame_loop._FrameLoop.estimate_loop_variance`).
    edges : sequence of RegistrationEdge
        Every edge of the graph, with its current information (not modified).
    max_iterations : int
        Estimate, rescale and solve again at most this often.
    tol : float
        Stop when ``|sigma_L^2 - 1| < tol``.

    Returns
    -------
    LoopVarianceFactor
        ``scale``: the factor for every loop edge's information (the product over iterations);
        1 with ``reason`` set when it cannot be estimated (no loops, no loop redundancy, zero
        residuals, a singular normal matrix). The dense ``(6 n_loops, 6 K)`` block of the
        Jacobian it forms is ~90 MB for 69 loops over 4,541 poses.
    """
    loops = [i for i, e in enumerate(edges) if e.kind == "loop"]
    if not loops:
        return LoopVarianceFactor(1.0, [], None, 0, 0, False, "no loops")
    info = [np.asarray(e.information, np.float64) for e in edges]
    is_loop = set(loops)
    scale, history, r_loop = 1.0, [], None
    for it in range(max_iterations):
        graph, values = solve([scale * h if i in is_loop else h for i, h in enumerate(info)])
        chi2 = sum(2.0 * graph.at(1 + i).error(values) for i in loops)  # factor 0 is the prior
        try:
            r_loop = factor_redundancies(graph, values, [[1 + i for i in loops]])[0]
        except RuntimeError as exc:  # splu: a singular normal matrix (a pose no factor constrains)
            return LoopVarianceFactor(1.0, history, None, len(loops), it, False, f"singular normal matrix ({exc})")
        if r_loop < 0.5 or not np.isfinite(chi2) or chi2 <= 0.0:
            reason = "no loop redundancy" if r_loop < 0.5 else "zero or non-finite loop residuals"
            return LoopVarianceFactor(1.0, history, r_loop, len(loops), it, False, reason)
        s2 = float(chi2 / r_loop)
        history.append(s2)
        scale /= s2
        if abs(s2 - 1.0) < tol:
            return LoopVarianceFactor(scale, history, r_loop, len(loops), it + 1, True)
    return LoopVarianceFactor(scale, history, r_loop, len(loops), max_iterations, False)


@dataclass
class LoopAxisVarianceFactors:
    """Result of :func:`loop_axis_variance_factors`.

    Attributes
    ----------
    axis_scale : list of float
        ``d``: six factors, one per axis of a loop edge's tangent space ([omega, v], gtsam order),
        applied as ``Lambda' = diag(sqrt d) Lambda diag(sqrt d)`` (all 1 when nothing was estimated).
    sigma_sq : list of list of float
        The six ``sigma_j^2`` of every iteration (all near 1 at the last when it converged).
    redundancy : list of float or None
        ``r_j`` at the last iteration (they add up to the loops' redundancy).
    n_loops, iterations, converged, reason
        As :class:`LoopVarianceFactor`.
    """

    axis_scale: list[float]
    sigma_sq: list[list[float]]
    redundancy: list[float] | None
    n_loops: int
    iterations: int
    converged: bool
    reason: str | None = None

    def scaled_information(self, information: np.ndarray) -> np.ndarray:
        """A loop edge's ``(6, 6)`` information with the six factors applied."""
        return _axis_scaled(information, np.asarray(self.axis_scale))

    def summary(self) -> dict[str, Any]:
        """JSON-ready dict (the round summary's ``loop_variance["axes"]``)."""
        return {"method": "loop_axis_variance_components", "axis_scale": self.axis_scale,
                "sigma_sq": self.sigma_sq, "redundancy": self.redundancy, "n_loops": self.n_loops,
                "iterations": self.iterations, "converged": self.converged, "reason": self.reason}


def loop_axis_variance_factors(solve: Callable[[list[np.ndarray]], tuple[gtsam.NonlinearFactorGraph, gtsam.Values]],
                               edges: Sequence[RegistrationEdge], max_iterations: int = 20,
                               tol: float = 1e-2, inflate_only: bool = True) -> LoopAxisVarianceFactors:
    """Six variance factors of the loops, one per tangent axis, the odometry held fixed (the second
    stage of ``graph.loop_variance: estimated_axes``, applied to the loops :func:`loop_variance_factor`
    has scaled).

    The model: every loop edge's covariance is ``S Sigma_e S`` with ``S = diag(sigma_1 .. sigma_6)``
    shared by all loops, e.g. a registration whose pitch error is larger than its Hessian says (a
    16-ring scan pair misses part of a pitch difference: ``benchmarks/ring_pattern_study.py``) while
    its translation is conservative. With ``v_e`` a loop's residual at the optimum,
    ``Lambda_e`` its information and ``R_e = I - J_e N^-1 J_e^T Lambda_e`` its block of the
    redundancy matrix (unwhitened; ``N`` the normal matrix of the whole graph)::

        sigma_j^2 = sum_loops v_ej (Lambda_e v_e)_j / sum_loops (R_e)_jj

    (the iterated variance-component estimate: at its fixed point, with the weights equal to the true
    ones and the odometry consistent, ``E[v_e v_e^T] Lambda_e = R_e``, so every ``sigma_j^2`` is 1;
    the numerators add up to the loops' chi2 and the denominators to their redundancy, i.e. the
    redundancy-weighted mean of the ``sigma_j^2`` is :func:`loop_variance_factor`'s estimate; a
    single ``R_jj`` may be negative when a loop's information correlates its axes).
    ``Lambda_e`` is rescaled by ``1 / sigma_j`` on both sides of axis ``j``, the graph solved again,
    until every ``|sigma_j^2 - 1| < tol``. The iteration amplifies the noise of the first estimate:
    on simulated consistent loops (80, ~30 redundancy an axis) single factors came out down to 0.47.

    ``inflate_only`` (default): a factor never exceeds 1, i.e. a loop is never made more certain
    on an axis than it came in (its information is a floor: biases only add to the error). Without
    this, an axis on which the loops are far more precise than the odometry between them collapses:
    a stronger loop leaves itself less redundancy and a smaller residual, so its factor grows
    without bound (seen on the 16-channel full route, started from the loops as registered: yaw and
    x/y redundancies 0.4-0.6 after three iterations). An axis whose redundancy is under 0.5 is left
    as it is.

    Parameters and the dense Jacobian block as :func:`loop_variance_factor`.

    Returns
    -------
    LoopAxisVarianceFactors
        All factors 1 with ``reason`` set when they cannot be estimated (no loops, no axis with
        redundancy and a positive residual sum, a singular normal matrix).
    """
    ones = [1.0] * 6
    loops = [i for i, e in enumerate(edges) if e.kind == "loop"]
    if not loops:
        return LoopAxisVarianceFactors(ones, [], None, 0, 0, False, "no loops")
    info = [np.asarray(e.information, np.float64) for e in edges]
    is_loop = set(loops)
    d = np.ones(6)
    history: list[list[float]] = []
    r_axes: list[float] | None = None
    for it in range(max_iterations):
        graph, values = solve([_axis_scaled(h, d) if i in is_loop else h for i, h in enumerate(info)])
        try:
            J, lu = _whitened_jacobian(graph, values)
        except RuntimeError as exc:  # splu: a singular normal matrix (a pose no factor constrains)
            return LoopAxisVarianceFactors(ones, history, None, len(loops), it, False,
                                           f"singular normal matrix ({exc})")
        J_loops = J[_factor_rows([1 + i for i in loops])].toarray()  # factor 0: the prior
        X = lu.solve(np.ascontiguousarray(J_loops.T))
        quadratic, redundancy = np.zeros(6), np.zeros(6)
        for n, i in enumerate(loops):
            factor = graph.at(1 + i)
            # the whitening gtsam used (W^T W = Lambda as the graph holds it, floors included): the
            # whitened Jacobian's rows are W J, so J N^-1 J^T Lambda = W^-1 (W J N^-1 J^T W^T) W
            W = np.asarray(factor.noiseModel().R(), np.float64)
            block = slice(6 * n, 6 * n + 6)
            redundancy += 1.0 - np.diag(np.linalg.solve(W, (J_loops[block] @ X[:, block]) @ W))
            v = np.asarray(factor.unwhitenedError(values), np.float64)
            quadratic += v * ((W.T @ W) @ v)
        r_axes = redundancy.tolist()
        estimable = (redundancy >= 0.5) & np.isfinite(quadratic) & (quadratic > 0.0)
        if not estimable.any():
            return LoopAxisVarianceFactors(ones, history, r_axes, len(loops), it, False,
                                           "no loop redundancy or no loop residuals on any axis")
        s2 = np.where(estimable, quadratic / np.where(estimable, redundancy, 1.0), 1.0)
        history.append(s2.tolist())
        d = np.minimum(d / s2, 1.0) if inflate_only else d / s2
        settled = (np.abs(s2 - 1.0) < tol) | ((d == 1.0) & (s2 < 1.0)) if inflate_only else np.abs(s2 - 1.0) < tol
        if np.all(settled):
            return LoopAxisVarianceFactors(d.tolist(), history, r_axes, len(loops), it + 1, True)
    return LoopAxisVarianceFactors(d.tolist(), history, r_axes, len(loops), max_iterations, False)
