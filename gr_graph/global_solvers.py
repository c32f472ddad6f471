"""Global registration solvers: two scans registered from scratch (no initial guess).

Both start from FPFH features of voxel-downsampled scans:

- ``"kiss_matcher"``: KISS-Matcher (faster-PFH + ROBIN max-clique pruning + GNC, a
  TEASER-class certifiable-style solver). Optional dependency ``kiss-matcher``; when it is
  missing the solver is skipped with a log line. Run in a worker process bound to one CPU, so
  that its answers do not depend on thread scheduling (:func:`register_kiss_matcher`).
- ``"fpfh_ransac"``: open3d's FPFH + RANSAC
  (``registration_ransac_based_on_feature_matching``), seeded and deterministic.

Scans are ``(N, 3)`` points in their own sensor frame; a solver returns
``T_target_source`` (maps source points into the target frame). The evaluation protocol is
:mod:`gr_graph.global_registration`.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)

DEFAULT_VOXEL = 0.5
SOLVER_NAMES = ("kiss_matcher", "fpfh_ransac")


@dataclass(frozen=True)
class RegistrationOutcome:
    """One global registration: the estimate ``T_target_source`` and solver diagnostics.

    ``valid`` is False when the solver found no solution (``T`` is then the identity, which the
    evaluation must count as a failure: near pairs are often within the success thresholds of it).
    """

    solver: str
    T: np.ndarray
    n_inliers: int
    seconds: float
    valid: bool = True


def _check_cloud(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected (N, 3) points, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: contains non-finite points")
    if len(p) < 10:
        raise ValueError(f"{name}: only {len(p)} points")
    return p


def _fpfh(points: np.ndarray, voxel: float) -> tuple[Any, Any]:
    import open3d as o3d

    reg = o3d.pipelines.registration
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    feat = reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100))
    return pc, feat


def register_fpfh_ransac(
    source: np.ndarray,
    target: np.ndarray,
    voxel: float = DEFAULT_VOXEL,
    seed: int = 0,
    max_iterations: int = 100_000,
    confidence: float = 0.999,
) -> RegistrationOutcome:
    """Global registration with open3d FPFH features + RANSAC (deterministic for a seed).

    Parameters
    ----------
    source, target : (N, 3) arrays
        Points in their own frames.
    voxel : float
        Voxel size (m) of the downsampling; normals use radius 2.5 voxel, FPFH 5 voxel,
        inlier distance 1.5 voxel.
    seed : int
        open3d random seed.
    max_iterations, confidence : RANSAC stopping criteria.

    Returns
    -------
    RegistrationOutcome
        ``T`` maps source points into the target frame; ``n_inliers`` is the RANSAC
        correspondence-set size (``valid`` False under 3: no hypothesis was accepted).
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    src = _check_cloud(source, "source")
    tgt = _check_cloud(target, "target")
    t0 = time.perf_counter()
    a, fa = _fpfh(src, voxel)
    b, fb = _fpfh(tgt, voxel)
    o3d.utility.random.seed(int(seed))
    dist = 1.5 * voxel
    res = reg.registration_ransac_based_on_feature_matching(
        a,
        b,
        fa,
        fb,
        True,  # mutual filter
        dist,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(int(max_iterations), float(confidence)),
    )
    T = np.array(res.transformation, dtype=np.float64)
    n_in = int(len(res.correspondence_set))
    # no hypothesis passed the checkers: open3d returns the identity with no correspondences
    return RegistrationOutcome("fpfh_ransac", T, n_in, time.perf_counter() - t0, valid=n_in >= 3)


def kiss_matcher_available() -> bool:
    """True when the optional ``kiss_matcher`` package can be imported."""
    try:
        import kiss_matcher  # noqa: F401
    except ImportError:
        return False
    return True


