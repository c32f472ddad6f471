"""What the anisotropy filter keeps, by surface orientation: the trained network against PCA (not a test).

The learning rounds replace every scan by samples around the points whose covariance is
anisotropic (``1 - l_min / l_max > training.tau_ani``, Algorithm 2). This takes scans of a
finished run, the network a learning round trained (``round_R/training/model.pt``), and counts,
per surface orientation, which share of the points passes the filter with the network's
covariances and with PCA covariances of the same points (``gr_graph.pca_covariances``, the
``k = preprocess.num_neighbors`` nearest neighbours: the GICP covariance). The orientation of a
point is that of its PCA covariance's normal (``gr_graph.densify.surface_orientation``: the
geometry, not the network, decides the class). Also the network's median eigenvalue ratio and
axis lengths per class.

Run::

    python benchmarks/densify_filter_study.py RUN [RUN ...] [--round 1] [--scans 8] [--write]

``RUN``: a ``gr_graph.slam`` output folder (``config.yaml``, ``round_R/training/model.pt``); the
scans are read again from the run's data settings (the synthetic world is rendered) and
preprocessed as SLAM preprocesses them, i.e. the network's input. ``--write`` writes
``benchmarks/results/densify_filter.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

CLASS_NAMES = {1: "horizontal", 2: "vertical", 3: "oblique", 0: "no normal"}


def study(run: Path, round_index: int, n_scans: int) -> dict:
    """Per orientation class: point share, kept share (network, PCA), the network's median axes."""
    import torch

    from gr_graph.config import load_config
    from gr_graph.datasets.registry import open_configured_sequence
    from gr_graph.densify import surface_orientation
    from gr_graph.pca_covariances import pca_covariances
    from gr_graph.preprocess import preprocess_scan
    from training.densify import anisotropy, symmetric_eigenvalues
    from training.predict import predict_covariances
    from training.trainer import load_model

    torch.set_num_threads(1)
    cfg = load_config(run / "config.yaml")
    model_path = run / f"round_{round_index}" / "training" / "model.pt"
    if not model_path.is_file():
        raise FileNotFoundError(f"{model_path}: no trained network of round {round_index} in {run}")
    model = load_model(model_path)
    seq, _ = open_configured_sequence(cfg.data, cfg.seed, cfg.sensor)
    tau = cfg.training.tau_ani
    rows = np.unique(np.linspace(0, len(seq) - 1, n_scans).round().astype(int))
    acc: dict[int, dict[str, list]] = {c: {"n": [], "net": [], "pca": [], "ratio": [], "major": [], "minor": []}
                                       for c in CLASS_NAMES}
    total = 0
    for i in rows:
        scan = preprocess_scan(seq[int(i)].points, cfg.preprocess, index=int(i))
        p = scan.points
        C_net = predict_covariances(model, p, seed=cfg.training.seed)
        C_pca = pca_covariances(p, cfg.preprocess.num_neighbors, cfg.training.trainer.net.eps)  # as the pca ablation
        cls = surface_orientation(C_pca)
        w = symmetric_eigenvalues(C_net)
        kept_net, kept_pca = anisotropy(C_net, w) > tau, anisotropy(C_pca) > tau
        total += len(p)
        for c in CLASS_NAMES:
            m = cls == c
            a = acc[c]
            a["n"].append(int(m.sum()))
            a["net"].append(int(kept_net[m].sum()))
            a["pca"].append(int(kept_pca[m].sum()))
            a["ratio"].extend((w[m, 0] / w[m, 2]).tolist())
            a["major"].extend(np.sqrt(w[m, 2]).tolist())
            a["minor"].extend(np.sqrt(w[m, 0]).tolist())
    classes = {}
    for c, name in CLASS_NAMES.items():
        a = acc[c]
        n = sum(a["n"])
        classes[name] = {
            "share_of_points": n / max(total, 1),
            "kept_network": sum(a["net"]) / max(n, 1),
            "kept_pca": sum(a["pca"]) / max(n, 1),
            "network_median_lmin_over_lmax": float(np.median(a["ratio"])) if n else None,
            "network_median_major_std_m": float(np.median(a["major"])) if n else None,
            "network_median_minor_std_m": float(np.median(a["minor"])) if n else None,
        }
    kept_net_total = sum(sum(acc[c]["net"]) for c in CLASS_NAMES)
    kept_pca_total = sum(sum(acc[c]["pca"]) for c in CLASS_NAMES)
    return {"run": str(run), "round": round_index, "model": str(model_path), "scans": [int(i) for i in rows],
            "points": total, "tau_ani": tau, "channels": cfg.data.channels, "seed": cfg.seed, "classes": classes,
            "kept_network": kept_net_total / max(total, 1), "kept_pca": kept_pca_total / max(total, 1),
            "horizontal_share_of_kept_network": sum(acc[1]["net"]) / max(kept_net_total, 1),
            "horizontal_share_of_kept_pca": sum(acc[1]["pca"]) / max(kept_pca_total, 1)}


def markdown(results: list[dict], command: str) -> str:
    from gr_graph.provenance import machine_line

    lines = ["# What the anisotropy filter keeps: the trained network against PCA, by surface orientation", "",
             f"Command: `{command}`. Machine: {machine_line()}; "
             f"written {datetime.now(timezone.utc).isoformat(timespec='minutes')}.",
             "Orientation from the PCA covariance's normal (30° tolerance); kept: `1 - l_min/l_max > tau_ani`.", ""]
    for r in results:
        lines += [f"## {r['run']} (round {r['round']} network, {r['channels']} channels, seed {r['seed']}, "
                  f"{len(r['scans'])} scans, {r['points']:,} points, tau_ani {r['tau_ani']})", "",
                  f"Kept: network {100 * r['kept_network']:.1f} % of the points "
                  f"({100 * r['horizontal_share_of_kept_network']:.0f} % of them horizontal), PCA "
                  f"{100 * r['kept_pca']:.1f} % ({100 * r['horizontal_share_of_kept_pca']:.0f} % horizontal).", "",
                  "| surface (PCA normal) | share of points | kept, network | kept, PCA | network l_min/l_max (median) "
                  "| network axes: major / minor std [m] (median) |",
                  "|---|---|---|---|---|---|"]
        for name, c in r["classes"].items():
            if c["network_median_lmin_over_lmax"] is None:
                continue
            lines.append(f"| {name} | {100 * c['share_of_points']:.1f} % | {100 * c['kept_network']:.1f} % | "
                         f"{100 * c['kept_pca']:.1f} % | {c['network_median_lmin_over_lmax']:.3f} | "
                         f"{c['network_median_major_std_m']:.3f} / {c['network_median_minor_std_m']:.3f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="gr_graph.slam output folders")
    ap.add_argument("--round", type=int, default=1, help="the learning round whose network is read (default 1)")
    ap.add_argument("--scans", type=int, default=8, help="scans per run, evenly spaced (default 8)")
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/densify_filter.md and .json")
    args = ap.parse_args(argv)
    results = [study(r, args.round, args.scans) for r in args.runs]
    command = (f"python benchmarks/densify_filter_study.py {' '.join(str(r) for r in args.runs)} --round {args.round} "
               f"--scans {args.scans}")
    from results_io import print_and_write

    print_and_write("densify_filter", markdown(results, command), {"command": command, "results": results}, args.write)


if __name__ == "__main__":
    main()
