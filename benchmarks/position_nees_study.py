"""Why the marginals' positions miss their band when the edges meet theirs: odometry chains, and chance.

For each finished round (``marginals.npz``): the odometry edges' NEES one by one and over chains of
10 and 100 consecutive edges (:func:`gr_graph.noise_consistency.chain_nees`: the error of the
relative pose a chain adds up to, against the covariance its edges give it when independent, as
the graph takes them), the same edges chained in a random order (every edge of the 100-edge chains
once; their covariances kept, any correlation between neighbours removed), the per-axis ``z²`` of
edges and chains, and the marginals' position NEES, horizontal and vertical. Chains below their
shuffled figure: errors that cancel from one edge to the next; above: errors that persist. With
``--draws N``, also the spread of one run's mean position NEES were every edge's information exact
(:func:`gr_graph.noise_consistency.position_nees_draws`, Monte Carlo around the round's solution,
the graph solved as the run did): its 5 / 50 / 95 % points, how often it falls in the band, and
where the observed figure falls among the draws.

Usage::

    python benchmarks/position_nees_study.py LABEL RUN@R [LABEL RUN@R ...] [--draws N] [--seed S]
        [--name N --title T --note N --write]
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ground_tilt_offset_study import group_of  # noqa: E402
from loop_factor_undone_study import _fmt, rounds_given, study_parser  # noqa: E402
from results_io import print_and_write  # noqa: E402

#: chain length of the shuffled comparison and of the per-axis columns (one of CHAIN_LENGTHS)
LONG = 100


def _fmt_or_dash(x: float | None) -> str:
    """:func:`_fmt`, or "-" for a figure that could not be computed (no chain that long)."""
    return "-" if x is None or not np.isfinite(x) else _fmt(x)


def shuffled_chains(chains: list[np.ndarray], seed: int) -> list[np.ndarray]:
    """The edges of ``chains``, every one once, in a random order, cut into chains of the same length."""
    if not chains:
        return []
    edges = np.random.default_rng(seed).permutation(np.concatenate(chains))
    return list(edges.reshape(len(chains), -1))
#: axes shown per chain (gtsam order indices): roll, pitch, yaw, x, y, z
AXIS_NAMES = ("roll", "pitch", "yaw", "x", "y", "z")



def study_round(round_dir: Path, seed: int, graph_cfg: Any, draws: int) -> dict[str, Any]:
    """Chain figures of one round and, with ``draws``, the Monte Carlo spread of its position NEES."""
    from gr_graph.noise_consistency import (
        chain_nees_of,
        gt_relative_poses,
        odometry_chains,
        position_nees_draws,
        round_noise_consistency,
    )

    nc = round_noise_consistency(round_dir)
    with np.load(round_dir / "marginals.npz") as z:
        sel = (z["edge_kind"] == 0) & z["edge_ok"].astype(bool)
        edges, edge_T, info, gt = z["edges"][sel], z["edge_T"][sel], z["edge_information"][sel], z["gt_poses"]
    shuffled = chain_nees_of(shuffled_chains(odometry_chains(edges, LONG), seed), edge_T, info,
                             gt_relative_poses(edges, gt), LONG)
    odometry = nc["edges"]["odometry"]
    out = {"odometry": {k: odometry[k] for k in ("n", "mean", "per_axis", "chains")},
           "chains_shuffled": {str(LONG): shuffled}, "position": nc["position"],
           "loop_nees": nc["edges"]["loop"]["mean"]}
    if draws:
        out["position_draws"] = position_nees_draws(round_dir, graph_cfg, draws, seed, progress=True)
    return out


def table(rows: list[tuple[str, dict[str, Any]]]) -> str:
    """Markdown: per run the NEES of edges, chains and positions, then the per-axis z² of edges and of
    100-edge chains; mean ± std per group of runs (:func:`group_of`) holding several."""
    def figures(r: dict[str, Any]) -> list[float]:
        o, c = r["odometry"], r["odometry"]["chains"]
        p = r["position"]
        return [o["mean"], c["10"]["mean"], c[str(LONG)]["mean"], r["chains_shuffled"][str(LONG)]["mean"],
                p["mean"], p["horizontal"]["mean"], p["vertical"]["mean"]]

    def axes(r: dict[str, Any]) -> list[tuple[float, float]]:
        chain = r["odometry"]["chains"][str(LONG)]["z2_mean"] or [None] * 6
        return list(zip(r["odometry"]["per_axis"]["z2_mean"], chain))

    head = ("| run | odometry NEES: edges | chains of 10 | of 100 | of 100, shuffled | positions | horizontal | "
            "vertical | " + " | ".join(f"{a} z²: edges / chains of {LONG}" for a in AXIS_NAMES) + " |")
    lines = [head, "|" + "---|" * (8 + len(AXIS_NAMES))]
    for label, r in rows:
        lines.append(f"| {label} | " + " | ".join(_fmt_or_dash(x) for x in figures(r)) + " | "
                     + " | ".join(f"{_fmt_or_dash(e)} / {_fmt_or_dash(c)}" for e, c in axes(r)) + " |")
    for group in dict.fromkeys(group_of(label) for label, _ in rows):
        members = [r for label, r in rows if group_of(label) == group]
        if len(members) < 2:
            continue
        f = np.array([figures(r) for r in members], float)  # None -> nan
        a = np.array([axes(r) for r in members], float)
        lines.append(f"| {group}: mean ± std | " + " | ".join(f"{_fmt_or_dash(m)} ± {_fmt_or_dash(s)}" for m, s in
                                                             zip(f.mean(0), f.std(0, ddof=1)))
                     + " | " + " | ".join(f"{_fmt_or_dash(e)} / {_fmt_or_dash(c)}" for e, c in a.mean(0)) + " |")
    return "\n".join(lines)


def draws_table(rows: list[tuple[str, dict[str, Any]]]) -> str:
    """Markdown: per run the observed mean position NEES against its Monte Carlo spread."""
    from gr_graph.noise_consistency import POSITION_BAND

    lo, hi = POSITION_BAND
    lines = [f"| run | loop NEES | position NEES observed (horizontal / vertical) | if exact: 5 / 50 / 95 % | "
             f"if exact: runs in {lo:g}-{hi:g} | observed above this share of the draws |", "|---|---|---|---|---|---|"]
    f = _fmt_or_dash
    for label, r in rows:
        d, p = r["position_draws"]["position"], r["position"]
        q = d["percentiles"]
        lines.append(f"| {label} | {f(r['loop_nees'])} | {f(p['mean'])} ({f(p['horizontal']['mean'])} / "
                     f"{f(p['vertical']['mean'])}) | {f(q['5'])} / {f(q['50'])} / {f(q['95'])} | "
                     f"{100 * d['frac_in_band']:.0f} % | {d['observed_percentile']:.0f} % |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = study_parser(__doc__, "position_nees_study", "Odometry chains, and the spread of one run's position NEES")
    ap.add_argument("--seed", type=int, default=0, help="of the shuffled chains' order and of the draws")
    ap.add_argument("--draws", type=int, default=0, help="Monte Carlo draws per round (0: none)")
    args = ap.parse_args(argv)
    rows = [(label, study_round(round_dir, args.seed, cfg.graph, args.draws))
            for label, _, round_dir, cfg in rounds_given(ap, args.pairs)]
    command = shlex.join(["python", "benchmarks/position_nees_study.py", *(sys.argv[1:] if argv is None else argv)])
    text = (f"# {args.title}\n\nCommand: `{command}`. Odometry edges not flagged; chains of consecutive edges, "
            "not overlapping (gr_graph.noise_consistency.chain_nees: the chain's error against the covariance its "
            "edges add up to if independent, first order); shuffled: the edges of the 100-edge chains, each once, "
            "chained in a random order "
            f"(seed {args.seed}). Ideal: edges and chains 6, positions 3 (horizontal 2, vertical 1), z² 1. "
            "Group rows: mean ± std over the group's runs, the z² columns their means.\n\n"
            + table(rows) + "\n"
            + (f"\nThe spread of one run's mean position NEES if every edge's information were exact ({args.draws} "
               f"draws a round, seed {args.seed}; gr_graph.noise_consistency.position_nees_draws: measurements drawn "
               "around the round's solution from the covariances its graph uses, the graph solved as the run did, "
               "scored with the round's own marginals):\n\n" + draws_table(rows) + "\n" if args.draws else "")
            + (f"\n{args.note}\n" if args.note else ""))
    print_and_write(args.name, text, {"runs": [{"label": label, **r} for label, r in rows]}, args.write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
