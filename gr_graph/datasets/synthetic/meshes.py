"""Triangle-mesh primitives for the procedural town (boxes, cylinders, irregular blobs).

Every primitive returns ``(vertices (V, 3) float64, triangles (T, 3) int64)``; a
:class:`MeshBuilder` concatenates them with a per-triangle reflectance (albedo) and a
per-triangle material id. Triangle winding is not relied on (intensity uses ``|cos|``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

# Material ids (index into MATERIAL_NAMES); reflectance is stored per triangle separately.
MATERIAL_NAMES = ("road", "sidewalk", "terrain", "building", "wall", "pole", "trunk",
                  "foliage", "car", "glass", "person")
MATERIAL = {name: i for i, name in enumerate(MATERIAL_NAMES)}


def box(cx: float, cy: float, yaw: float, length: float, width: float,
        z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """An oriented box without its bottom face: ``length`` along ``yaw``, ``width`` across."""
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = 0.5 * length, 0.5 * width
    local = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])
    xy = local @ np.array([[c, s], [-s, c]]) + (cx, cy)
    v = np.concatenate([np.c_[xy, np.full(4, z0)], np.c_[xy, np.full(4, z1)]])
    t = np.array([
        [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6],
        [3, 0, 4], [3, 4, 7], [4, 5, 6], [4, 6, 7],
    ])
    return v, t


def cylinder(cx: float, cy: float, radius: float, z0: float, z1: float,
             n_seg: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A vertical capped cylinder (prism with ``n_seg`` sides)."""
    a = np.linspace(0.0, 2 * np.pi, n_seg, endpoint=False)
    ring = np.c_[cx + radius * np.cos(a), cy + radius * np.sin(a)]
    v = np.concatenate([np.c_[ring, np.full(n_seg, z0)], np.c_[ring, np.full(n_seg, z1)],
                        [[cx, cy, z1]]])
    i = np.arange(n_seg)
    j = (i + 1) % n_seg
    side = np.concatenate([np.c_[i, j, j + n_seg], np.c_[i, j + n_seg, i + n_seg]])
    cap = np.c_[i + n_seg, j + n_seg, np.full(n_seg, 2 * n_seg)]
    return v, np.concatenate([side, cap])


@lru_cache(maxsize=4)
def unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere (read-only arrays): 20·4^subdivisions triangles."""
    p = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p],
                  [0, -1, -p], [0, 1, -p], [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]],
                 dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)  # midpoints of edges (01, 12, 20) per face
        v = np.concatenate([v, mid])
        f = np.concatenate([np.c_[f[:, 0], m[:, 0], m[:, 2]], np.c_[f[:, 1], m[:, 1], m[:, 0]],
                            np.c_[f[:, 2], m[:, 2], m[:, 1]], m])
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def blob(center: np.ndarray, radii: np.ndarray, rng: np.random.Generator,
         subdivisions: int = 2, roughness: float = 0.18) -> tuple[np.ndarray, np.ndarray]:
    """An irregular closed blob (tree crown, bush): a deformed, scaled icosphere.

    The radius is modulated by a few random smooth lobes, so no two blobs look alike.
    """
    u, f = unit_icosphere(subdivisions)
    dirs = rng.normal(size=(5, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    freq = rng.uniform(1.5, 4.0, size=5)
    phase = rng.uniform(0, 2 * np.pi, size=5)
    amp = rng.uniform(0.3, 1.0, size=5) * roughness / 2.0
    mod = 1.0 + (amp * np.cos((u @ dirs.T) * freq + phase)).sum(axis=1)
    return u * mod[:, None] * radii + center, f.copy()


class MeshBuilder:
    """Accumulates triangle soups with a reflectance and material per triangle."""

    def __init__(self) -> None:
        self._v: list[np.ndarray] = []
        self._t: list[np.ndarray] = []
        self._albedo: list[np.ndarray] = []
        self._material: list[np.ndarray] = []
        self._nv = 0

    def add(self, mesh: tuple[np.ndarray, np.ndarray], albedo: float | np.ndarray,
            material: int | np.ndarray) -> None:
        """Append a mesh; ``albedo``/``material`` are scalars or per-triangle arrays."""
        v, t = mesh
        self._v.append(np.asarray(v, dtype=np.float64))
        self._t.append(np.asarray(t, dtype=np.int64) + self._nv)
        self._albedo.append(np.broadcast_to(np.asarray(albedo, np.float32), (len(t),)))
        self._material.append(np.broadcast_to(np.asarray(material, np.uint8), (len(t),)))
        self._nv += len(v)

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Return ``(vertices float64, triangles uint32, albedo float32, material uint8)``."""
        if not self._v:
            return (np.zeros((0, 3)), np.zeros((0, 3), np.uint32), np.zeros(0, np.float32),
                    np.zeros(0, np.uint8))
        return (np.concatenate(self._v), np.concatenate(self._t).astype(np.uint32),
                np.concatenate(self._albedo), np.concatenate(self._material))


