"""Small ray-cast scenes with known geometry and known sensor noise (tests and benchmarks).

A scene is a set of analytic surfaces in the world frame: planes and vertical cylinders. A
spinning LiDAR with ``n_rings`` beams (elevations evenly spread between ``elev_max`` and
``elev_min`` degrees, like a channel-subsampled HDL-64E) and ``n_azimuth`` steps per turn is
ray cast against them; every hit is displaced along the *true surface normal* by
``N(0, sigma_normal^2)``. Hence the true local covariance of a point has its smallest
eigenvector along the returned normal with variance ``sigma_normal^2`` (the paper's C_q;
a correspondence residual then has normal variance ``2 sigma_normal^2``).

:func:`make_memory` renders a drive and builds a ``gr_graph.memory.Memory`` whose edges carry
the true relative poses and nearest-neighbour correspondences found with them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from gr_graph.memory import EDGE_LOOP, EDGE_ODOMETRY, Memory

__all__ = [
    "Plane", "Cylinder", "Scene", "street_scene", "render_scan", "correspondences", "make_memory", "pose_xy_yaw",
    "random_street_poses", "pca_covariances", "normal_angles_deg", "LearningProblem", "street_learning_problem",
]


@dataclass
class Plane:
    """Infinite plane ``n . x = offset`` (world frame, ``n`` unit)."""

    normal: np.ndarray
    offset: float


@dataclass
class Cylinder:
    """Vertical cylinder of ``radius`` around the axis through ``(cx, cy)``, for ``z`` in ``[z0, z1]``."""

    cx: float
    cy: float
    radius: float
    z0: float = -10.0
    z1: float = 10.0


@dataclass
class Scene:
    """Planes and cylinders."""

    planes: list[Plane] = field(default_factory=list)
    cylinders: list[Cylinder] = field(default_factory=list)


def street_scene(length: float = 60.0, half_width: float = 7.0, pole_spacing: float = 6.0, seed: int = 0,
                 radius_range: tuple[float, float] = (0.15, 0.6)) -> Scene:
    """Ground ``z = 0``, two walls ``y = +-half_width`` and vertical cylinders (poles, trunks,
    columns of radius in ``radius_range``) along both kerbs."""
    rng = np.random.default_rng(seed)
    planes = [
        Plane(np.array([0.0, 0.0, 1.0]), 0.0),
        Plane(np.array([0.0, 1.0, 0.0]), half_width),
        Plane(np.array([0.0, -1.0, 0.0]), half_width),
    ]
    cyl = []
    for x in np.arange(-length / 2, length / 2, pole_spacing):
        for side in (-1, 1):
            r = float(rng.uniform(*radius_range))
            cyl.append(Cylinder(float(x + rng.uniform(-1.5, 1.5)), side * (half_width - 1.5 - rng.uniform(0, 1.0)), r, 0.0, float(rng.uniform(2.5, 6.0))))
    return Scene(planes, cyl)


def pose_xy_yaw(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    """``T_w_s`` (4x4) of a sensor at ``(x, y, z)`` with heading ``yaw`` (rad)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, z]
    return T


