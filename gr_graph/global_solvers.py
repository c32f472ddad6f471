"""Global registration solvers: two scans registered from scratch (no initial guess).

Both start from FPFH features of voxel-downsampled scans:

- ``"kiss_matcher"``: KISS-Matcher (faster-PFH + ROBIN max-clique pruning + GNC, a
  TEASER-class certifiable-style solver). Optional dependency ``kiss-matcher``; when it is
  missing the solver is skipped with a log line. Run in a worker process bound to one CPU, so
  that its answers do not depend on thread scheduling (:func:`register_kiss_matcher`,
  :mod:`gr_graph.kiss_matcher_worker`).
- ``"fpfh_ransac"``: open3d's FPFH + RANSAC
  (``registration_ransac_based_on_feature_matching``), seeded and deterministic.

Scans are ``(N, 3)`` points in their own sensor frame; a solver returns
``T_target_source`` (maps source points into the target frame). The evaluation protocol is
:mod:`gr_graph.global_registration`.
"""

from __future__ import annotations

import atexit
import logging
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
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
    It therefore runs in a process bound to one CPU (:mod:`gr_graph.kiss_matcher_worker`, started
    on first use), where the same pair gives the same answer in every call and process. Where a
    process cannot be bound (no ``os.sched_setaffinity``: macOS, Windows) it runs here, not
    deterministic (warned once). A worker that dies is started again for the pair once; a second
    death raises :class:`SolverCrashError`.

    Returns
    -------
    RegistrationOutcome
        ``T`` maps source points into the target frame (identity and ``valid`` False when
        KISS-Matcher reports no valid solution); ``n_inliers`` is its final inlier count.

    Raises
    ------
    ImportError
        ``kiss_matcher`` is not installed.
    RuntimeError
        KISS-Matcher raised on the pair (in the worker).
    SolverCrashError
        The worker process died twice on the pair.
    """
    if not kiss_matcher_available():  # pragma: no cover - depends on the environment
        raise ImportError("KISS-Matcher is not installed: pip install kiss-matcher")
    src = _check_cloud(source, "source")
    tgt = _check_cloud(target, "target")
    t0 = time.perf_counter()
    if not hasattr(os, "sched_setaffinity"):
        global _UNBOUND_WARNED
        if not _UNBOUND_WARNED:
            logger.warning("KISS-Matcher: this system cannot bind a process to one CPU; its results vary from "
                           "run to run (TBB thread scheduling)")
            _UNBOUND_WARNED = True
        valid, T, n_in = kiss_matcher_estimate(src, tgt, float(voxel))
    else:
        valid, T, n_in = _WORKER.solve(src, tgt, float(voxel))
    if not valid:
        logger.debug("KISS-Matcher returned no valid solution")
    return RegistrationOutcome("kiss_matcher", T, n_in, time.perf_counter() - t0, valid=valid)


def kiss_matcher_estimate(src: np.ndarray, tgt: np.ndarray, voxel: float) -> tuple[bool, np.ndarray, int]:
    """One KISS-Matcher solve in this process: (valid, T_target_source, final inliers); identity and 0
    when not valid. Not deterministic on several CPUs: :func:`register_kiss_matcher` runs it bound."""
    import kiss_matcher

    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel))
    sol = matcher.estimate(src, tgt)
    T = np.eye(4)
    if not sol.valid:
        return False, T, 0
    T[:3, :3] = np.asarray(sol.rotation, dtype=np.float64)
    T[:3, 3] = np.asarray(sol.translation, dtype=np.float64).ravel()
    return True, T, int(matcher.get_num_final_inliers())


class SolverCrashError(Exception):
    """A solver's worker process died twice on one pair (e.g. a crash in the native library, or the
    out-of-memory killer): not one failed pair, so the evaluation stops."""


class _BoundWorker:
    """The :mod:`gr_graph.kiss_matcher_worker` process (one, started on first use, ended at exit)."""

    def __init__(self) -> None:
        self._proc: subprocess.Popen[bytes] | None = None
        self._lock = threading.Lock()
        self.cpu_seconds = 0.0  # CPU time of the solves in the worker processes so far

    def _start(self) -> subprocess.Popen[bytes]:
        import gr_graph

        env = dict(os.environ)  # the worker imports this very gr_graph, installed or not
        root = str(Path(gr_graph.__file__).resolve().parents[1])
        env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
        return subprocess.Popen([sys.executable, "-m", "gr_graph.kiss_matcher_worker"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, env=env)

    def solve(self, src: np.ndarray, tgt: np.ndarray, voxel: float) -> tuple[bool, np.ndarray, int]:
        from gr_graph.kiss_matcher_worker import read_message, write_message

        with self._lock:
            for attempt in (1, 2):
                if self._proc is None:
                    self._proc = self._start()
                assert self._proc.stdin is not None and self._proc.stdout is not None
                try:
                    write_message(self._proc.stdin, (src, tgt, voxel))
                    status, answer, cpu_s = read_message(self._proc.stdout)
                except (EOFError, OSError) as exc:  # BrokenPipeError is an OSError
                    try:
                        code = self._proc.wait(timeout=10)
                    except subprocess.TimeoutExpired:  # alive but not answering: ended
                        code = None
                    self.close_locked()
                    if attempt == 2:
                        raise SolverCrashError(f"KISS-Matcher's worker process died twice on one pair (exit code "
                                               f"{code}; {type(exc).__name__})") from exc
                    logger.warning("KISS-Matcher's worker process died (exit code %s): started again", code)
                    continue
                self.cpu_seconds += float(cpu_s)
                if status != "ok":
                    raise RuntimeError(f"KISS-Matcher: {answer}")
                return answer
        raise AssertionError("unreachable")

    def close_locked(self) -> None:
        if self._proc is not None:
            proc, self._proc = self._proc, None
            for stream in (proc.stdin, proc.stdout):
                if stream is not None:
                    stream.close()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def close(self) -> None:
        with self._lock:
            self.close_locked()


_WORKER = _BoundWorker()
_UNBOUND_WARNED = False
atexit.register(_WORKER.close)


def worker_cpu_seconds() -> float:
    """CPU time spent in the KISS-Matcher worker processes of this process so far [s] (their solves)."""
    return _WORKER.cpu_seconds


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
