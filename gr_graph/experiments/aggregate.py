"""Aggregating finished cells into a table: mean +- std over seeds, relative reductions, markdown.

Conventions (stated in every report):

* ``std`` is the sample standard deviation over seeds (``ddof=1``); with one seed it is None
  (shown as "n/a"); values that could not be computed (None, e.g. RPE-300 on a window shorter
  than 300 frames) are left out and the count ``n`` says how many seeds remain;
* a relative reduction is ``100 (raw - x) / raw`` per seed, where ``raw`` is the same seed's
  round 0; the table gives mean +- std of the per-seed reductions (not the reduction of means);
* "2-step unguarded" is round 2 as computed (the cells run with ``training.stop_on_reject:
  false``); "2-step guarded" is the last round r <= 2 such that rounds 1..r were all accepted
  (round 0 when round 1 was rejected): what a run that stops after a rejection ends with, and,
  for runs of at most 2 rounds, the final trajectory ``gr_graph.slam`` writes
  (:func:`gr_graph.round_acceptance.guarded_round`). When
  ``metrics.json`` has no ``accepted`` key every round counts as accepted (reported);
* a round that was not run because the run converged (``training.convergence_delta``) is
  replaced by the last round before it (noted).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

from gr_graph.experiments.cells import PAPER_REDUCTIONS, PAPER_REGISTRATION
from gr_graph.experiments.run_cell import METRIC_KEYS, NEES_KEYS, SHORT_RANGE_KEYS
from gr_graph.round_acceptance import accepted_flags, guarded_round

__all__ = ["mean_std", "reduction_percent", "select_round", "table1_summary", "table2_summary",
           "ablation_summary", "fmt_ms", "round_diagnostics", "STEPS", "METRIC_LABELS", "NEES_LABELS", "NEES_IDEAL",
           "SHORT_RANGE_LABELS", "DIAGNOSTIC_KEYS"]

STEPS = ("raw", "1-step", "2-step", "2-step guarded")
METRIC_LABELS = {
    "rpe300_consecutive_mean": "RPE-300 mean (consec.) [m]",
    "rpe300_consecutive_rmse": "RPE-300 RMSE (consec.) [m]",
    "rpe300_all_pairs_mean": "RPE-300 mean (all pairs) [m]",
    "rpe300_all_pairs_rmse": "RPE-300 RMSE (all pairs) [m]",
    "ate_rmse": "ATE RMSE [m]",
    "kitti_t_err_percent": "KITTI [%]",
}
SHORT_RANGE_LABELS = {"rpe1_all_pairs_mean": "RPE-1 mean [m]", "rpe10_all_pairs_mean": "RPE-10 mean [m]"}
#: figures computed from a round's files when a report is written (noise consistency, short-range RPE)
DIAGNOSTIC_KEYS = NEES_KEYS + SHORT_RANGE_KEYS
NEES_LABELS = {"nees_odometry_mean": "odometry edges", "nees_loop_mean": "loop edges",
               "nees_position_mean": "marginal positions", "odometry_path_error_percent": "odometry path error [%]"}
#: Smallest gap to the baseline that counts, as a fraction of the baseline's own mean value: gaps
#: below it are float noise (rounds that differ only in rounding give gaps of 1e-10 m that agree
#: in sign on every seed), not a difference that could justify changing a default.
MIN_RELATIVE_GAP = 1e-3
#: the ideal value of each of :data:`NEES_KEYS` (a mean NEES: its chi2 degrees of freedom; the path error: 0)
NEES_IDEAL = {"nees_odometry_mean": 6, "nees_loop_mean": 6, "nees_position_mean": 3, "odometry_path_error_percent": 0}


def mean_std(values: Iterable[float | None]) -> dict[str, Any]:
    """``{"mean", "std", "n", "n_given", "values"}`` over the non-None, finite values (std: ddof=1, None if
    n < 2); ``n_given`` counts every value given, so a seed left out (None, NaN: a diverged run) shows."""
    given = list(values)
    vals = [float(v) for v in given if v is not None and math.isfinite(float(v))]
    n = len(vals)
    if n == 0:
        return {"mean": None, "std": None, "n": 0, "n_given": len(given), "values": []}
    m = sum(vals) / n
    s = math.sqrt(sum((v - m) ** 2 for v in vals) / (n - 1)) if n >= 2 else None
    return {"mean": m, "std": s, "n": n, "n_given": len(given), "values": vals}


def reduction_percent(raw: float | None, value: float | None) -> float | None:
    """``100 (raw - value) / raw``; None if either is missing or ``raw`` is 0."""
    if raw is None or value is None or raw == 0:
        return None
    return 100.0 * (raw - value) / raw


def select_round(rounds: dict[str, Any], step: str) -> tuple[int | None, str | None]:
    """The round of a cell's ``rounds`` (:func:`gr_graph.experiments.run_cell.round_figures`)
    standing for ``step`` (one of :data:`STEPS`) and a note when it is not the nominal round."""
    have = sorted(int(r) for r in rounds)
    if not have:
        return None, "no round finished"
    if step == "2-step guarded":
        r, why = guarded_round(accepted_flags(rounds), last=2)
        return r, None if r == min(2, have[-1]) else why.split(":")[0]  # "round 2 rejected" or "round 2 missing"
    want = {"raw": 0, "1-step": 1, "2-step": 2}[step]
    if want in have:
        return want, None
    earlier = [k for k in have if k < want]
    if not earlier:
        return None, f"round {want} missing"
    return earlier[-1], f"round {want} not run (the run stopped after round {earlier[-1]}, e.g. converged)"


def round_diagnostics(cell: dict[str, Any], r: int | None) -> dict[str, float | None]:
    """The mean NEES figures (:data:`NEES_KEYS`) and the short-range RPE (:data:`SHORT_RANGE_KEYS`)
    of round ``r`` of ``cell`` (None where absent)."""
    rnd = cell["rounds"].get(str(r), {}) if r is not None else {}
    nees, short = rnd.get("nees") or {}, rnd.get("short_range") or {}
    return {**{k: nees.get(k) for k in NEES_KEYS}, **{k: short.get(k) for k in SHORT_RANGE_KEYS}}


def _reductions(cell: dict[str, Any], fig: dict[str, Any], diagnostics: dict[str, Any]) -> dict[str, float | None]:
    """Per-seed reduction [%] against the cell's round 0 of every metric and short-range RPE."""
    raw = cell["rounds"].get("0", {}).get("slam", {})
    raw_short = round_diagnostics(cell, 0)
    return {**{f"reduction_{k}": reduction_percent(raw.get(k), fig.get(k)) for k in METRIC_KEYS},
            **{f"reduction_{k}": reduction_percent(raw_short.get(k), diagnostics.get(k)) for k in SHORT_RANGE_KEYS}}


