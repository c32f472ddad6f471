"""Loop closures: candidates (proximity on the estimate, Scan Context), geometric verification.

Candidates for the query scan i are older scans j (i − j ≥ ``min_frame_gap`` and, when
``min_path_length`` is set, that much path back along the estimate: :func:`newest_candidate`):

- *proximity*: the nearest scan within ``radius`` on the current (loop-corrected) estimate,
  with the estimate's relative pose as initial guess;
- *Scan Context* (Kim & Kim, IROS 2018): a polar max-height descriptor (rings × sectors),
  a rotation-invariant ring key to shortlist, and the column-shift distance to rescore; the
  best shift gives an initial yaw. It finds revisits when drift is too large for proximity.

A candidate enters the graph only after verification: GICP from the guess with a coarse
then a fine correspondence distance; accepted when the fraction of source points within
``max_correspondence_distance`` of the target is ≥ ``min_inlier_ratio``, the inlier RMSE is
≤ ``max_rmse`` and (proximity) the correction to the guess is ≤ ``max_correction``.
The edge is (i, j): source P = S_i, target Q = S_j, T̂_ij maps scan i into the frame of j.

When a SLAM run looks for loops and re-optimises its graph is :class:`LoopClosureSchedule`;
loops against ground truth are :mod:`gr_graph.loop_evaluation`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import small_gicp

from gr_graph.config import GraphConfig, LoopConfig
from gr_graph.odometry import RegistrationEdge, registration_information
from gr_graph.preprocess import Scan
from gr_graph.registration_covariance import gicp_correspondences

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- descriptor


def scan_context(points: np.ndarray, n_rings: int = 20, n_sectors: int = 60, max_radius: float = 80.0,
                 z_offset: float = 2.0) -> np.ndarray:
    """Scan Context descriptor: max of (z + ``z_offset``) per polar bin, ``(n_rings, n_sectors)``.

    Sector 0 starts at azimuth −π; empty bins are 0.
    """
    p = np.asarray(points, dtype=np.float64)
    desc = np.zeros((n_rings, n_sectors), dtype=np.float64)
    if len(p) == 0:
        return desc
    r = np.hypot(p[:, 0], p[:, 1])
    keep = r < max_radius
    p, r = p[keep], r[keep]
    ring = np.minimum((r / max_radius * n_rings).astype(np.int64), n_rings - 1)
    az = np.arctan2(p[:, 1], p[:, 0])
    sector = np.minimum(((az + np.pi) / (2 * np.pi) * n_sectors).astype(np.int64), n_sectors - 1)
    h = np.maximum(p[:, 2] + z_offset, 0.0)
    np.maximum.at(desc, (ring, sector), h)
    return desc


def ring_key(desc: np.ndarray) -> np.ndarray:
    """Rotation-invariant key: the fraction of occupied sectors per ring."""
    return (desc > 0).mean(axis=1)


def scan_context_distance(query: np.ndarray, candidate: np.ndarray) -> tuple[float, int]:
    """Column-shift cosine distance between two descriptors and the best shift.

    Returns ``(distance in [0, 1], shift)`` where ``np.roll(query, shift, axis=1)`` best
    matches ``candidate``: the query scan is rotated by ``shift · 2π / n_sectors`` (yaw)
    relative to the candidate.
    """
    n_s = query.shape[1]
    shifts = np.stack([np.roll(query, s, axis=1) for s in range(n_s)])  # (S, R, N)
    num = np.einsum("srn,rn->sn", shifts, candidate)
    nq = np.linalg.norm(shifts, axis=1)
    nc = np.linalg.norm(candidate, axis=0)[None, :]
    valid = (nq > 0) & (nc > 0)
    cos = np.where(valid, num / np.where(valid, nq * nc, 1.0), 0.0)
    cnt = valid.sum(axis=1)
    sim = np.where(cnt > 0, cos.sum(axis=1) / np.maximum(cnt, 1), 0.0)
    s = int(np.argmax(sim))
    return float(1.0 - sim[s]), s


def yaw_matrix(yaw: float) -> np.ndarray:
    """4x4 rotation about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


# ----------------------------------------------------------------------------- candidates


@dataclass
class LoopCandidate:
    """A candidate pair: query i (source) and old scan j (target), with an initial guess T_ji
    (maps points of scan i into the frame of scan j: the module's T̂_ij, named by its frames here)."""

    query: int
    match: int
    guess: np.ndarray
    source: str  # "proximity" or "scan_context"
    score: float  # distance [m] or descriptor distance


class RowBuffer:
    """Rows appended one at a time to an array that doubles its capacity: :meth:`rows` gives
    the first rows without converting a Python list of all of them (a cost that grew with the run
    at every loop check)."""

    def __init__(self, row_shape: tuple[int, ...], dtype: type = np.float64) -> None:
        self._data = np.zeros((16, *row_shape), dtype)
        self.n = 0

    def append(self, row: np.ndarray) -> None:
        if self.n == len(self._data):
            grown = np.zeros((2 * len(self._data), *self._data.shape[1:]), self._data.dtype)
            grown[: self.n] = self._data
            self._data = grown
        self._data[self.n] = row
        self.n += 1

    def extend(self, rows: list[np.ndarray]) -> None:
        for row in rows:
            self.append(row)

    def rows(self, upto: int | None = None) -> np.ndarray:
        """A read-only view of the first ``upto`` rows (all by default)."""
        view = self._data[: self.n if upto is None else min(int(upto), self.n)]
        view.flags.writeable = False
        return view


