"""Pictures of the synthetic sequence: ``python -m gr_graph.datasets.synthetic.plots``.

Writes ``docs/images/synthetic_scan.png`` (a rendered 64-ring scan and its 16-ring
subsample: bird's-eye views and range images) and ``docs/images/synthetic_town.png`` (the
town around the generated route from above, with a zoom showing a scan in place).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from gr_graph.atomic import atomic_savefig
from gr_graph.cli_common import add_log_level, add_out, add_seed, make_parser, setup_logging
from gr_graph.datasets.synthetic.sequence import SyntheticSequence

log = logging.getLogger(__name__)
DEFAULT_OUT = Path(__file__).resolve().parents[3] / "docs" / "images"


def _range_image(frame, n_az: int) -> np.ndarray:
    img = np.full((frame.n_rings, n_az), np.nan)
    az = np.mod(np.arctan2(frame.points[:, 1], frame.points[:, 0]), 2 * np.pi)
    col = np.minimum((az / (2 * np.pi) * n_az).astype(int), n_az - 1)
    img[frame.ring, col] = np.linalg.norm(frame.points, axis=1)
    return img


def plot_scan(out: Path, index: int = 1000, seed: int = 0) -> Path:
    """Figure of frame ``index`` at 64 rings and its 16-ring subsample."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seqs = [SyntheticSequence(seed=seed, n_rings=n) for n in (64, 16)]
    frames = [s[index] for s in seqs]
    fig = plt.figure(figsize=(13, 9.5))
    gs = fig.add_gridspec(3, 2, height_ratios=[3.2, 0.7, 0.7])
    for col, (s, f) in enumerate(zip(seqs, frames)):
        ax = fig.add_subplot(gs[0, col])
        m = np.flatnonzero((np.abs(f.points[:, 0]) < 45) & (np.abs(f.points[:, 1]) < 45))
        m = m[np.argsort(f.points[m, 2])]  # draw high points last
        sc = ax.scatter(f.points[m, 0], f.points[m, 1], c=f.points[m, 2], s=0.15 if col == 0 else 0.5,
                        cmap="viridis", vmin=-2.0, vmax=6.0, rasterized=True)
        ax.set_aspect("equal")
        ax.set_xlim(-45, 45)
        ax.set_ylim(-45, 45)
        ax.set_title(f"{s.n_rings} rings: {len(f):,} points (frame {index}, seed {seed})")
        ax.set_xlabel("x [m] (forward)")
        ax.set_ylabel("y [m]")
    fig.colorbar(sc, ax=fig.axes[:2], label="z [m] (LiDAR frame)", shrink=0.8)
    for row, (s, f) in enumerate(zip(seqs, frames), start=1):
        ax = fig.add_subplot(gs[row, :])
        img = _range_image(f, s.beams.n_azimuth)
        ax.imshow(img, aspect="auto", cmap="turbo", vmin=0, vmax=60, interpolation="nearest",
                  extent=(0, 360, s.n_rings - 0.5, -0.5))
        ax.set_ylabel(f"ring ({s.n_rings})")
        ax.set_title(f"range image, {s.n_rings} rings (ring 0 = +2.0°, last = -24.9°; "
                     "colour = range 0-60 m, white = no return)", fontsize=9)
    ax.set_xlabel("azimuth [deg] (counter-clockwise from forward)")
    path = out / "synthetic_scan.png"
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


