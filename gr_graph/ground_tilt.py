"""The ground-tilt offset: a registration's roll and pitch checked against the ground seen in both scans.

Why. Two scans taken from nearly the same place with the sensor tilted differently (a revisit
with the body pitched by braking, accelerating or loading) sample the world along the same
sensor-frame beams, but at other places. Registration by nearest neighbours (GICP, ICP, VGICP)
is pulled towards the relative attitude at which the two ring patterns coincide, i.e. towards
no relative tilt: in the clean synthetic town, GICP recovers 24-34 % of a pure 0.25-0.5° tilt
between two renders from one spot at 16 channels (95-101 % at 64), and on the full route the
loops' pitch errors follow the relative pitch of the two passes (correlation -0.85 to -0.88 with
the offset below; benchmarks/results/findings.md, "The ground-tilt offset"). The registration's own residuals
cannot show this error (they are smaller at the biased pose than at the true one), so no
residual-based covariance (the Hessian, the cluster-robust sandwich) contains it.

What. The ground under a sensor is a plane in its frame; the same ground patch, seen from the
two scans of an edge, must map onto itself by the edge's rotation. For an edge
``T = T̂_{target,source}`` (source points into the target frame) with ground normals ``n_s``
(source frame) and ``n_t`` (target frame):

    w_t = angle(R n_s, n_t) · axis(R n_s × n_t)       rotation taking R n_s onto n_t (target frame)
    o   = Rᵀ w_t                                       the same rotation in the source frame

``o`` is the correction to the edge's roll and pitch that the ground asks for (the gtsam
between-factor error ``Log(T̂⁻¹ X_t⁻¹ X_s)`` perturbs T̂ on the right, in the source frame). The
edge's covariance is widened by it, rank one in the rotation block::

    Σ' = Σ + v vᵀ,  v = [o, 0, 0, 0]        Λ' = Λ - (Λ v)(Λ v)ᵀ / (1 + vᵀ Λ v)   (Sherman-Morrison)

the same rule for odometry and loop edges, with no factor fitted: an edge whose ground
agrees with its rotation keeps its information, one whose ground disagrees loses it along
the disagreement. ``graph.ground_tilt_offset`` turns it on (``--ground-tilt-offset``).

Ground plane of one scan (:func:`fit_ground_plane`): the points below the sensor in a
horizontal annulus (4-25 m by default), seeded at the 10th percentile of their heights, then
least squares ``z = a x + b y + c`` refitted on the points within a band of the plane, a few
times. The fit is refused (None, counted by :class:`GroundTiltOffsets`; the edges of that scan
keep their information) when too few points support it or they spread too thinly in some
horizontal direction (a strip of ground leaves the tilt across it open). It assumes a sensor mounted
roughly level above the ground, z up (KITTI, most cars); on a sensor tilted by more than a few
degrees the annulus misses the ground and the fit is refused or the offset meaningless.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from collections.abc import Sequence
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: defaults of :func:`fit_ground_plane`
MIN_RANGE_M = 4.0
MAX_RANGE_M = 25.0
BAND_M = 0.15
SEED_BAND_M = 0.5
ITERATIONS = 5
MIN_INLIERS = 50
MIN_SPREAD_M = 2.0


@dataclass(frozen=True)
class GroundPlane:
    """A scan's ground plane ``z = a x + b y + c`` in the sensor frame.

    Attributes
    ----------
    normal : np.ndarray
        ``(3,)`` unit normal, z component positive.
    height : float
        ``c``: the plane's height under the sensor [m] (negative for a sensor above the ground).
    n_inliers : int
        Points within the band of the final plane.
    rms : float
        RMS of their heights about the plane [m].
    """

    normal: np.ndarray
    height: float
    n_inliers: int
    rms: float


def fit_ground_plane(points: np.ndarray, min_range: float = MIN_RANGE_M, max_range: float = MAX_RANGE_M,
                     band: float = BAND_M, iterations: int = ITERATIONS, min_inliers: int = MIN_INLIERS,
                     min_spread: float = MIN_SPREAD_M) -> GroundPlane | None:
    """The ground plane of one scan (sensor frame, z up), or None when the scan does not show one.

    Parameters
    ----------
    points : np.ndarray
        ``(N, 3)`` (or more columns, the first three used) points in the sensor frame.
    min_range, max_range : float
        Horizontal annulus of the candidate points [m].
    band : float
        Points within this height of the plane are refitted, each iteration [m].
    iterations : int
        Refits after the seed.
    min_inliers : int
        Fewer supporting points: None.
    min_spread : float
        The supporting points' horizontal spread (square root of the smaller eigenvalue of their
        x-y covariance) below this: None (a strip of ground on one side leaves the tilt across
        it undetermined) [m].

    Returns
    -------
    GroundPlane or None
    """
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] < 3:
        raise ValueError(f"fit_ground_plane: points must be (N, 3), got {p.shape}")
    p = p[np.isfinite(p[:, :3]).all(axis=1), :3]
    r = np.hypot(p[:, 0], p[:, 1])
    cand = p[(r >= min_range) & (r <= max_range) & (p[:, 2] < 0.0)]
    if len(cand) < min_inliers:
        return None
    z0 = float(np.percentile(cand[:, 2], 10.0))
    inl = cand[np.abs(cand[:, 2] - z0) < SEED_BAND_M]
    coef = np.array([0.0, 0.0, z0])
    for _ in range(iterations + 1):
        if len(inl) < min_inliers:
            return None
        A = np.c_[inl[:, 0], inl[:, 1], np.ones(len(inl))]
        coef = np.linalg.lstsq(A, inl[:, 2], rcond=None)[0]
        resid = cand[:, 2] - (cand[:, :2] @ coef[:2] + coef[2])
        inl = cand[np.abs(resid) < band]
    if len(inl) < min_inliers:
        return None
    xy = inl[:, :2] - inl[:, :2].mean(axis=0)
    if np.sqrt(max(np.linalg.eigvalsh(xy.T @ xy / len(xy))[0], 0.0)) < min_spread:
        return None
    resid = inl[:, 2] - (inl[:, :2] @ coef[:2] + coef[2])
    normal = np.array([-coef[0], -coef[1], 1.0])
    return GroundPlane(normal / np.linalg.norm(normal), float(coef[2]), len(inl), float(np.sqrt(np.mean(resid**2))))


def tilt_offset(T_target_source: np.ndarray, source_normal: np.ndarray, target_normal: np.ndarray) -> np.ndarray:
    """The rotation (source frame, radians, ``[ω_x, ω_y, ω_z]``) that would make the edge's rotation
    map the source's ground normal onto the target's (module docstring)."""
    R = np.asarray(T_target_source, np.float64)[:3, :3]
    a = R @ (np.asarray(source_normal, np.float64) / np.linalg.norm(source_normal))
    b = np.asarray(target_normal, np.float64) / np.linalg.norm(target_normal)
    cross = np.cross(a, b)
    s = np.linalg.norm(cross)
    if s == 0.0:
        return np.zeros(3)
    angle = np.arctan2(s, float(a @ b))
    return R.T @ (angle * cross / s)


def widened_information(information: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``(Λ⁻¹ + v vᵀ)⁻¹`` with ``v = [offset, 0, 0, 0]`` (gtsam order [ω, v]), by Sherman-Morrison:
    exact for any positive definite ``Λ``, without inverting it."""
    info = np.asarray(information, np.float64)
    v = np.zeros(6)
    v[:3] = offset
    u = info @ v
    out = info - np.outer(u, u) / (1.0 + float(v @ u))
    return 0.5 * (out + out.T)