def register_kiss_matcher(
    source: np.ndarray, target: np.ndarray, voxel: float = DEFAULT_VOXEL
) -> RegistrationOutcome:
    """Global registration with KISS-Matcher (``pip install kiss-matcher``), deterministic.

    KISS-Matcher runs its loops on TBB threads, and its answer depends on how they are
    scheduled: on 2 cores the same pair gave another transform and inlier count on every call.
    It therefore runs in a worker process bound to one CPU (TBB sizes its thread pool from that),
    where the same pair gives the same answer in every call and process. Where a process cannot be
    bound (no ``os.sched_setaffinity``: macOS, Windows) it runs here, not deterministic (warned once).

    Returns
    -------
    RegistrationOutcome
        ``T`` maps source points into the target frame (identity and ``valid`` False when
        KISS-Matcher reports no valid solution); ``n_inliers`` is its final inlier count.

    Raises
    ------
    ImportError
        ``kiss_matcher`` is not installed.
    """
    if not kiss_matcher_available():  # pragma: no cover - depends on the environment
        raise ImportError("KISS-Matcher is not installed: pip install kiss-matcher")
    src = _check_cloud(source, "source")
    tgt = _check_cloud(target, "target")
    t0 = time.perf_counter()
    worker = _one_cpu_worker()
    if worker is None:
        valid, T, n_in = _kiss_matcher_estimate(src, tgt, float(voxel))
    else:
        valid, T, n_in = worker.submit(_kiss_matcher_estimate, src, tgt, float(voxel)).result()
    if not valid:
        logger.debug("KISS-Matcher returned no valid solution")
    return RegistrationOutcome("kiss_matcher", T, n_in, time.perf_counter() - t0, valid=valid)


def _kiss_matcher_estimate(src: np.ndarray, tgt: np.ndarray, voxel: float) -> tuple[bool, np.ndarray, int]:
    """One KISS-Matcher solve: (valid, T_target_source, final inliers); identity and 0 when not valid."""
    import kiss_matcher

    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel))
    sol = matcher.estimate(src, tgt)
    T = np.eye(4)
    if not sol.valid:
        return False, T, 0
    T[:3, :3] = np.asarray(sol.rotation, dtype=np.float64)
    T[:3, 3] = np.asarray(sol.translation, dtype=np.float64).ravel()
    return True, T, int(matcher.get_num_final_inliers())


_WORKER: Any = None
_WORKER_LOCK = threading.Lock()


def _bind_to_one_cpu() -> None:
    """Worker initialiser: this process on its lowest allowed CPU, before KISS-Matcher starts TBB."""
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def _one_cpu_worker() -> Any:
    """The process pool of one worker bound to one CPU (started on first use, 'spawn': no state of
    this process, in particular no TBB pool, is inherited), or None where processes cannot be bound."""
    global _WORKER
    if not hasattr(os, "sched_setaffinity"):
        if _WORKER is None:
            logger.warning("KISS-Matcher: this system cannot bind a process to one CPU; its results vary from "
                           "run to run (TBB thread scheduling)")
            _WORKER = False
        return None
    with _WORKER_LOCK:
        if not _WORKER:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            _WORKER = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                          initializer=_bind_to_one_cpu)
        return _WORKER


def available_solvers() -> tuple[str, ...]:
    """Names of the solvers usable here (``kiss_matcher`` only if installed)."""
    return tuple(s for s in SOLVER_NAMES if s != "kiss_matcher" or kiss_matcher_available())


def register(solver: str, source: np.ndarray, target: np.ndarray, voxel: float = DEFAULT_VOXEL, seed: int = 0) -> RegistrationOutcome:
    """Dispatch to a solver by name (see :data:`SOLVER_NAMES`)."""
    if solver == "fpfh_ransac":
        return register_fpfh_ransac(source, target, voxel=voxel, seed=seed)
    if solver == "kiss_matcher":
        return register_kiss_matcher(source, target, voxel=voxel)
    raise ValueError(f"unknown solver {solver!r}; choose from {SOLVER_NAMES}")
