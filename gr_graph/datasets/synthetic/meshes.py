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
                  "foliage", "car", "glass")
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
