"""The ground-tilt offset (``graph.ground_tilt_offset``) on finished rounds, offline: one rule for every edge.

A finished round's graph (``marginals.npz``, ``round.json``) is solved again three times
(:func:`loop_factor_undone_study.solve_round`, the run's ``graph`` options): as run (checked to
reproduce the round's own NEES and ATE), with the loops' own variance factors divided out, and
with them divided out and every registered edge, odometry and loop alike, widened by its
ground-tilt offset (:mod:`gr_graph.ground_tilt`; the ground planes fitted on the round's stored
scans, ``round_R/memory``). Flagged odometry edges keep their fallback information, as in a run.
Each is scored against the ground truth: NEES of the odometry edges, the loops and the marginal
positions, ATE RMSE; plus how closely the offsets follow the edges' roll and pitch errors.

Usage::

    python benchmarks/ground_tilt_offset_study.py LABEL RUN@R [LABEL RUN@R ...] [--name N --title T --note N --write]
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from loop_factor_undone_study import (  # noqa: E402
    REPRODUCE_RTOL,
    _fmt,
    check_reproduced,
    rounds_given,
    solve_round,
    study_parser,
)
from results_io import print_and_write  # noqa: E402


def ground_tilt_offsets(round_dir: Path, marginals: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Every edge's ground-tilt offset (``(E, 3)`` radians, source frame; NaN where an edge is flagged or
    a scan has no ground plane) from the round's stored scans, and whether each edge has one."""
    from gr_graph.ground_tilt import fit_ground_plane, tilt_offset
    from gr_graph.memory import load_memory

    memory = load_memory(round_dir / "memory")
    if memory.n_scans != len(marginals["poses"]):
        raise RuntimeError(f"{round_dir}: the memory holds {memory.n_scans} scans, the round {len(marginals['poses'])} poses")
    planes = [fit_ground_plane(memory.scan(k)) for k in range(memory.n_scans)]
    offsets = np.full((len(marginals["edges"]), 3), np.nan)
    for e, ((k, l), T, ok) in enumerate(zip(marginals["edges"], marginals["edge_T"], marginals["edge_ok"], strict=True)):
        if ok and planes[k] is not None and planes[l] is not None:
            offsets[e] = tilt_offset(T, planes[k].normal, planes[l].normal)
    return offsets, np.isfinite(offsets).all(axis=1)


def offset_agreement(marginals: dict[str, np.ndarray], offsets: np.ndarray, has: np.ndarray) -> dict[str, Any]:
    """Per edge kind: correlation of the offsets with the edges' roll and pitch errors against the ground
    truth, and their RMS [deg]."""
    from gr_graph.noise_consistency import edge_errors, gt_relative_poses

    out: dict[str, Any] = {}
    for kind, name in ((0, "odometry"), (1, "loop")):
        sel = np.nonzero(has & (marginals["edge_kind"] == kind))[0]
        # the measurement's deviation from the truth, Log(T_kl^-1 T̂_kl) = -Log(T̂_kl^-1 T_kl)
        err = -edge_errors(marginals["edge_T"][sel], gt_relative_poses(marginals["edges"][sel],
                                                                       marginals["gt_poses"]))[:, :2]
        o = offsets[sel, :2]
        out[name] = {"n": len(sel), "corr_roll_pitch": [float(np.corrcoef(o[:, a], err[:, a])[0, 1]) for a in (0, 1)],
                     "rms_offset_deg": np.degrees(np.sqrt(np.mean(o**2, axis=0))).tolist(),
                     "rms_error_deg": np.degrees(np.sqrt(np.mean(err**2, axis=0))).tolist()}
    return out