def render_scan(
    scene: Scene,
    T_w_s: np.ndarray,
    rng: np.random.Generator,
    n_rings: int = 16,
    n_azimuth: int = 720,
    elev_max: float = 2.0,
    elev_min: float = -24.8,
    sigma_normal: float = 0.02,
    max_range: float = 50.0,
    return_ids: bool = False,
) -> tuple[np.ndarray, ...]:
    """Ray cast one scan; returns points and true unit normals, both ``(N, 3)`` in the sensor frame.

    With ``return_ids`` also the ``(N,)`` index of the surface hit: planes ``0..P-1`` (in
    ``scene.planes`` order), then cylinders ``P..``.
    """
    el = np.deg2rad(np.linspace(elev_max, elev_min, n_rings))
    az = np.arange(n_azimuth) * (2 * np.pi / n_azimuth) + rng.uniform(0, 2 * np.pi / n_azimuth)
    E, A = np.meshgrid(el, az, indexing="ij")
    u = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    R, o = T_w_s[:3, :3], T_w_s[:3, 3]
    dw = u @ R.T
    best = np.full(len(u), np.inf)
    nrm = np.zeros_like(u)
    ids = np.full(len(u), -1)
    for pid, pl in enumerate(scene.planes):
        den = dw @ pl.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (pl.offset - o @ pl.normal) / den
        ok = (t > 0.1) & (t < best) & np.isfinite(t)
        best[ok] = t[ok]
        nrm[ok] = pl.normal * (-np.sign(den[ok]))[:, None]  # facing the sensor
        ids[ok] = pid
    for cid, cy in enumerate(scene.cylinders):
        ox, oy = o[0] - cy.cx, o[1] - cy.cy
        a = dw[:, 0] ** 2 + dw[:, 1] ** 2
        b = 2 * (ox * dw[:, 0] + oy * dw[:, 1])
        c = ox**2 + oy**2 - cy.radius**2
        disc = b * b - 4 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(disc)) / (2 * a)
        z = o[2] + t * dw[:, 2]
        ok = (disc > 0) & (t > 0.1) & (t < best) & (z >= cy.z0) & (z <= cy.z1)
        best[ok] = t[ok]
        hit = o + t[ok, None] * dw[ok]
        n = np.stack([hit[:, 0] - cy.cx, hit[:, 1] - cy.cy, np.zeros(len(hit))], -1) / cy.radius
        nrm[ok] = n
        ids[ok] = len(scene.planes) + cid
    hit_mask = best < max_range
    xw = o + best[hit_mask, None] * dw[hit_mask]
    nw = nrm[hit_mask]
    xw = xw + rng.normal(0.0, sigma_normal, len(xw))[:, None] * nw
    pts = (xw - o) @ R
    ns = nw @ R
    if return_ids:
        return pts, ns, ids[hit_mask]
    return pts, ns


def correspondences(P: np.ndarray, Q: np.ndarray, T_qp: np.ndarray, n_max: int, max_dist: float, rng: np.random.Generator) -> np.ndarray:
    """Nearest-neighbour pairs ``(i, j)``: ``T_qp p_i``'s nearest ``q_j`` within ``max_dist``."""
    idx = rng.choice(len(P), min(n_max, len(P)), replace=False)
    pq = P[idx] @ T_qp[:3, :3].T + T_qp[:3, 3]
    d, j = cKDTree(Q).query(pq, k=1)
    ok = d < max_dist
    return np.stack([idx[ok], j[ok]], 1).astype(np.int32)


def make_memory(
    scene: Scene,
    poses: list[np.ndarray],
    edges: list[tuple[int, int]],
    seed: int = 0,
    n_corr: int = 2000,
    max_dist: float = 1.0,
    pose_noise: tuple[float, float] = (0.0, 0.0),
    **render_kw,
) -> tuple[Memory, list[np.ndarray]]:
    """Render ``poses`` (``T_w_s``), build edges with true ``T̂_kl`` (optionally perturbed).

    Returns the memory and the per-scan true normals (sensor frame).
    ``pose_noise = (rot_std_rad, trans_std_m)`` perturbs each ``T̂_kl`` on the right.
    """
    rng = np.random.default_rng(seed)
    scans, normals = [], []
    for T in poses:
        p, n = render_scan(scene, T, rng, **render_kw)
        scans.append(p)
        normals.append(n)
    eT, eH, corr, kinds = [], [], [], []
    for k, l in edges:
        T_lk = np.linalg.inv(poses[l]) @ poses[k]
        corr.append(correspondences(scans[k], scans[l], T_lk, n_corr, max_dist, rng))
        if pose_noise[0] > 0 or pose_noise[1] > 0:
            from scipy.spatial.transform import Rotation

            dT = np.eye(4)
            dT[:3, :3] = Rotation.from_rotvec(rng.normal(0, pose_noise[0], 3)).as_matrix()
            dT[:3, 3] = rng.normal(0, pose_noise[1], 3)
            T_lk = T_lk @ dT
        eT.append(T_lk)
        eH.append(np.eye(6) * 1e4)
        kinds.append(EDGE_ODOMETRY if l == k + 1 else EDGE_LOOP)
    mem = Memory.from_scans(scans, np.stack(poses), edges, kinds, eT, eH, corr, info={"toy_scene": True})
    return mem, normals