def plot_town(out: Path, index: int = 1000, seed: int = 0) -> Path:
    """Figure of the town around the trajectory, with a zoom around frame ``index``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PatchCollection, PolyCollection
    from matplotlib.patches import Circle

    seq = SyntheticSequence(seed=seed)
    town = seq.town
    traj = seq.gt_poses[:, :3, 3]
    frame = seq[index]
    T = seq.gt_poses[index]
    pw = frame.points @ T[:3, :3].T + T[:3, 3]
    fig, axes = plt.subplots(1, 2, figsize=(16, 8.2))
    g = town.ground_grid
    for k, ax in enumerate(axes):
        ax.imshow(g["z"].T, origin="lower", cmap="gist_earth", alpha=0.55,
                  extent=(g["x"][0], g["x"][-1], g["y"][0], g["y"][-1]))
        fp = town.footprints
        ax.add_collection(PolyCollection(fp["building"], facecolor="0.45", edgecolor="0.2", lw=0.4))
        ax.add_collection(PolyCollection(fp["wall"], facecolor="0.1", edgecolor="0.1", lw=0.6))
        ax.add_collection(PolyCollection(fp["car"], facecolor="tab:blue", edgecolor="navy", lw=0.3))
        for kind, colour in (("tree", "forestgreen"), ("bush", "yellowgreen"), ("pole", "k")):
            circles = [Circle((x, y), max(r, 0.4)) for x, y, r in fp[kind]]
            ax.add_collection(PatchCollection(circles, facecolor=colour, edgecolor="none", alpha=0.8))
        ax.plot(traj[:, 0], traj[:, 1], color="red", lw=0.8 if k == 0 else 1.5, label="route")
        ax.plot(*traj[0, :2], "o", color="red", ms=6)
        route = seq.path.route
        if route is not None and k == 0:
            for n, r in enumerate(route.revisits):
                a, b = r.frames
                ax.plot(traj[a:b, 0], traj[a:b, 1], lw=3.5, alpha=0.6,
                        color="orange" if r.direction == "same" else "deepskyblue",
                        label=(f"driven again ({r.direction} direction)" if n == [
                            q.direction for q in route.revisits].index(r.direction) else None))
            for n, st in enumerate(route.stops):
                ax.plot(*traj[st.frames[0], :2], "s", color="k", ms=6,
                        label="stop (10 s or more)" if n == 0 else None)
            ax.legend(loc="lower left", fontsize=8)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    c = traj[index, :2]
    axes[1].scatter(pw[:, 0], pw[:, 1], s=0.05, c="magenta", alpha=0.5, rasterized=True,
                    label=f"scan {index} (64 rings)")
    axes[1].set_xlim(c[0] - 70, c[0] + 70)
    axes[1].set_ylim(c[1] - 70, c[1] + 70)
    axes[1].legend(loc="upper right", markerscale=40)
    axes[0].add_patch(plt.Rectangle((c[0] - 70, c[1] - 70), 140, 140, fill=False, ec="magenta", lw=1.5))
    axes[0].set_xlim(g["x"][0] + 100, g["x"][-1] - 100)
    axes[0].set_ylim(g["y"][0] + 100, g["y"][-1] - 100)
    n = {k: len(v) for k, v in town.footprints.items()}
    axes[0].set_title(f"procedural town (seed {seed}) around the generated route: {n['building']} buildings, "
                      f"{n['tree']} trees, {n['car']} cars, {len(town.triangles) / 1e6:.2f} M triangles",
                      fontsize=10)
    axes[1].set_title(f"zoom around frame {index}: buildings (grey), walls (black), trees, bushes, "
                      "poles, parked cars (blue)", fontsize=10)
    fig.tight_layout()
    path = out / "synthetic_town.png"
    atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


EXAMPLES = (
    "python -m gr_graph.datasets.synthetic.plots",
    "python -m gr_graph.datasets.synthetic.plots --out /tmp/pictures --frame 2000 --seed 1",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m gr_graph.datasets.synthetic.plots``."""
    ap = make_parser("python -m gr_graph.datasets.synthetic.plots", __doc__, EXAMPLES)
    add_out(ap, "output folder (default: docs/images of the repository)")
    ap.add_argument("--frame", type=int, default=1000, metavar="K", help="frame shown")
    add_seed(ap, "seed of the town and the noise")
    add_log_level(ap)
    return ap


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level)
    out = DEFAULT_OUT if args.out is None else Path(args.out)
    for p in (plot_scan(out, args.frame, args.seed), plot_town(out, args.frame, args.seed)):
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