class ScanContextDatabase:
    """Descriptors and ring keys of the scans seen so far."""

    def __init__(self, cfg: LoopConfig) -> None:
        self.cfg = cfg
        self.descs: list[np.ndarray] = []
        self.keys = RowBuffer((cfg.sc_rings,))

    def add(self, points: np.ndarray) -> None:
        d = scan_context(points, self.cfg.sc_rings, self.cfg.sc_sectors, self.cfg.sc_max_radius,
                         self.cfg.sc_height_offset)
        self.descs.append(d)
        self.keys.append(ring_key(d))

    def query(self, i: int, last: int | None = None) -> LoopCandidate | None:
        """Best Scan Context candidate for scan ``i`` among scans ≤ ``last`` (default i − min_frame_gap)."""
        if last is None:
            last = i - self.cfg.min_frame_gap
        if last < 0:
            return None
        keys = self.keys.rows(last + 1)
        dk = np.linalg.norm(keys - self.keys.rows()[i][None, :], axis=1)
        order = np.argsort(dk, kind="stable")[: self.cfg.sc_num_candidates]  # ties (a stop): the same on any CPU
        best: tuple[float, int, int] | None = None
        for j in order:
            d, s = scan_context_distance(self.descs[i], self.descs[j])
            if best is None or d < best[0]:
                best = (d, int(j), s)
        if best is None or best[0] > self.cfg.sc_threshold:
            return None
        d, j, s = best
        yaw = s * 2 * np.pi / self.cfg.sc_sectors
        return LoopCandidate(i, j, yaw_matrix(yaw), "scan_context", d)


def newest_candidate(estimate: np.ndarray, i: int, cfg: LoopConfig) -> int:
    """The newest scan that may be a loop candidate for scan ``i`` (-1: none).

    It is ``min_frame_gap`` frames back and, with ``min_path_length`` > 0, also that much path back
    along ``estimate`` (poses 0..i, (K, 4, 4)): summed distances between consecutive positions.
    A vehicle stopped for longer than ``min_frame_gap`` frames otherwise finds "loops" with itself at
    the stop, which tell the graph nothing about drift but count as loops.
    """
    last = i - cfg.min_frame_gap
    if last < 0:
        return -1
    if cfg.min_path_length <= 0.0:
        return last
    return min(last, last_scan_path_back(path_lengths(estimate[: i + 1, :3, 3]), i, cfg.min_path_length))