def leaf_cloud(points: np.ndarray, size: float | np.ndarray,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Small randomly oriented triangles (leaf clusters, twigs) centred on ``points`` ``(N, 3)``.

    Each element is an equilateral triangle of side ``size`` (m, scalar or ``(N,)``) in a
    uniformly random plane: ``N`` triangles, ``3 N`` vertices. A crown made of such elements
    is porous: a ray travels a random free path between them (see ``town`` for the density).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    normal = rng.normal(size=(n, 3))
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normal, u)
    spin = rng.uniform(0.0, 2 * np.pi, n)[:, None]
    e1 = np.cos(spin) * u + np.sin(spin) * v
    e2 = np.cross(normal, e1)
    r = (np.broadcast_to(np.asarray(size, np.float64), (n,)) / np.sqrt(3.0))[:, None]  # circumradius
    verts = np.empty((n, 3, 3))
    for k, ang in enumerate((0.0, 2 * np.pi / 3, 4 * np.pi / 3)):
        verts[:, k] = points + r * (np.cos(ang) * e1 + np.sin(ang) * e2)
    return verts.reshape(-1, 3), np.arange(3 * n).reshape(n, 3)


def gable_roof(cx: float, cy: float, yaw: float, length: float, width: float, z0: float,
               ridge_height: float, overhang: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A gable roof (triangular prism, ridge along ``yaw``) on a ``length`` x ``width`` block.

    The eaves overhang the walls by ``overhang`` on every side (at height ``z0``).
    """
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = 0.5 * length + overhang, 0.5 * width + overhang
    local = np.array([[-hl, -hw, z0], [hl, -hw, z0], [hl, hw, z0], [-hl, hw, z0],
                      [-hl, 0.0, z0 + ridge_height], [hl, 0.0, z0 + ridge_height]])
    xy = local[:, :2] @ np.array([[c, s], [-s, c]]) + (cx, cy)
    v = np.c_[xy, local[:, 2]]
    t = np.array([[0, 1, 5], [0, 5, 4], [3, 2, 5], [3, 5, 4], [0, 4, 3], [1, 2, 5],
                  [0, 1, 2], [0, 2, 3]])  # two slopes, two gables, the soffit
    return v, t


def _loft(sections: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mesh through closed cross-sections ``(S, P, 3)`` (quads between them, fans at the ends)."""
    n_s, n_p, _ = sections.shape
    v = sections.reshape(-1, 3)
    i = np.arange(n_p)
    j = (i + 1) % n_p
    tris = []
    for a in range(n_s - 1):
        o0, o1 = a * n_p, (a + 1) * n_p
        tris.append(np.c_[o0 + i, o0 + j, o1 + j])
        tris.append(np.c_[o0 + i, o1 + j, o1 + i])
    centres = sections.mean(axis=1)
    v = np.concatenate([v, centres[[0, -1]]])
    tris.append(np.c_[i, j, np.full(n_p, len(v) - 2)])
    tris.append(np.c_[(n_s - 1) * n_p + i, (n_s - 1) * n_p + j, np.full(n_p, len(v) - 1)])
    return v, np.concatenate(tris)


def car_mesh(length: float, width: float, height: float, clearance: float,
             rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A passenger car with a curved body in its own frame (x forward, z up, ground at z = 0).

    A loft of 13 cross-sections: rounded bumpers and plan shape, a hood rising to a raked
    windscreen, a roof, a sloping rear window and a trunk; the greenhouse (windows) is
    narrower than the body (tumblehome); four wheels (8-sided) under the body. Typical
    dimensions (compact to mid-size cars): length 3.8-4.9 m, width 1.7-1.95 m, height
    1.4-1.55 m, ground clearance 0.14-0.2 m.

    Returns ``(vertices, triangles, is_glass (T,) bool)``.
    """
    r = rng if rng is not None else np.random.default_rng(0)
    hl, hw = 0.5 * length, 0.5 * width
    belt = clearance + r.uniform(0.55, 0.65) * (height - clearance)
    xs = hl * np.array([-1.0, -0.97, -0.9, -0.75, -0.55, -0.3, 0.0, 0.2, 0.35, 0.5, 0.75, 0.93, 1.0])
    # roof line over x: trunk, rear window, roof, windscreen, hood, bumper (fractions of length)
    roof = np.interp(xs / hl, [-1.0, -0.9, -0.72, -0.5, 0.1, 0.38, 0.55, 1.0],
                     [belt - 0.12, belt + 0.02, belt + 0.05, height, height, belt + 0.08, belt + 0.03,
                      belt - 0.1])
    plan = np.sqrt(np.clip(1.0 - (np.maximum(np.abs(xs) / hl - 0.8, 0.0) / 0.2) ** 2, 0.15, 1.0))
    sections = []
    for x, top, p in zip(xs, roof, plan):
        w = hw * p
        upper = top > belt + 0.06
        wg = w - (0.18 if upper else 0.05)
        z_top = max(top, clearance + 0.25)
        yz = [(-0.85 * w, clearance), (-w, clearance + 0.25), (-w, min(belt, z_top - 0.02)),
              (-wg, z_top - 0.02), (-0.75 * wg, z_top), (0.75 * wg, z_top), (wg, z_top - 0.02),
              (w, min(belt, z_top - 0.02)), (w, clearance + 0.25), (0.85 * w, clearance)]
        sections.append([(x, y, z) for y, z in yz])
    v, t = _loft(np.asarray(sections))
    centroid = v[t].mean(axis=1)
    cab = (centroid[:, 2] > belt + 0.03) & (centroid[:, 2] < height - 0.04)
    wheels_v, wheels_t = [v], [t]
    n_v = len(v)
    rw = min(0.33, clearance + 0.17)
    for wx in (0.68 * hl, -0.66 * hl):
        for wy in (-hw + 0.12, hw - 0.12):
            a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
            ring = np.c_[wx + rw * np.cos(a), np.zeros(8), rw + rw * np.sin(a)]
            wv = np.concatenate([ring + (0, wy - 0.1, 0), ring + (0, wy + 0.1, 0)])
            i = np.arange(8)
            j = (i + 1) % 8
            wt = np.concatenate([np.c_[i, j, j + 8], np.c_[i, j + 8, i + 8],
                                 np.c_[np.zeros(6, int), i[1:7], i[2:8]],
                                 np.c_[np.full(6, 8), i[1:7] + 8, i[2:8] + 8]])
            wheels_v.append(wv)
            wheels_t.append(wt + n_v)
            n_v += len(wv)
    tris = np.concatenate(wheels_t)
    glass = np.concatenate([cab, np.zeros(len(tris) - len(t), bool)])
    return np.concatenate(wheels_v), tris, glass


def pedestrian_mesh(height: float, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A standing/walking person in their own frame (x forward, z up, feet at z = 0).

    A loft of elliptical cross-sections (legs as one section 0.3 x 0.2 m, hips, torso
    0.45 x 0.25 m at the shoulders, neck, head 0.2 m): adult stature 1.55-1.90 m.
    """
    r = rng if rng is not None else np.random.default_rng(0)
    s = height / 1.75
    build = r.uniform(0.9, 1.15)
    # (z fraction of height, half width across, half depth forward)
    prof = [(0.0, 0.13, 0.12), (0.05, 0.15, 0.09), (0.45, 0.17, 0.10), (0.55, 0.19, 0.12),
            (0.72, 0.21, 0.12), (0.81, 0.23, 0.12), (0.85, 0.06, 0.06), (0.88, 0.09, 0.1),
            (0.95, 0.095, 0.105), (1.0, 0.04, 0.05)]
    a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    sections = [np.c_[d * build * s * np.cos(a), w * build * s * np.sin(a), np.full(8, z * height)]
                for z, w, d in prof]
    return _loft(np.asarray(sections))


def rod(p0: np.ndarray, p1: np.ndarray, radius: float, n_seg: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """An open prism of ``n_seg`` sides and ``radius`` from ``p0`` to ``p1`` (a branch, a rail)."""
    p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    axis = p1 - p0
    axis /= max(np.linalg.norm(axis), 1e-12)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    a = np.linspace(0, 2 * np.pi, n_seg, endpoint=False)
    ring = radius * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * w)
    v = np.concatenate([ring + p0, ring + p1])
    i = np.arange(n_seg)
    j = (i + 1) % n_seg
    return v, np.concatenate([np.c_[i, j, j + n_seg], np.c_[i, j + n_seg, i + n_seg]])