def fmt_ms(d: dict[str, Any] | None, fmt: str = "{:.3f}", pct: bool = False) -> str:
    """``mean ± std`` (``n/a`` parts when missing); ``(n=k of N)`` when values were left out (None, NaN)."""
    if not d or d.get("mean") is None:
        return "n/a"
    u = " %" if pct else ""
    given = d.get("n_given", d["n"])
    count = f" (n={d['n']} of {given})" if given > d["n"] else f" (n={d['n']})"
    if d.get("std") is None:
        return f"{fmt.format(d['mean'])}{u}{count}"
    return f"{fmt.format(d['mean'])} ± {fmt.format(d['std'])}{u}{count if given > d['n'] else ''}"


def acceptance_recorded(results: Sequence[dict[str, Any]]) -> bool:
    """Whether any learning round of ``results`` carries an ``accepted`` flag."""
    return any(v.get("accepted") is not None for c in results for r, v in c.get("rounds", {}).items() if r != "0")


def table1_summary(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Per group (``16ch``, ``32ch``, ``64ch``, ``full-16ch``) and step: every metric's per-seed
    values and mean +- std, the per-seed reductions vs raw, KISS-ICP, the 2x2 acceptance count."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for c in results:
        groups.setdefault(c["definition"]["group"], []).append(c)
    out: dict[str, Any] = {}
    for g, cells in groups.items():
        cells = sorted(cells, key=lambda c: c["definition"]["seed"])
        ch = cells[0]["definition"]["channels"]
        steps: dict[str, Any] = {}
        for step in STEPS:
            if step != "raw" and all(max(int(r) for r in c["rounds"]) < 1 for c in cells):
                continue
            if step.startswith("2-step") and all(c["definition"]["params"]["rounds"] < 2 for c in cells):
                continue
            per_seed, notes = [], []
            for c in cells:
                r, note = select_round(c["rounds"], step)
                fig = c["rounds"][str(r)]["slam"] if r is not None else {}
                diag = round_diagnostics(c, r)
                per_seed.append({"seed": c["definition"]["seed"], "round": r, **fig, **diag,
                                 **_reductions(c, fig, diag)})
                if note:
                    notes.append(f"seed {c['definition']['seed']}: {note}")
            steps[step] = {"per_seed": per_seed, "notes": notes,
                           **{k: mean_std(p.get(k) for p in per_seed) for k in METRIC_KEYS + DIAGNOSTIC_KEYS},
                           **{f"reduction_{k}": mean_std(p.get(f"reduction_{k}") for p in per_seed)
                              for k in METRIC_KEYS + SHORT_RANGE_KEYS}}
        kiss = [c.get("kiss_icp") for c in cells if c.get("kiss_icp")]
        out[g] = {"channels": ch, "seeds": [c["definition"]["seed"] for c in cells],
                  "frames": cells[0]["definition"]["frames"], "steps": steps,
                  "kiss_icp": {k: mean_std(x.get(k) for x in kiss) for k in METRIC_KEYS} if kiss else None,
                  # the paper's Table I is the whole KITTI 00: its figures apply to windows and the full run alike
                  "paper_reduction": PAPER_REDUCTIONS.get(ch),
                  "acceptance_2x2": acceptance_counts(cells)}
    return out


def acceptance_counts(cells: Sequence[dict[str, Any]], key: str = "rpe300_all_pairs_mean") -> dict[str, int]:
    """2x2 count over the learning rounds of ``cells``: accepted/rejected x better/worse by ground
    truth (``key``) than the round the test judged against, the last accepted one (round 0 at
    first); "better" is strictly lower, so a round equal to its reference counts as worse
    (no gain). Rounds without an ``accepted`` flag are not counted."""
    counts = {"accepted_better": 0, "accepted_worse": 0, "rejected_better": 0, "rejected_worse": 0}
    for c in cells:
        rounds = c.get("rounds", {})
        reference = 0
        for r in sorted(int(k) for k in rounds):
            accepted = rounds[str(r)].get("accepted")
            if r == 0 or accepted is None:
                continue
            now = rounds[str(r)]["slam"].get(key)
            before = rounds.get(str(reference), {}).get("slam", {}).get(key)
            if now is not None and before is not None:
                a = "accepted" if accepted else "rejected"
                counts[f"{a}_{'better' if now < before else 'worse'}"] += 1
            if accepted:
                reference = r
    return counts


def table2_summary(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Per channel count, step (raw / 1-step / 2-step) and solver: success rate [%] per seed and
    mean +- std; ``best_step`` is the densified step with the highest mean, beside the paper's."""
    out: dict[str, Any] = {}
    for c in results:
        d = c["definition"]
        ch, step = d["channels"], ("raw" if d["params"]["round"] == 0 else f"{d['params']['round']}-step")
        for solver, s in c["summary"].items():
            row = out.setdefault(str(ch), {}).setdefault(step, {}).setdefault(solver, {"per_seed": []})
            rate = s["success_rate"]  # None (no pair evaluated) stays missing, not 0 %
            row["per_seed"].append({"seed": d["seed"], "success_percent": None if rate is None else 100.0 * rate,
                                    "n_pairs": s["n_pairs"], "note": c.get("note")})
    for ch, steps in out.items():
        for step, solvers in list(steps.items()):
            for solver, row in solvers.items():
                row.update(mean_std(p["success_percent"] for p in row["per_seed"]))
        best: dict[str, Any] = {}
        solvers_all = {s for st in steps.values() for s in st}
        for solver in sorted(solvers_all):
            dens = [(st, steps[st][solver]["mean"]) for st in steps if st != "raw" and solver in steps[st]
                    and steps[st][solver]["mean"] is not None]  # a step without any success rate: none
            if dens:
                st, m = max(dens, key=lambda x: x[1])
                best[solver] = {"step": st, "mean": m}
        steps_sorted = dict(sorted(steps.items(), key=lambda kv: (kv[0] != "raw", kv[0])))
        out[ch] = {"steps": steps_sorted, "best_step": best, "paper": PAPER_REGISTRATION.get(int(ch))}
    return dict(sorted(out.items(), key=lambda kv: -int(kv[0])))


def ablation_summary(results: Sequence[dict[str, Any]], baseline: str = "default") -> dict[str, Any]:
    """Per ablation and step (raw, 1-step, 2-step, 2-step guarded): metric mean +- std over seeds,
    the per-seed reduction against the cell's own round 0 (what the learning rounds bring), the
    per-seed difference to the ``baseline`` cell of the same seed (mean +- std, and whether all
    seeds agree in sign with ``|mean| > std`` and ``|mean|`` above :data:`MIN_RELATIVE_GAP` of the
    baseline's value: the rule for changing a default) and the 2x2
    acceptance count of the ablation's learning rounds."""
    by: dict[str, dict[int, dict[str, Any]]] = {}
    for c in results:
        by.setdefault(c["definition"]["group"], {})[c["definition"]["seed"]] = c
    out: dict[str, Any] = {}
    base = by.get(baseline, {})
    for name, cells in by.items():
        steps: dict[str, Any] = {}
        for step in ("raw", "1-step", "2-step", "2-step guarded"):
            per_seed = []
            for seed, c in sorted(cells.items()):
                r, note = select_round(c["rounds"], step)
                fig = c["rounds"][str(r)]["slam"] if r is not None else {}
                diag = round_diagnostics(c, r)
                row: dict[str, Any] = {"seed": seed, "round": r, "note": note, **fig, **diag,
                                       **_reductions(c, fig, diag)}
                b = base.get(seed)
                if b is not None:
                    rb, _ = select_round(b["rounds"], step)
                    bfig = b["rounds"][str(rb)]["slam"] if rb is not None else {}
                    for k in METRIC_KEYS:
                        row[f"diff_{k}"] = (None if fig.get(k) is None or bfig.get(k) is None
                                            else fig[k] - bfig[k])
                per_seed.append(row)
            entry: dict[str, Any] = {"per_seed": per_seed, **{k: mean_std(p.get(k) for p in per_seed)
                                                              for k in METRIC_KEYS + DIAGNOSTIC_KEYS},
                                     **{f"reduction_{k}": mean_std(p.get(f"reduction_{k}") for p in per_seed)
                                        for k in METRIC_KEYS + SHORT_RANGE_KEYS}}
            for k in METRIC_KEYS:
                diff = mean_std(p.get(f"diff_{k}") for p in per_seed)
                vals = diff["values"]
                base_mean = mean_std(p[k] - p[f"diff_{k}"] for p in per_seed
                                     if p.get(k) is not None and p.get(f"diff_{k}") is not None)["mean"]
                resolution = MIN_RELATIVE_GAP * abs(base_mean) if base_mean is not None else 0.0
                # every seed of the ablation, each with a difference (a seed left out cannot agree)
                diff["consistent"] = bool(len(vals) >= 2 and len(vals) == len(per_seed) == len(base)
                                          and (all(v > 0 for v in vals) or all(v < 0 for v in vals))
                                          and diff["std"] is not None and abs(diff["mean"]) > diff["std"]
                                          and abs(diff["mean"]) > resolution)
                entry[f"diff_{k}"] = diff
            steps[step] = entry
        out[name] = {"what": next(iter(cells.values()))["what"].split(",")[0], "seeds": sorted(cells),
                     "steps": steps, "reuse": {s: c.get("reuse") for s, c in sorted(cells.items())},
                     "acceptance_2x2": acceptance_counts(list(cells.values()))}
    return out