def study_round(round_dir: Path, graph_cfg: Any) -> dict[str, Any]:
    """The three solves of one round (module docstring) and the offsets' agreement with the errors."""
    seen: dict[str, Any] = {}

    def widen(marginals: dict[str, np.ndarray], information: np.ndarray) -> np.ndarray:
        from gr_graph.ground_tilt import widened_information

        offsets, has = ground_tilt_offsets(round_dir, marginals)
        seen.update(agreement=offset_agreement(marginals, offsets, has), n_edges=len(has), n_widened=int(has.sum()))
        out = information.copy()
        for e in np.nonzero(has)[0]:
            out[e] = widened_information(information[e], offsets[e])
        return out

    as_run = solve_round(round_dir, graph_cfg, undo_loop_factors=False)
    check_reproduced(as_run, round_dir)
    undone = solve_round(round_dir, graph_cfg, undo_loop_factors=True)
    tilt = solve_round(round_dir, graph_cfg, undo_loop_factors=True, information_change=widen)
    return {"as_run": as_run, "loop_factors_undone": undone, "ground_tilt_offset": tilt, **seen}


KEYS = ("odometry_nees", "loop_nees", "position_nees", "ate_rmse")
COLUMNS = ("as_run", "loop_factors_undone", "ground_tilt_offset")


def group_of(label: str) -> str:
    """The group a run's label names: what comes before its last ``-s`` (``full-s0`` -> ``full``), else the label."""
    head, sep, _ = label.rpartition("-s")
    return head if sep else label


def table(rows: list[tuple[str, dict[str, Any]]]) -> str:
    """Markdown: per run the three solves (odometry / loop / position NEES, ATE), then mean ± std per group of
    runs (:func:`group_of`) holding several."""
    lines = ["| run | as run (loops with their own factors) | loop factors undone | loop factors undone, every edge "
             "widened by its ground-tilt offset | offset vs. pitch error: correlation odometry / loops |",
             "|---|---|---|---|---|"]
    for label, r in rows:
        a = r["agreement"]
        lines.append(f"| {label} | " + " | ".join(" / ".join(_fmt(r[c][k]) for k in KEYS) for c in COLUMNS)
                     + f" | {a['odometry']['corr_roll_pitch'][1]:.2f} / {a['loop']['corr_roll_pitch'][1]:.2f} |")
    for group in dict.fromkeys(group_of(label) for label, _ in rows):
        members = [r for label, r in rows if group_of(label) == group]
        if len(members) < 2:
            continue

        def ms(c: str, k: str) -> str:
            v = np.array([r[c][k] for r in members], float)
            return f"{_fmt(v.mean())} ± {_fmt(v.std(ddof=1))}"

        lines.append(f"| {group}: mean ± std | " + " | ".join(" / ".join(ms(c, k) for k in KEYS) for c in COLUMNS)
                     + " | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = study_parser(__doc__, "ground_tilt_offset_study", "The ground-tilt offset on finished rounds, offline")
    args = ap.parse_args(argv)
    rows = []
    for label, spec, round_dir, cfg in rounds_given(ap, args.pairs):
        if not (round_dir / "memory").is_dir():
            ap.error(f"{round_dir}: no memory folder (the stored scans the ground planes are fitted on)")
        if round_dir.name != "round_0" and (cfg.training.densify or cfg.training.slam_voxel_size is not None):
            ap.error(f"{spec}: a learning round's memory holds round 0's scans, and this run's learning rounds "
                     "registered others (training.densify or slam_voxel_size): the planes would not be the run's")
        rows.append((label, study_round(round_dir, cfg.graph)))
    command = shlex.join(["python", "benchmarks/ground_tilt_offset_study.py", *(sys.argv[1:] if argv is None else argv)])
    text = (f"# {args.title}\n\nCommand: `{command}`. Each cell: odometry / loop / position NEES, ATE RMSE [m]. "
            "Each round's graph is solved again from its marginals.npz: as run (reproducing the round's own NEES "
            f"and ATE to {REPRODUCE_RTOL:.0%}, checked), with the loops' own variance factors (round.json) divided "
            "out, and with them divided out and every registered edge widened by its ground-tilt offset "
            "(gr_graph.ground_tilt; ground planes of the round's stored scans). Bands: edges 3-12 (ideal 6), "
            "positions 1.5-6 (ideal 3).\n\n" + table(rows) + "\n" + (f"\n{args.note}\n" if args.note else ""))
    print_and_write(args.name, text, {"runs": [{"label": label, **r} for label, r in rows]}, args.write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