class GroundTiltOffsets:
    """Ground planes of a run's scans and the widening of its registered edges (``graph.ground_tilt_offset``).

    :meth:`widen` on every edge before it enters the graph, with the run's scans (sensor-frame
    points by run position); each scan's plane is fitted once, when an edge first needs it
    (:meth:`forget` drops it when a scan is preprocessed again; edges widened before keep their
    offset). Flagged edges (``ok=False``: a fallback guess with its own weak noise) and edges of a
    scan without a ground plane keep their information and are counted. The residual-based
    calibrations (the learned noise's shared scale, the loops' variance factors) are estimated on
    the informations before the widening (:meth:`restore`), which then widens the calibrated ones
    (:meth:`rewiden`): ``Σ = Σ₀ / s + v vᵀ``, the offset stays in radians.
    """

    def __init__(self) -> None:
        self.planes: dict[int, GroundPlane | None] = {}
        self.widened: list[tuple[Any, np.ndarray, np.ndarray]] = []  # (edge, information before, offset)
        self.n_without_ground = {"odometry": 0, "loop": 0}
        self.n_flagged = 0

    def plane(self, i: int, scans: Sequence[np.ndarray]) -> GroundPlane | None:
        """The ground plane of the scan at run position ``i`` (fitted on first use)."""
        if i not in self.planes:
            self.planes[i] = fit_ground_plane(scans[i]) if len(scans[i]) else None
        return self.planes[i]

    def forget(self, i: int) -> None:
        """Drop scan ``i``'s plane (its points changed)."""
        self.planes.pop(i, None)

    def widen(self, edge: Any, scans: Sequence[np.ndarray]) -> None:
        """Widen ``edge.information`` (a :class:`~gr_graph.odometry.RegistrationEdge`) in place by its
        ground-tilt offset; the offset in degrees goes to ``edge.info["ground_tilt_offset_deg"]``."""
        if not edge.ok:
            self.n_flagged += 1
            return
        source, target = self.plane(edge.source, scans), self.plane(edge.target, scans)
        if source is None or target is None:
            self.n_without_ground[edge.kind] += 1
            return
        o = tilt_offset(edge.T, source.normal, target.normal)
        self.widened.append((edge, np.array(edge.information, np.float64), o))
        edge.information = widened_information(edge.information, o)
        edge.info["ground_tilt_offset_deg"] = np.degrees(o).tolist()

    def restore(self) -> None:
        """Every widened edge back to its information before the widening (for the residual-based
        calibrations, which are estimated without it; :meth:`rewiden` afterwards)."""
        for edge, before, _ in self.widened:
            edge.information = before.copy()

    def rewiden(self) -> None:
        """Widen every edge of :meth:`widen` again, from its information as it is now (calibrated)."""
        for edge, _, o in self.widened:
            edge.information = widened_information(edge.information, o)

    def summary(self) -> dict[str, Any]:
        """For the round summary: scans without a ground plane, edges widened or left, RMS offsets."""
        out: dict[str, Any] = {"n_scans_fitted": len(self.planes),
                               "n_scans_without_ground": sum(p is None for p in self.planes.values()),
                               "n_flagged_edges_left": self.n_flagged}
        for kind in ("odometry", "loop"):
            deg = np.degrees(np.asarray([o for edge, _, o in self.widened if edge.kind == kind]).reshape(-1, 3))
            out[kind] = {"n_widened": len(deg), "n_without_ground": self.n_without_ground[kind],
                         "rms_offset_deg": np.sqrt(np.mean(deg**2, axis=0)).tolist() if len(deg) else None}
        return out
