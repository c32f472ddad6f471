"""Where does the thickness of real KITTI scans come from? (not a test)

Breaks the statistics of :mod:`gr_graph.datasets.realism` down by local class, height above
the sensor and range band, for the real KITTI 00 frames and for synthetic frames, and prints
Markdown tables.

Classes of each downsampled point (from its 10-neighbour PCA): ``ground`` (normal within
25 deg of vertical and more than 1.2 m below the sensor), ``vertical`` (normal within 25 deg
of horizontal: facades, walls, car sides, trunks), ``other`` (the rest: vegetation, clutter,
edges, roofs).

Run::

    python benchmarks/realism_diagnosis.py [--frames 12] [--preset kitti] [--world kitti]

(``--world residential``: the world before the kitti world, ``TownConfig.residential()`` and the
moving actors.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from gr_graph.datasets.realism import NEIGHBOURS, downsample


def point_table(ds: np.ndarray) -> dict[str, np.ndarray]:
    _, idx = cKDTree(ds).query(ds, k=NEIGHBOURS)
    nb = ds[idx]
    c = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", c, c) / NEIGHBOURS
    ev, evec = np.linalg.eigh(cov)
    ev = np.maximum(ev, 0.0)
    nz = np.abs(evec[:, 2, 0])
    cls = np.full(len(ds), 2)
    cls[(nz > np.cos(np.radians(25))) & (ds[:, 2] < -1.2)] = 0
    cls[nz < np.sin(np.radians(25))] = 1
    return {"thick": 100 * np.sqrt(ev[:, 0]), "aniso": 1 - ev[:, 0] / np.maximum(ev[:, 2], 1e-300),
            "cls": cls, "z": ds[:, 2], "r": np.linalg.norm(ds[:, :2], axis=1)}


def summarise(tables: list[dict[str, np.ndarray]]) -> dict[str, dict[str, float]]:
    t = {k: np.concatenate([x[k] for x in tables]) for k in tables[0]}
    n = len(t["thick"])
    out = {}
    groups = {"all": np.ones(n, bool)}
    for i, name in enumerate(("ground", "vertical", "other")):
        groups[name] = t["cls"] == i
    for lo, hi in ((0, 10), (10, 20), (20, 40), (40, 100)):
        groups[f"range {lo}-{hi} m"] = (t["r"] >= lo) & (t["r"] < hi)
    for lo, hi in ((-9, -1.2), (-1.2, 0.5), (0.5, 3), (3, 99)):
        groups[f"z {lo}..{hi} m"] = (t["z"] >= lo) & (t["z"] < hi)
    for lo, hi in ((0, 10), (10, 20), (20, 40)):
        groups[f"ground, range {lo}-{hi} m"] = (t["cls"] == 0) & (t["r"] >= lo) & (t["r"] < hi)
    for name, m in groups.items():
        out[name] = {"share": m.mean(), "thick_med": float(np.median(t["thick"][m])) if m.any() else np.nan,
                     "a90": float(np.mean(t["aniso"][m] > 0.9)) if m.any() else np.nan,
                     "a99": float(np.mean(t["aniso"][m] > 0.99)) if m.any() else np.nan}
    return out


def real_tables(root: Path) -> list[dict[str, np.ndarray]]:
    files = sorted((root / "sequences" / "00" / "velodyne").glob("*.bin"))
    return [point_table(downsample(np.fromfile(f, np.float32).reshape(-1, 4)[:, :3].astype(np.float64)))
            for f in files]


def synthetic_tables(frames: int, preset: str, world: str) -> list[dict[str, np.ndarray]]:
    from gr_graph.datasets.synthetic import SyntheticSequence

    seq = SyntheticSequence(seed=0, nthreads=1, preset=preset, world=world)
    idx = np.round(np.linspace(0, len(seq) - 2, frames)).astype(int)
    return [point_table(downsample(seq[int(i)].points)) for i in idx]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--preset", default="kitti")
    ap.add_argument("--world", default="kitti", choices=("clean", "residential", "kitti"))
    ap.add_argument("--real", type=Path, default=Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "kitti")
    args = ap.parse_args()
    cols = {"real KITTI 00": summarise(real_tables(args.real)),
            f"synthetic {args.preset}/{args.world}": summarise(synthetic_tables(args.frames, args.preset, args.world))}
    names = list(cols)
    print("| group | " + " | ".join(f"{n}: share / thick cm / a90 / a99" for n in names) + " |")
    print("|---|" + "---|" * len(names))
    for g in cols[names[0]]:
        cells = [f"{c[g]['share']:.2f} / {c[g]['thick_med']:.2f} / {c[g]['a90']:.2f} / {c[g]['a99']:.2f}"
                 for c in cols.values()]
        print(f"| {g} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
