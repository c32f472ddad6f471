"""What covariance the correspondence NLL asks for, by surface orientation (not a test).

The trainer fits each target point's covariance ``C`` to the residuals ``d = q_j - T̂_kl p_i`` of
the memory's nearest-neighbour correspondences (``training.losses``). This reads a round-0 memory,
pools the residuals of sampled edges in a local frame of their target point (its PCA normal ``n``,
the horizontal direction ``t`` in the surface, and ``b = n x t``), per surface orientation of the
target point (``gr_graph.densify.surface_orientation`` of the PCA covariance of its
``preprocess.num_neighbors`` nearest neighbours in the stored scan), and reports:

* the residuals' root-mean-square spread per axis, ``sqrt(E[d_a^2] / 2)``: what a Gaussian NLL
  fits (the ``/2``: the loss's ``2C``), and the eigenvalue ratio ``l_min / l_max`` of ``E[d d^T]``;
* their robust spread per axis (``1.4826 median |d_a| / sqrt(2)``) and the share of heavy tails;
* per trained network given (``LABEL=model.pt``), the median of its covariances' spread along the
  same axes, their median ``l_min / l_max`` and the share that passes the anisotropy filter
  (``1 - l_min / l_max > training.tau_ani``).

Run::

    python benchmarks/correspondence_residuals_study.py RUN [RUN ...] [--model LABEL=PATH ...] [--edges 60] [--write]

``RUN``: a ``gr_graph.slam`` output folder (``config.yaml``, ``round_0/memory``). ``--write``
writes ``benchmarks/results/correspondence_residuals.md`` and ``.json`` (several runs: call once with
every run).
"""

from __future__ import annotations

import argparse
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

CLASS_NAMES = {1: "horizontal", 2: "vertical", 3: "oblique", 0: "no normal"}
AXES = ("normal", "tangent", "other")