def path_lengths(positions: np.ndarray) -> np.ndarray:
    """``(K,)`` path length from the first of ``positions`` (K, 3) to each: summed distances between
    consecutive positions."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])


def last_scan_path_back(path: np.ndarray, i: int, length: float) -> int:
    """The last scan j at least ``length`` of path before scan ``i`` (``path``: :func:`path_lengths`),
    -1 when there is none."""
    return int(np.searchsorted(path, path[i] - length, side="right")) - 1


def proximity_candidate(poses: np.ndarray, i: int, cfg: LoopConfig, last: int | None = None) -> LoopCandidate | None:
    """Nearest scan ≤ ``last`` (default i − min_frame_gap) within ``radius`` of scan ``i`` on the
    estimate ``poses`` (K, 4, 4)."""
    if last is None:
        last = i - cfg.min_frame_gap
    if last < 0:
        return None
    d = np.linalg.norm(poses[: last + 1, :3, 3] - poses[i, :3, 3][None, :], axis=1)
    j = int(np.argmin(d))
    if d[j] > cfg.radius:
        return None
    guess = np.linalg.inv(poses[j]) @ poses[i]
    return LoopCandidate(i, j, guess, "proximity", float(d[j]))


def loop_candidates(estimate: np.ndarray, i: int, scan_context_db: ScanContextDatabase | None,
                    cfg: LoopConfig) -> list[LoopCandidate]:
    """Candidates for query scan ``i`` among the scans up to :func:`newest_candidate`: proximity on
    ``estimate`` (poses 0..i) first, then Scan Context (``scan_context_db``, None when disabled)
    unless it names a scan within 5 frames of the proximity match."""
    cands: list[LoopCandidate] = []
    last = newest_candidate(estimate, i, cfg)
    if last < 0:
        return cands
    c = proximity_candidate(estimate, i, cfg, last) if cfg.use_proximity else None
    if c is not None:
        cands.append(c)
    if scan_context_db is not None:
        c = scan_context_db.query(i, last)
        if c is not None and not any(abs(c.match - o.match) < 5 for o in cands):
            cands.append(c)
    return cands


# ----------------------------------------------------------------------------- schedule


class LoopClosureSchedule:
    """When a SLAM run looks for loops and when it re-optimises the graph.

    Scan ``i`` is checked when ``i`` is a multiple of ``check_every``, at least
    ``min_frame_gap``, its scan is usable, and no cooldown is running; a cooldown of
    ``cooldown`` such checks follows each accepted loop (the check is skipped and the cooldown
    counts down). After new loops the graph is re-optimised at a check at least
    ``reoptimize_every`` frames after the last re-optimisation.

    Use: ``if schedule.should_check(i, usable): ...; schedule.loop_accepted(); ...;
    if schedule.should_reoptimize(i): optimise; schedule.reoptimized(i)``.
    """

    def __init__(self, cfg: LoopConfig) -> None:
        self.cfg = cfg
        self.cooldown = 0  # checks still to skip
        self.pending_loops = 0  # loops accepted since the last re-optimisation
        self.last_optimisation = 0  # frame of the last re-optimisation

    def should_check(self, i: int, usable: bool) -> bool:
        """Whether to look for a loop at scan ``i`` (counts the cooldown down on a skipped check)."""
        if i % self.cfg.check_every or i < self.cfg.min_frame_gap or not usable:
            return False
        if self.cooldown > 0:
            self.cooldown -= 1
            return False
        return True

    def loop_accepted(self) -> None:
        """A loop entered the graph: start the cooldown, ask for a re-optimisation."""
        self.pending_loops += 1
        self.cooldown = self.cfg.cooldown

    def should_reoptimize(self, i: int) -> bool:
        """Whether to re-optimise after the check at scan ``i``."""
        return self.pending_loops > 0 and i - self.last_optimisation >= self.cfg.reoptimize_every

    def reoptimized(self, i: int) -> None:
        """The graph was re-optimised at scan ``i``."""
        self.pending_loops, self.last_optimisation = 0, i


# ----------------------------------------------------------------------------- verification


def verify_loop(
    source: Scan, target: Scan, cand: LoopCandidate, cfg: LoopConfig, graph_cfg: GraphConfig, num_threads: int = 1
) -> RegistrationEdge:
    """Register ``source`` (scan i) onto ``target`` (scan j) from the guess and judge it.

    Returns a loop :class:`RegistrationEdge` with ``ok`` telling whether it was accepted and
    ``reason`` why not.
    """
    info = {"candidate": cand.source, "score": cand.score}

    def reject(reason: str, T: np.ndarray, extra: dict | None = None) -> RegistrationEdge:
        return RegistrationEdge(cand.query, cand.match, T, np.zeros((6, 6)), np.zeros((6, 6)), 0.0,
                                float("nan"), 0, False, reason, "loop", {**info, **(extra or {})})

    if not (source.usable and target.usable):
        return reject("unusable scan", cand.guess)
    T = cand.guess
    res = None
    stages = [cfg.coarse_correspondence_distance, 0.5 * (cfg.coarse_correspondence_distance + cfg.max_correspondence_distance),
              cfg.max_correspondence_distance]
    for dist in stages:
        res = small_gicp.align(target.cloud, source.cloud, target.tree, init_T_target_source=T,
                               registration_type="GICP", max_correspondence_distance=dist,
                               num_threads=num_threads, max_iterations=30)
        T = np.asarray(res.T_target_source)
        if not np.all(np.isfinite(T)):
            return reject("non-finite registration", cand.guess)
    src = source.points @ T[:3, :3].T + T[:3, 3]
    idx, d2 = target.tree.batch_nearest_neighbor_search(src, num_threads=num_threads)
    d = np.sqrt(np.asarray(d2))
    inl = d <= cfg.max_correspondence_distance
    ratio = float(inl.mean()) if len(d) else 0.0
    rmse = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else float("inf")
    correction = float(np.linalg.norm((np.linalg.inv(cand.guess) @ T)[:3, 3]))
    extra = {"inlier_ratio": ratio, "rmse": rmse, "correction": correction}
    if ratio < cfg.min_inlier_ratio:
        return reject(f"inlier ratio {ratio:.2f} < {cfg.min_inlier_ratio:.2f}", T, extra)
    max_rmse = 0.35 if cfg.max_rmse is None else cfg.max_rmse
    if rmse > max_rmse:
        return reject(f"rmse {rmse:.2f} > {max_rmse:.2f} m", T, extra)
    if cand.source == "proximity" and correction > cfg.max_correction:
        return reject(f"correction {correction:.1f} m > {cfg.max_correction:.1f} m", T, extra)
    H = np.asarray(res.H, dtype=np.float64)
    if not np.all(np.isfinite(H)) or res.num_inliers < 6:
        return reject("degenerate Hessian", T, extra)
    information, model = registration_information(
        res, T, graph_cfg, lambda: gicp_correspondences(target.cloud, target.tree, source.cloud, T,
                                                        cfg.max_correspondence_distance))
    return RegistrationEdge(cand.query, cand.match, T, H, information, ratio,
                            float(res.error / max(res.num_inliers, 1)), int(res.iterations), True, "", "loop",
                            {**info, **extra, "covariance": model}, converged=bool(res.converged))
