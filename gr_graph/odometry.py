"""VGICP odometry front end (small_gicp) with a constant-velocity guess and failure handling.

Each new scan ``k+1`` (source) is registered onto the past (target): in ``"map"`` mode a
sliding Gaussian voxel map of the recent scans in the odometry frame, in ``"scan"`` mode
the previous scan alone. The result is one odometry edge ``(k+1, k)`` with

- ``T``: T̂_{k+1,k} = T_k⁻¹ T_{k+1}, mapping points of scan k+1 into the frame of scan k
  (the memory convention: source P = S_{k+1}, target Q = S_k);
- ``H_raw``: small_gicp's Gauss-Newton Hessian of its cost ½Σ dᵀΩd (gtsam order [ω, v],
  right perturbation, so it is directly the Hessian w.r.t. T̂_{k+1,k} ∘ Exp(ξ));
- ``information``: ``H_raw`` divided by the a-posteriori variance factor
  σ₀² = 2·error / (3·inliers − 6) (small_gicp's covariances are unit-less plane shapes, not
  metric noise), times ``graph.hessian_scale`` (points are spatially correlated); or, with
  ``graph.registration_covariance: cluster_robust``, the inverse of the cluster-robust covariance
  from the registration's own residuals (:mod:`gr_graph.registration_covariance`);
- fitness figures: inlier ratio, mean cost per inlier, iterations.

In ``"map"`` mode every scan enters the map at its pose by default. With
``map_keyframe_translation`` / ``map_keyframe_rotation_deg`` a scan enters only after the
vehicle moved or turned that much since the last scan that entered (:meth:`VgicpOdometry.
enters_map`): a stopped vehicle otherwise fills the map with one ring pattern, repeated scan after
scan, and the registrations at motion start follow that pattern rather than the world (the car's
pitch as it pulls away is missed: benchmarks/results/findings.md, Odometry at motion start).

The constant-velocity guess of a step is the last accepted frame-to-frame motion, scaled to the
time between the two frames when their timestamps are given (:meth:`VgicpOdometry.step`'s ``dt``;
:func:`time_scaled_motion`: ``Exp(ratio · Log(delta))``, ``ratio`` = this step's time over the time
the last accepted motion spanned): after dropped frames (a 0.4 s gap in a 10 Hz recording) the guess
covers the whole gap, and so does the divergence test. A ratio within :data:`GUESS_RATIO_DEADBAND`
of 1 (the timestamps' jitter: at most 3.4 % in KITTI 00's) leaves the motion as it is, bit for bit;
a ratio that is not finite or not positive (repeated or decreasing timestamps) is taken as 1; a
ratio above :data:`MAX_GUESS_RATIO` is clipped to it.

A registration that returns non-finite values, has an inlier ratio below
``min_inlier_ratio``, or ends further than ``max_deviation_*`` from the constant-velocity
guess is *flagged* (``ok=False``, ``reason`` says why), logged, and replaced by the guess
with a weak fallback information (``graph.fallback_sigmas``); never silently kept. Until a first
registration is accepted no motion is known and the guess (the identity) predicts nothing: the
divergence test is not applied then (logged once), so a recording that starts at speed (more than
``max_deviation_translation`` a frame: 72 km/h at 10 Hz, or a folder keeping every other frame)
is not flagged edge after edge against a standing start; the inlier ratio still guards.

The learned alternative to the registration information is :mod:`gr_graph.edge_noise`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import small_gicp

from factors.se3 import exp_se3, log_se3, rotation_angle
from gr_graph.config import GraphConfig, OdometryConfig
from gr_graph.preprocess import Scan
from gr_graph.registration_covariance import Correspondences, cluster_robust_information, vgicp_correspondences

log = logging.getLogger(__name__)

#: a time ratio within this of 1 leaves the constant-velocity guess unscaled (timestamp jitter, not a
#: change of frame rate; keeps evenly spaced sequences bit-identical whatever the float rounding of their times)
GUESS_RATIO_DEADBAND = 0.1
#: the constant-velocity guess is extrapolated over at most this many times the last motion's duration
MAX_GUESS_RATIO = 10.0


@dataclass
class RegistrationEdge:
    """One registered scan pair (odometry or loop).

    Attributes
    ----------
    source, target : int
        Positions (0-based, within the run) of the source scan P and target scan Q.
    T : np.ndarray
        ``(4, 4)`` T̂_{source,target}: maps source points into the target frame.
    H_raw : np.ndarray
        ``(6, 6)`` small_gicp Hessian (zeros when the registration failed).
    information : np.ndarray
        ``(6, 6)`` information used for the graph factor, gtsam order [ω, v].
    inlier_ratio, error_per_inlier : float
        Fitness figures of the registration.
    iterations : int
    ok : bool
        False when the registration failed and ``T`` is a fallback guess.
    reason : str
        Why it failed ("" when ok).
    kind : str
        "odometry" or "loop".
    info : dict
        Extra figures (loop rmse, descriptor distance...).
    converged : bool
        False when the registration ended without passing small_gicp's convergence test: it
        stopped at its iteration limit, or the Levenberg-Marquardt steps found no lower error (of a
        loop, the last of its three GICP stages). Such an edge is kept if its other tests pass,
        and counted in the round's summary. True for failed edges, which carry no registration.
    """

    source: int
    target: int
    T: np.ndarray
    H_raw: np.ndarray
    information: np.ndarray
    inlier_ratio: float
    error_per_inlier: float
    iterations: int
    ok: bool
    reason: str = ""
    kind: str = "odometry"
    info: dict = field(default_factory=dict)
    converged: bool = True


def sigmas_information(sigmas: tuple[float, ...] | np.ndarray) -> np.ndarray:
    """Diagonal information ``diag(1/σ²)`` for gtsam-ordered sigmas [ω, v]."""
    s = np.asarray(sigmas, dtype=np.float64)
    return np.diag(1.0 / s**2)


def scaled_information(H: np.ndarray, error: float, num_inliers: int, scale: float) -> np.ndarray:
    """Registration Hessian → pose information: ``scale · H / σ₀²``, σ₀² = 2·error/(3n − 6).

    small_gicp's cost is e = ½Σ dᵢᵀΩᵢdᵢ with unit-less Ωᵢ; if the real residual covariance
    is σ₀²Ωᵢ⁻¹ then E[2e] ≈ (3n − 6)·σ₀², so σ₀² is estimated from the final cost.
    """
    dof = max(3 * int(num_inliers) - 6, 1)
    var = max(2.0 * float(error) / dof, 1e-12)
    Hs = 0.5 * (H + H.T)
    return scale * Hs / var


def registration_information(res: small_gicp.RegistrationResult, T: np.ndarray, graph_cfg: GraphConfig,
                             correspondences: Callable[[], Correspondences]) -> tuple[np.ndarray, str]:
    """Information of a registered edge and the model that gave it (``graph.registration_covariance``).

    ``T`` is the registration's result (source into target), ``correspondences`` rebuilds its
    correspondences at ``T`` (called only for ``cluster_robust``). Returns the information and
    ``"scaled_hessian"``, ``"cluster_robust"`` or ``"scaled_hessian_fallback"`` (the cluster-robust
    covariance was not available: too few clusters or a singular Hessian).
    """
    scaled = scaled_information(np.asarray(res.H, dtype=np.float64), res.error, res.num_inliers,
                                graph_cfg.hessian_scale)
    if graph_cfg.registration_covariance != "cluster_robust":
        return scaled, "scaled_hessian"
    info, n_clusters = cluster_robust_information(T, correspondences(), graph_cfg.cluster_size, graph_cfg.min_clusters)
    if info is None:
        log.debug("cluster-robust covariance not available (%d clusters); scaled Hessian used", n_clusters)
        return scaled, "scaled_hessian_fallback"
    return info, "cluster_robust"


def guess_time_ratio(dt: float | None, dt_delta: float | None) -> float:
    """How much longer this step lasts (``dt``) than the last accepted motion did (``dt_delta``).

    1.0 when either is unknown, not finite or not positive, or when the ratio is within
    :data:`GUESS_RATIO_DEADBAND` of 1; clipped to :data:`MAX_GUESS_RATIO`.
    """
    if dt is None or dt_delta is None:
        return 1.0
    dt, dt_delta = float(dt), float(dt_delta)
    if not (np.isfinite(dt) and np.isfinite(dt_delta) and dt > 0.0 and dt_delta > 0.0):
        return 1.0
    ratio = dt / dt_delta
    if abs(ratio - 1.0) <= GUESS_RATIO_DEADBAND:
        return 1.0
    return min(ratio, MAX_GUESS_RATIO)


def time_scaled_motion(delta: np.ndarray, ratio: float) -> np.ndarray:
    """``Exp(ratio · Log(delta))``: the motion ``delta`` at the same velocity for ``ratio`` times as
    long; ``delta`` itself (the same array) when ``ratio`` is exactly 1."""
    if ratio == 1.0:
        return delta
    return exp_se3(ratio * log_se3(np.asarray(delta, np.float64)))


def check_registration(
    T: np.ndarray,
    guess: np.ndarray,
    inlier_ratio: float,
    min_inlier_ratio: float,
    max_dt: float,
    max_drot_deg: float,
) -> str:
    """Return "" when a registration result is acceptable, else the reason it is not."""
    if not np.all(np.isfinite(T)):
        return "non-finite result"
    if inlier_ratio < min_inlier_ratio:
        return f"inlier ratio {inlier_ratio:.2f} < {min_inlier_ratio:.2f}"
    dev = np.linalg.inv(guess) @ T
    dt = float(np.linalg.norm(dev[:3, 3]))
    drot = np.degrees(rotation_angle(dev[:3, :3]))
    if dt > max_dt or drot > max_drot_deg:
        return f"diverged: {dt:.2f} m / {drot:.1f} deg from the guess"
    return ""


class VgicpOdometry:
    """Streaming VGICP odometry. Feed preprocessed scans in order with :meth:`step`.

    Attributes
    ----------
    poses : list of (4, 4) arrays
        Odometry poses T_odom_k (the first scan is the identity).
    edges : list of RegistrationEdge
        One edge (k+1, k) per step after the first.
    """

    def __init__(self, cfg: OdometryConfig, graph_cfg: GraphConfig) -> None:
        self.cfg = cfg
        self.graph_cfg = graph_cfg
        self.poses: list[np.ndarray] = []
        self.edges: list[RegistrationEdge] = []
        self._delta = np.eye(4)
        self._delta_dt: float | None = None  # time spanned by _delta [s] (None: unknown)
        self._motion_known = False  # a registration was accepted: _delta is a measured motion
        self._map: small_gicp.GaussianVoxelMap | None = None
        self._prev: Scan | None = None
        self._last_map_pose: np.ndarray | None = None  # pose of the last scan that entered the map
        self.scans_left_out_of_map = 0

    @property
    def last_increment_period(self) -> float | None:
        """The time [s] :attr:`last_increment` spans (None: not known). After a flagged step the
        increment is still the last accepted one, and so is its period."""
        return self._delta_dt

    @property
    def last_increment(self) -> np.ndarray:
        """The last accepted frame-to-frame motion T_{k-1}^-1 T_k (identity before the second
        scan); the constant-velocity guess of the next step and the frame loop's deskew motion."""
        return self._delta.copy()

    def rebuild_map(self, scans: list[Scan]) -> None:
        """Replace the target map by ``scans`` (the first ``len(scans)`` scans, re-preprocessed)
        inserted at their current poses; the frame loop calls it once, when deskewing starts,
        so that the scans taken before any motion was known enter the map deskewed too."""
        if len(scans) > len(self.poses):
            raise ValueError(f"rebuild_map: {len(scans)} scans for {len(self.poses)} poses")
        self._map = None
        self._last_map_pose = None
        self.scans_left_out_of_map = 0
        for scan, T in zip(scans, self.poses):
            self._insert(scan, T)
        if scans and len(scans) == len(self.poses):
            self._prev = scans[-1]

    # ------------------------------------------------------------------ map
    def _new_map(self) -> small_gicp.GaussianVoxelMap:
        vm = small_gicp.GaussianVoxelMap(self.cfg.voxel_resolution)
        vm.set_lru(horizon=self.cfg.map_horizon, clear_cycle=max(1, min(10, self.cfg.map_horizon)))
        return vm

    def enters_map(self, T: np.ndarray) -> bool:
        """Whether a scan at pose ``T`` enters the ``"map"`` mode's map: always for the first one
        and with both keyframe thresholds 0, else when it is at least ``map_keyframe_translation``
        metres or ``map_keyframe_rotation_deg`` degrees away from the last scan that entered (a
        threshold of 0 is not used: ``0.1`` and ``0`` let a scan in after 0.1 m, whatever it turned)."""
        min_translation, min_rotation_deg = self.cfg.map_keyframe_translation, self.cfg.map_keyframe_rotation_deg
        if self._last_map_pose is None or (min_translation == 0.0 and min_rotation_deg == 0.0):
            return True
        step = np.linalg.inv(self._last_map_pose) @ T
        return bool((min_translation > 0.0 and np.linalg.norm(step[:3, 3]) >= min_translation)
                    or (min_rotation_deg > 0.0 and np.degrees(rotation_angle(step[:3, :3])) >= min_rotation_deg))

    def _insert(self, scan: Scan, T: np.ndarray) -> None:
        if not scan.usable:
            return
        if self.cfg.mode == "map":
            if not self.enters_map(T):
                self.scans_left_out_of_map += 1
                return
            if self._map is None:
                self._map = self._new_map()
            self._map.insert(scan.cloud, T)
            self._last_map_pose = np.array(T, dtype=np.float64)
        else:
            vm = small_gicp.GaussianVoxelMap(self.cfg.voxel_resolution)
            vm.insert(scan.cloud)
            self._map = vm

    def _deviates(self, T_rel: np.ndarray, guess_rel: np.ndarray) -> bool:
        """``T_rel`` is further from ``guess_rel`` than the divergence test allows once motion is known."""
        return bool(check_registration(T_rel, guess_rel, 1.0, 0.0, self.cfg.max_deviation_translation,
                                       self.cfg.max_deviation_rotation_deg))

    # ------------------------------------------------------------------ step
    def step(self, scan: Scan, dt: float | None = None) -> RegistrationEdge | None:
        """Register ``scan`` onto the past; return its odometry edge (None for the first scan).

        ``dt`` is the time since the previous scan [s] when the timestamps are known: the
        constant-velocity guess (initial value and divergence test) is scaled to it
        (:func:`time_scaled_motion` by :func:`guess_time_ratio`); None uses the last accepted motion as it is.
        """
        k = len(self.poses)
        if k == 0:
            self.poses.append(np.eye(4))
            self._insert(scan, np.eye(4))
            self._prev = scan
            return None
        T_prev = self.poses[-1]
        ratio = guess_time_ratio(dt, self._delta_dt)
        guess_rel = time_scaled_motion(self._delta, ratio)
        if ratio != 1.0:
            log.debug("odometry edge (%d, %d): constant-velocity guess scaled x %.3g to %.3f s", k, k - 1, ratio, dt)
        reason = ""
        if not scan.usable:
            reason = "source scan unusable (too few points)"
        elif self._map is None or (self.cfg.mode == "scan" and not self._prev.usable):
            reason = "no target map (previous scans unusable)"
        if not reason:
            init = T_prev @ guess_rel if self.cfg.mode == "map" else guess_rel
            res = small_gicp.align(
                self._map,
                scan.cloud,
                init_T_target_source=init,
                max_correspondence_distance=self.cfg.max_correspondence_distance,
                num_threads=self.cfg.num_threads,
                max_iterations=self.cfg.max_iterations,
            )
            T_res = np.asarray(res.T_target_source)
            T_rel = np.linalg.inv(T_prev) @ T_res if self.cfg.mode == "map" else T_res
            n = scan.cloud.size()
            inlier_ratio = res.num_inliers / max(n, 1)
            if self._motion_known:
                max_dt, max_drot_deg = self.cfg.max_deviation_translation, self.cfg.max_deviation_rotation_deg
            else:  # the identity guess predicts nothing: no divergence test before a first accepted motion
                max_dt = max_drot_deg = float("inf")
            reason = check_registration(T_rel, guess_rel, inlier_ratio, self.cfg.min_inlier_ratio, max_dt, max_drot_deg)
            if not reason and not self._motion_known and self._deviates(T_rel, guess_rel):
                log.info("odometry edge (%d, %d): %.2f m / %.1f deg with no motion known before: kept (no "
                         "divergence test before a first accepted motion)", k, k - 1,
                         float(np.linalg.norm(T_rel[:3, 3])), float(np.degrees(rotation_angle(T_rel[:3, :3]))))
            if not reason and not np.all(np.isfinite(res.H)):
                reason = "non-finite Hessian"
        if reason:
            log.warning("odometry edge (%d, %d): %s; using the constant-velocity guess (edge flagged)", k, k - 1, reason)
            T_rel = guess_rel.copy()
            edge = RegistrationEdge(
                source=k,
                target=k - 1,
                T=T_rel,
                H_raw=np.zeros((6, 6)),
                information=sigmas_information(self.graph_cfg.fallback_sigmas),
                inlier_ratio=0.0,
                error_per_inlier=float("nan"),
                iterations=0,
                ok=False,
                reason=reason,
            )
        else:
            H = np.asarray(res.H, dtype=np.float64)
            if self.graph_cfg.odometry_noise == "hessian":
                target_map = self._map
                info, model = registration_information(
                    res, T_res, self.graph_cfg, lambda: vgicp_correspondences(
                        target_map, scan.cloud, T_res, self.cfg.voxel_resolution, self.cfg.max_correspondence_distance))
            else:
                info, model = sigmas_information(self.graph_cfg.fixed_sigmas), "fixed"
            edge = RegistrationEdge(
                source=k,
                target=k - 1,
                T=T_rel,
                H_raw=H,
                information=info,
                inlier_ratio=float(inlier_ratio),
                error_per_inlier=float(res.error / max(res.num_inliers, 1)),
                iterations=int(res.iterations),
                ok=True,
                info={"covariance": model},
                converged=bool(res.converged),
            )
            self._delta = T_rel
            self._motion_known = True
            self._delta_dt = float(dt) if dt is not None and np.isfinite(dt) and dt > 0.0 else None
        T_new = T_prev @ edge.T
        self.poses.append(T_new)
        self.edges.append(edge)
        self._insert(scan, T_new)
        self._prev = scan
        return edge