def random_street_poses(rng: np.random.Generator, xs: list[float]) -> list[np.ndarray]:
    """Sensor poses along a street at positions ``xs``: lateral +-1 m, height 1.73 +- 0.15 m,
    yaw +-0.2 rad and roll/pitch +-0.03 rad drawn from ``rng`` (in that order, per pose)."""
    from scipy.spatial.transform import Rotation

    out = []
    for x in xs:
        T = pose_xy_yaw(x, rng.uniform(-1, 1), 1.73 + rng.uniform(-0.15, 0.15), rng.uniform(-0.2, 0.2))
        T[:3, :3] = T[:3, :3] @ Rotation.from_euler("xy", rng.uniform(-0.03, 0.03, 2)).as_matrix()
        out.append(T)
    return out


def pca_covariances(points: np.ndarray, k: int = 16) -> np.ndarray:
    """``(N, 3, 3)`` sample covariance of each point's ``k`` nearest neighbours (the hand-crafted
    estimate the learned covariances are compared with)."""
    _, j = cKDTree(points).query(points, k=k)
    nb = points[j]
    c = nb - nb.mean(1, keepdims=True)
    return np.einsum("nki,nkj->nij", c, c) / (k - 1)


def normal_angles_deg(C: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle (deg) between each covariance's smallest eigenvector and the true normal, and the
    ``(N, 3)`` ascending eigenvalues."""
    w, v = np.linalg.eigh(C)
    return np.degrees(np.arccos(np.clip(np.abs((v[:, :, 0] * normals).sum(1)), 0, 1))), w


@dataclass(frozen=True)
class LearningProblem:
    """A self-supervised learning problem with known answers (see :func:`street_learning_problem`).

    ``memory`` holds the training scans and pairs; ``points``, ``normals`` and ``ids``
    (surface index: planes first, ``ids < n_planes``) describe a held-out scan.
    """

    scene: Scene
    memory: Memory
    edges: list[tuple[int, int]]
    points: np.ndarray
    normals: np.ndarray
    ids: np.ndarray
    sigma: float

    @property
    def n_planes(self) -> int:
        return len(self.scene.planes)


def street_learning_problem(sigma: float = 0.02, n_azimuth: int = 720) -> LearningProblem:
    """The 16-channel street used to show what f_theta learns (tests and benchmark share it).

    Ground, two walls and cylinders of radius 0.3-1 m; 6 training scans from random street
    poses, 9 pairs (k, k+1) and (k, k+2) with true T̂ and 1,500 nearest-neighbour
    correspondences each; one held-out scan from a new pose. Normal noise ``sigma``.
    """
    scene = street_scene(seed=1, radius_range=(0.3, 1.0))
    rng = np.random.default_rng(11)
    poses = random_street_poses(rng, [k - 3.0 for k in range(6)])
    edges = [(k, k + 1) for k in range(5)] + [(k, k + 2) for k in range(4)]
    mem, _ = make_memory(scene, poses, edges, seed=0, n_corr=1500, max_dist=1.0, sigma_normal=sigma,
                         n_azimuth=n_azimuth)
    pts, nrm, ids = render_scan(scene, random_street_poses(rng, [0.5])[0], np.random.default_rng(5),
                                sigma_normal=sigma, n_azimuth=n_azimuth, return_ids=True)
    return LearningProblem(scene, mem, edges, pts, nrm, ids, sigma)