def local_frames(C: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` rows ``n, t, b`` per covariance: the minor axis ``n``, the horizontal direction
    ``t`` orthogonal to it (the major axis where ``n`` is vertical), ``b = n x t``."""
    _, V = np.linalg.eigh(C)
    n = V[:, :, 0]
    t = np.cross(n, np.array([0.0, 0.0, 1.0]))
    norm = np.linalg.norm(t, axis=1, keepdims=True)
    t = np.where(norm > 1e-6, t / np.maximum(norm, 1e-12), V[:, :, 2])
    return np.stack([n, t, np.cross(n, t)], axis=1)


def study(run: Path, models: dict[str, Path], n_edges: int, seed: int = 0) -> dict:
    """Per orientation class: the residuals' spreads and, per network, its covariances' spreads."""
    import torch

    from gr_graph.config import load_config
    from gr_graph.densify import surface_orientation
    from gr_graph.memory import load_memory
    from gr_graph.pca_covariances import pca_covariances
    from training.densify import symmetric_eigenvalues
    from training.predict import predict_covariances
    from training.trainer import load_model

    torch.set_num_threads(1)
    cfg = load_config(run / "config.yaml")
    memory = load_memory(run / "round_0" / "memory")
    nets = {label: load_model(path) for label, path in models.items()}
    tau = cfg.training.tau_ani
    rng = np.random.default_rng(seed)
    edges = np.sort(rng.choice(memory.n_edges, size=min(n_edges, memory.n_edges), replace=False))
    residuals: dict[int, list[np.ndarray]] = {c: [] for c in CLASS_NAMES}
    predicted: dict[str, dict[int, list[np.ndarray]]] = {lab: {c: [] for c in CLASS_NAMES} for lab in nets}
    for e in edges:
        edge = memory.edge(int(e))
        P = np.asarray(memory.scan(edge.k), np.float64)
        Q = np.asarray(memory.scan(edge.l), np.float64)
        corr = np.asarray(edge.corr, np.int64)
        if len(corr) == 0:
            continue
        T = np.asarray(edge.T, np.float64)
        d = Q[corr[:, 1]] - (P[corr[:, 0]] @ T[:3, :3].T + T[:3, 3])
        C_pca = pca_covariances(Q, cfg.preprocess.num_neighbors, cfg.training.trainer.net.eps)[corr[:, 1]]
        cls = surface_orientation(C_pca)
        R = local_frames(C_pca)
        d_local = np.einsum("nij,nj->ni", R, d)
        C_net = {lab: predict_covariances(net, Q.astype(np.float32), seed=cfg.training.seed)[corr[:, 1]]
                 for lab, net in nets.items()}
        for c in CLASS_NAMES:
            m = cls == c
            residuals[c].append(d_local[m])
            for lab, C in C_net.items():
                predicted[lab][c].append(np.einsum("nij,njk,nlk->nil", R[m], C[m], R[m]))
    total = sum(sum(len(x) for x in residuals[c]) for c in CLASS_NAMES)
    classes = {}
    for c, name in CLASS_NAMES.items():
        D = np.concatenate(residuals[c]) if residuals[c] else np.zeros((0, 3))
        if len(D) == 0:
            continue
        second = D.T @ D / len(D)
        w = np.linalg.eigvalsh(second)
        norm_n = np.abs(D[:, 0])
        entry = {
            "share": len(D) / max(total, 1),
            "rms_std_m": dict(zip(AXES, np.sqrt(np.diag(second) / 2).tolist())),
            "rms_lmin_over_lmax": float(w[0] / w[2]),
            "robust_std_m": dict(zip(AXES, (1.4826 * np.median(np.abs(D), axis=0) / np.sqrt(2)).tolist())),
            "normal_quantiles_m": dict(zip(("50", "90", "99"), np.quantile(norm_n, [0.5, 0.9, 0.99]).tolist())),
            "share_normal_over_20cm": float(np.mean(norm_n > 0.2)),
            "networks": {},
        }
        for lab in nets:
            Cl = np.concatenate(predicted[lab][c])
            ev = symmetric_eigenvalues(Cl)
            ratio = ev[:, 0] / ev[:, 2]
            entry["networks"][lab] = {
                "median_std_m": dict(zip(AXES, np.sqrt(np.median(np.diagonal(Cl, axis1=1, axis2=2), axis=0)).tolist())),
                "median_lmin_over_lmax": float(np.median(ratio)),
                "passes_filter": float(np.mean(1.0 - ratio > tau)),
            }
        classes[name] = entry
    return {"run": str(run), "channels": cfg.data.channels, "seed": cfg.seed, "edges": len(edges),
            "correspondences": total, "tau_ani": tau, "models": {k: str(v) for k, v in models.items()},
            "classes": classes}


def _cm(d: dict[str, float]) -> str:
    return " / ".join(f"{100 * d[a]:.1f}" for a in AXES)


def markdown(results: list[dict], command: str) -> str:
    from gr_graph.provenance import machine_line

    lines = ["# What the correspondence NLL asks of the covariances, by surface orientation", "",
             f"Command: `{command}`. Machine: {machine_line()}; "
             f"written {datetime.now(timezone.utc).isoformat(timespec='minutes')}.", "",
             "Residuals `d = q_j - T̂ p_i` of a round-0 memory's correspondences in the local frame of the target "
             "point (normal / horizontal tangent / other in-surface axis, from the PCA covariance of its neighbours), "
             "as spreads `sqrt(E[d_a²]/2)` [cm] (what a Gaussian NLL fits: its optimum is `C = E[d dᵀ]/2`) and "
             "robust spreads `1.4826 median|d_a| / √2` [cm]; networks: the median of their covariances along the "
             "same axes [cm], the median `l_min/l_max` and the share passing the anisotropy filter.", ""]
    for r in results:
        labels = list(r["models"])
        lines += [f"## {r['run']} ({r['channels']} channels, seed {r['seed']}, {r['edges']} edges, "
                  f"{r['correspondences']:,} correspondences, tau_ani {r['tau_ani']})", "",
                  "| surface | share | RMS spread n / t / b | l_min/l_max of E[ddᵀ] | robust spread n / t / b | "
                  "\\|d_n\\| median / q0.9 / q0.99 | \\|d_n\\| > 20 cm | "
                  + " | ".join(f"{lab}: median n / t / b, l_min/l_max, passes" for lab in labels) + " |",
                  "|---|---|---|---|---|---|---|" + "---|" * len(labels)]
        for name, c in r["classes"].items():
            q = c["normal_quantiles_m"]
            cells = [f"{_cm(n['median_std_m'])}, {n['median_lmin_over_lmax']:.3f}, {100 * n['passes_filter']:.0f} %"
                     for n in c["networks"].values()]
            lines.append(f"| {name} | {100 * c['share']:.1f} % | {_cm(c['rms_std_m'])} | {c['rms_lmin_over_lmax']:.3f} | "
                         f"{_cm(c['robust_std_m'])} | {100 * q['50']:.1f} / {100 * q['90']:.1f} / {100 * q['99']:.1f} | "
                         f"{100 * c['share_normal_over_20cm']:.1f} % | " + " | ".join(cells) + (" |" if cells else "|"))
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="gr_graph.slam output folders (round_0/memory is read)")
    ap.add_argument("--model", action="append", default=[], metavar="LABEL=PATH",
                    help="a trained network to compare, e.g. gaussian=round_1/training/model.pt: a relative "
                         "PATH is read inside each RUN, {seed} becomes the run's seed")
    ap.add_argument("--edges", type=int, default=60, help="edges sampled per run (default 60)")
    ap.add_argument("--write", action="store_true",
                    help="write benchmarks/results/correspondence_residuals.md and .json")
    args = ap.parse_args(argv)
    models = {}
    for spec in args.model:
        label, sep, path = spec.partition("=")
        if not sep or not label or not path:
            ap.error(f"--model {spec!r}: expected LABEL=PATH")
        models[label] = Path(path)
    from gr_graph.config import load_config

    results = []
    for run in args.runs:
        seed = load_config(run / "config.yaml").seed
        resolved = {lab: Path(str(p).replace("{seed}", str(seed))) for lab, p in models.items()}
        resolved = {lab: (p if p.is_absolute() else run / p) for lab, p in resolved.items()}
        for lab, p in resolved.items():
            if not p.is_file():
                raise FileNotFoundError(f"{p}: no network {lab!r} for {run}")
        results.append(study(run, resolved, args.edges))
    command = ("python benchmarks/correspondence_residuals_study.py " + " ".join(str(r) for r in args.runs)
               + "".join(f" --model {s}" for s in args.model) + f" --edges {args.edges}")
    from results_io import print_and_write

    print_and_write("correspondence_residuals", markdown(results, command), {"command": command, "results": results}, args.write)


if __name__ == "__main__":
    main()
