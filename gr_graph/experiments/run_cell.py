"""Running one cell: a resumable run in ``ROOT/<table>/<cell-key>/``.

Layout of a cell's folder::

    definition.json   the cell's definition and fingerprint, written when the cell starts
    reuse.json        ablation cells: what was taken from the source cell (kept for a resume)
    slam/             SLAM cells: the pipeline's --out (rounds resume on their own)
    kiss_icp.json     Table I cells: the KISS-ICP baseline on the same scans (resumed when present)
    pairs.json        Table II cells: the sampled scan pairs
    registration.json Table II cells: gr_graph.global_registration.evaluate_pairs output
    cell.json         written last and atomically: the cell's figures + fingerprint; marks it done

Resume: a cell whose ``cell.json`` holds the current fingerprint is skipped. A cell whose stored
definition (``definition.json`` or ``cell.json``) has another fingerprint is deleted and
recomputed from scratch (its memories may be pruned, so the pipeline's own round resume could
not be trusted), unless it may be another budget's (:func:`_start`: the cell stops instead). An unfinished cell with the same definition continues where it stopped (the
pipeline skips its finished rounds, training resumes from its checkpoint).

Pruning: once a SLAM cell is done and every cell reusing it is done, its ``round_*/memory``
folders and training ``checkpoint.pt`` files are deleted; ``model.pt``, the poses, the
marginals and ``metrics.json`` stay (Table II densifies with ``round_<r>/training/model.pt``).

Reuse (ablations): a cell with ``params["reuse"]`` copies, from its source cell if that one is
done and not pruned, ``round_0`` (round 0 does not depend on the ``training`` section) and, for
``"round1_training"``, ``round_1/training`` (its checkpoint resumes as finished, since the
trainer's settings are equal); otherwise it computes everything itself (logged and recorded
in ``cell.json["reuse"]``). Training is deterministic given the seed, so both give the same result.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Collection
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.atomic import atomic_write_json, read_json_or_none
from gr_graph.experiments.cell_lock import CellBusyError, cell_lock
from gr_graph.experiments.cells import Cell, source_mismatch
from gr_graph.experiments.records import read_result
from gr_graph.provenance import git_state, machine_line

log = logging.getLogger(__name__)

__all__ = ["METRIC_KEYS", "NEES_KEYS", "SHORT_RANGE_DELTAS", "SHORT_RANGE_KEYS", "CellDependencyError",
           "CellConflictError", "CellBusyError", "cell_dir",
           "read_cell_result", "is_done", "run_cell", "prune_cell", "prune_finished", "round_figures",
           "with_noise_consistency", "with_short_range_rpe", "resumed_work", "reused_from_source", "cell_wall_s"]

METRIC_KEYS = ("rpe300_consecutive_mean", "rpe300_consecutive_rmse", "rpe300_all_pairs_mean",
               "rpe300_all_pairs_rmse", "ate_rmse", "kitti_t_err_percent")
#: mean NEES per run of the odometry edges, loop edges and marginal positions (ideal 6, 6, 3), and
#: the odometry's path length against ground truth in percent (ideal 0)
NEES_KEYS = ("nees_odometry_mean", "nees_loop_mean", "nees_position_mean", "odometry_path_error_percent")
#: short-range accuracy of a round's SLAM trajectory: the mean translational RPE over every pair of
#: frames 1 and 10 apart [m] (frame-to-frame registration and local maps; RPE-300 measures drift)
SHORT_RANGE_DELTAS = (1, 10)
SHORT_RANGE_KEYS = tuple(f"rpe{d}_all_pairs_mean" for d in SHORT_RANGE_DELTAS)
CELL_JSON = "cell.json"
DEFINITION_JSON = "definition.json"
REUSE_JSON = "reuse.json"


class CellDependencyError(RuntimeError):
    """A cell needs another cell's results that are not there (run that cell first)."""


class CellConflictError(CellDependencyError):
    """A cell's folder holds a finished cell of another budget (keys repeat between budgets): its results
    are not deleted to make room."""


def cell_dir(root: str | Path, cell: Cell) -> Path:
    """``root/<table>/<key>``."""
    return Path(root) / cell.table / cell.key


def read_cell_result(root: str | Path, cell: Cell) -> dict[str, Any] | None:
    """The cell's ``cell.json`` if it is finished with the current definition, else None."""
    d = read_result(cell_dir(root, cell) / CELL_JSON)
    if d is None or d.get("fingerprint") != cell.fingerprint():
        return None
    if cell.source_fingerprint is not None:  # Table II on densified scans: made with these models?
        why = source_mismatch(cell, d, read_result(Path(root) / str(cell.source) / CELL_JSON))
        if why is not None:
            log.info("%s/%s: %s; recomputed", cell.table, cell.key, why)
            return None
    return d


def is_done(root: str | Path, cell: Cell) -> bool:
    """Whether the cell is finished with its current definition."""
    return read_cell_result(root, cell) is not None


def _start(root: Path, cell: Cell, budget: str | None = None) -> Path:
    """Create the cell's folder; delete it first if it holds another definition of the cell made by the
    same budget (:class:`CellConflictError` otherwise).

    Keys repeat between budgets, so a folder holding another definition may be another budget's
    cell in a shared root. A finished cell is deleted only when its ``cell.json`` names this very
    budget (or neither names one: library calls without budgets); one of another budget, or whose
    budget is not recorded (made before ``cell.json`` named it) while this run has one, is kept and
    the cell stops. An unfinished cell is cleared unless its ``definition.json`` names another budget.
    """
    d = cell_dir(root, cell)
    sweep_trash(d)  # a delete killed in an earlier call (under the cell's lock, as this one)
    fp = cell.fingerprint()
    started, finished = read_json_or_none(d / DEFINITION_JSON), read_result(d / CELL_JSON)
    if started is not None and not isinstance(started, dict):  # damaged: as another definition
        started = {"fingerprint": None}
    hint = (f"its results are kept: use another --root for {budget!r}, or delete that folder to recompute "
            "the cell")
    if finished is not None and finished.get("fingerprint") != fp:
        theirs = finished.get("budget")
        if theirs != budget:
            whose = (f"of budget {theirs!r}" if theirs is not None else
                     "whose budget is not recorded (made before cell.json named it)")
            raise CellConflictError(  # keys repeat between budgets: two budgets sharing a root
                f"{d} holds the finished cell {cell.table}/{cell.key} {whose}, another definition than "
                f"{budget!r}'s; {hint}")
    elif started is not None and started.get("fingerprint") != fp:
        theirs = started.get("budget")
        if theirs is not None and budget is not None and theirs != budget:
            raise CellConflictError(f"{d} holds the unfinished cell {cell.table}/{cell.key} of budget {theirs!r}, "
                                    f"another definition than {budget!r}'s; {hint}")
    if any(s is not None and s.get("fingerprint") != fp for s in (started, finished)):
        log.warning("%s/%s: the stored results were made with another definition; recomputing from scratch",
                    cell.table, cell.key)
        remove_tree(d)
    d.mkdir(parents=True, exist_ok=True)
    started_doc: dict[str, Any] = {"fingerprint": fp, "definition": cell.definition()}
    if budget is not None:
        started_doc["budget"] = budget
    atomic_write_json(d / DEFINITION_JSON, started_doc)
    return d


def round_figures(metrics: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per round of a pipeline ``metrics.json``: SLAM and odometry-only figures (:data:`METRIC_KEYS`),
    ``accepted`` (None when the pipeline did not record it), loops and densification fallbacks."""
    out: dict[str, dict[str, Any]] = {}
    for r, s in sorted(metrics.get("rounds", {}).items(), key=lambda kv: int(kv[0])):
        acc = s.get("accepted")
        if acc is None and isinstance(s.get("acceptance"), dict):
            acc = s["acceptance"].get("accepted")
        lc = s.get("loop_closure") or {}
        dens = s.get("densify") or {}
        out[str(r)] = {
            "slam": {k: (s.get("slam") or {}).get(k) for k in METRIC_KEYS},
            "odometry": {k: (s.get("odometry") or {}).get(k) for k in METRIC_KEYS},
            "accepted": acc,
            "n_loops": s.get("n_loops"),
            "loop_precision": lc.get("precision"),
            "densify_fallbacks": dens.get("fallbacks"),
            "trajectory_change": s.get("trajectory_change"),
            "runtime_s": s.get("runtime_s"),
        }
    return out


def with_noise_consistency(root: str | Path, cell: Cell, result: dict[str, Any]) -> dict[str, Any]:
    """``result`` (a SLAM cell's ``cell.json``) with ``rounds[r]["nees"]``: the mean NEES of the
    round's odometry edges, loop edges and marginal positions and the odometry's path error
    (:data:`NEES_KEYS`, by :mod:`gr_graph.noise_consistency` from ``round_<r>/marginals.npz``,
    which pruning keeps).

    Computed when a report is written, so cells finished before it existed get it too; a round
    without usable marginals gets None values (logged), never a failed report."""
    from gr_graph.noise_consistency import round_noise_consistency

    if cell.kind != "slam":
        return result
    out = {**result, "rounds": {r: dict(v) for r, v in result.get("rounds", {}).items()}}
    for r, figures in out["rounds"].items():
        round_dir = cell_dir(root, cell) / "slam" / f"round_{r}"
        try:
            nc = round_noise_consistency(round_dir)
        except Exception as exc:  # a diagnostic: a damaged or partial file must not cost the report
            log.warning("%s/%s round %s: no NEES (%s: %s)", cell.table, cell.key, r, type(exc).__name__, exc)
            figures["nees"] = dict.fromkeys(NEES_KEYS)
            continue
        figures["nees"] = {"nees_odometry_mean": nc["edges"]["odometry"]["mean"],
                           "nees_loop_mean": nc["edges"]["loop"]["mean"],
                           "nees_position_mean": nc["position"]["mean"],
                           "odometry_path_error_percent": nc["edges"]["odometry"].get("path_error_percent")}
    return out


def with_short_range_rpe(root: str | Path, cell: Cell, result: dict[str, Any]) -> dict[str, Any]:
    """``result`` (a SLAM cell's ``cell.json``) with ``rounds[r]["short_range"]``: the mean
    translational RPE of the round's SLAM poses over every pair of frames 1 and 10 apart
    (:data:`SHORT_RANGE_KEYS`, from ``slam/round_<r>/poses_kitti.txt`` and
    ``slam/gt_poses_kitti.txt``, which pruning keeps).

    Computed when a report is written, so cells finished before it existed get it too; a round
    whose poses are missing or unreadable gets None values (logged), never a failed report."""
    from gr_graph.metrics import rpe_translation
    from gr_graph.trajectory import read_kitti_poses

    if cell.kind != "slam":
        return result
    out = {**result, "rounds": {r: dict(v) for r, v in result.get("rounds", {}).items()}}
    slam = cell_dir(root, cell) / "slam"
    try:
        gt = read_kitti_poses(slam / "gt_poses_kitti.txt")
    except Exception as exc:  # a diagnostic: a missing or damaged file must not cost the report
        log.warning("%s/%s: no short-range RPE (%s: %s)", cell.table, cell.key, type(exc).__name__, exc)
        gt = None
    for r, figures in out["rounds"].items():
        figures["short_range"] = dict.fromkeys(SHORT_RANGE_KEYS)
        if gt is None:
            continue
        try:
            poses = read_kitti_poses(slam / f"round_{r}" / "poses_kitti.txt")
            for d, k in zip(SHORT_RANGE_DELTAS, SHORT_RANGE_KEYS):
                figures["short_range"][k] = rpe_translation(poses, gt, delta=d, all_pairs=True).mean
        except Exception as exc:
            log.warning("%s/%s round %s: no short-range RPE (%s: %s)", cell.table, cell.key, r,
                        type(exc).__name__, exc)
            figures["short_range"] = dict.fromkeys(SHORT_RANGE_KEYS)
    return out


def _slam_config(d: Path, cell: Cell, device: str) -> Any:
    from gr_graph.config import load_config

    out = {"out_dir": str(d / "slam"), "progress": False, "plot": True, "write_memory": True, "resume": True}
    return load_config(None, {**cell.overrides, "device": device, "output": out})


def _require_synthetic(cfg: Any, cell: Cell) -> None:
    """The cells are defined on the synthetic world: fail when this machine would read KITTI
    instead (a root in ``GR_GRAPH_KITTI_ROOT`` or ``./data/kitti``), which the cell's fingerprint
    would not show."""
    from gr_graph.datasets.registry import find_kitti_root

    if cfg.data.dataset == "auto" and cfg.data.path is None and find_kitti_root(cfg.data.seq, cfg.data.data_root):
        raise RuntimeError(f"{cell.table}/{cell.key}: the experiment cells run on the synthetic world, but this "
                           "machine has a KITTI root (GR_GRAPH_KITTI_ROOT, ./data/kitti or ~/data/kitti) that "
                           "the pipeline would read instead: unset or move it for the experiments")


def open_cell_sequence(cfg: Any) -> tuple[Any, str]:
    """The scans of a cell's run (its ``slam/config.yaml`` loaded as ``cfg``) and their description: the
    synthetic world the cells are defined on, even where a KITTI root has appeared since (``dataset:
    auto`` would read it: Table II and the report's pictures would be of other scans)."""
    from gr_graph.datasets.registry import open_configured_sequence

    data = cfg.data
    if data.dataset == "auto" and data.path is None:
        data = data.model_copy(update={"dataset": "synthetic"})
    return open_configured_sequence(data, synthetic_seed=cfg.seed)


def sweep_trash(path: Path) -> None:
    """Delete what a killed :func:`remove_tree` of ``path`` left (its hidden ``.trash-`` siblings)."""
    for stale in path.parent.glob(f".trash-{path.name}-*"):
        shutil.rmtree(stale, ignore_errors=True)


def remove_tree(path: Path) -> None:
    """Delete the folder ``path`` whole or not at all: renamed to a hidden sibling first (one rename), then
    deleted. A delete killed midway (a time limit, Ctrl-C) would otherwise leave some of the old results
    (``round_*/round.json`` without ``cell.json``) for the next run to resume; a killed delete here leaves
    only the hidden sibling, removed by the next start of the cell (:func:`sweep_trash`)."""
    sweep_trash(path)
    if not path.exists():
        return
    trash = path.parent / f".trash-{path.name}-{os.getpid()}-{time.monotonic_ns()}"
    path.rename(trash)
    shutil.rmtree(trash)


def _copy_tree_atomic(src: Path, dst: Path) -> None:
    """Copy the folder ``src`` to ``dst`` whole or not at all: into a hidden sibling, then renamed (an
    interrupted copy leaves only the sibling, replaced by the next copy; an old ``dst`` is removed whole
    first, :func:`remove_tree`)."""
    tmp = dst.parent / f".copying-{dst.name}"
    shutil.rmtree(tmp, ignore_errors=True)
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(src, tmp)
    remove_tree(dst)
    tmp.rename(dst)


def _reuse(root: Path, d: Path, cell: Cell) -> dict[str, Any] | None:
    """Copy round 0 (and round 1's training) from the source cell when possible (module docstring).

    The verdict (``source``, ``what`` was taken, ``copied``) is kept in the cell's ``reuse.json``, so
    a resumed call reports what the first one did: a cell that computed round 0 itself because its
    source was not ready says so after a resume too."""
    what = cell.params.get("reuse")
    if what is None or cell.source is None:
        return None
    slam = d / "slam"
    verdict_path = d / REUSE_JSON
    if (slam / "round_0" / "round.json").is_file():
        verdict = read_json_or_none(verdict_path)
        if verdict is not None:
            return verdict
        # a cell started before the verdict was kept: its round 0 taken as reused, as then
        return {"source": cell.source, "what": what, "note": "already in place"}
    src = Path(root) / cell.source / "slam"
    source_doc = read_result(Path(root) / cell.source / CELL_JSON)
    if source_doc is None or not (src / "round_0" / "memory").is_dir():
        log.info("%s: source %s not finished (or pruned): computing round 0 itself", cell.key, cell.source)
        verdict = {"source": cell.source, "what": None, "copied": [],
                   "note": "source not available: everything computed here"}
    elif cell.reuse_fingerprint is not None and source_doc.get("fingerprint") != cell.reuse_fingerprint:
        log.info("%s: source %s was made with another definition (another budget's, in a shared root): computing "
                 "round 0 itself", cell.key, cell.source)
        verdict = {"source": cell.source, "what": None, "copied": [],
                   "note": "source of another definition: everything computed here"}
    else:  # the verdict follows every copy: a kill between two leaves it saying what is in place
        verdict = {"source": cell.source, "what": what, "copied": []}
        atomic_write_json(verdict_path, verdict)
        _copy_tree_atomic(src / "round_0", slam / "round_0")
        verdict["copied"].append("round_0")
        atomic_write_json(verdict_path, verdict)
        if what == "round1_training" and (src / "round_1" / "training" / "checkpoint.pt").is_file():
            _copy_tree_atomic(src / "round_1" / "training", slam / "round_1" / "training")
            verdict["copied"].append("round_1/training")
    atomic_write_json(verdict_path, verdict)
    return verdict


def _run_slam_cell(root: Path, d: Path, cell: Cell, device: str) -> dict[str, Any]:
    from gr_graph.pipeline import SlamPipeline

    cfg = _slam_config(d, cell, device)
    _require_synthetic(cfg, cell)
    reuse = _reuse(root, d, cell)
    kp = d / "kiss_icp.json"
    pipeline = SlamPipeline(cfg)
    # the baseline reads the pipeline's frames afterwards: from its frame cache, when it has one
    pipeline.keep_frame_cache = bool(cell.params.get("kiss_icp")) and read_json_or_none(kp) is None
    metrics = pipeline.run()
    result: dict[str, Any] = {"rounds": round_figures(metrics), "source": metrics.get("source"),
                              "provenance": metrics.get("provenance"), "reuse": reuse}
    resumed_kiss = None
    if cell.params.get("kiss_icp"):
        kiss = read_json_or_none(kp)
        resumed_kiss = kiss
        if kiss is None:
            from gr_graph.experiments.kiss_baseline import kiss_icp_metrics

            try:
                kiss = kiss_icp_metrics(pipeline.sequence)
            finally:
                pipeline.remove_frame_cache()
            atomic_write_json(kp, kiss)
        result["kiss_icp"] = {"system": kiss["system"], **{k: kiss["metrics"].get(k) for k in METRIC_KEYS},
                              "wall_s": kiss["wall_s"], "cpu_s": kiss["cpu_s"]}
    result["resumed"] = resumed_work(metrics, pipeline.resumed_rounds, resumed_kiss, reused_from_source(reuse))
    return result


def reused_from_source(reuse: dict[str, Any] | None) -> set[str]:
    """What a cell takes from its source cell (:func:`_reuse`) and the source's time holds:
    ``"round_0"``, ``"round_1/training"``; empty when it computed them itself."""
    if reuse is not None and "copied" in reuse:  # what was actually copied (a pruned checkpoint is not)
        return set(reuse["copied"])
    what = (reuse or {}).get("what")  # results made before the verdict was kept whole
    return set() if what is None else {"round_0"} | ({"round_1/training"} if what == "round1_training" else set())


def resumed_work(metrics: dict[str, Any], rounds: list[int], kiss: dict[str, Any] | None,
                 reused: Collection[str] = ()) -> dict[str, Any]:
    """The work of a SLAM cell that this harness call took from an earlier one (an interrupted
    call, or a run adopted into the root) instead of doing it: the rounds it resumed and the
    KISS-ICP baseline it read back, with their recorded wall time (each round's SLAM ``total``
    plus its ``training``; the baseline's ``wall_s``). Work copied from a source cell
    (``reused``, :func:`reused_from_source`) is timed there and not counted. Added to the call's
    own ``wall_s`` this is the cell's time (:func:`cell_wall_s`); the time an interrupted call
    spent on work it did not finish is not in it."""
    wall = 0.0
    for r in rounds:
        runtime = metrics["rounds"][str(r)].get("runtime_s") or {}
        if f"round_{r}" not in reused:
            wall += float(runtime.get("total") or 0.0)
        if f"round_{r}/training" not in reused:
            wall += float(runtime.get("training") or 0.0)
    if kiss is not None:
        wall += float(kiss.get("wall_s") or 0.0)
    return {"rounds": list(rounds), "kiss_icp": kiss is not None, "wall_s": wall,
            "not_counted": sorted(reused)}


def cell_wall_s(doc: dict[str, Any]) -> float:
    """A finished cell's wall time [s]: its last harness call's ``wall_s`` plus the recorded time
    of the work that call resumed (:func:`resumed_work`; records made before it was recorded hold
    the call's time only, or, for an adopted run, the direct run's already added)."""
    return float(doc.get("wall_s", float("nan"))) + float((doc.get("resumed") or {}).get("wall_s") or 0.0)


def _source_round(src_slam: Path, r: int) -> tuple[int, str | None]:
    """The round of the source run to use for round ``r``: ``r`` itself, or the last finished
    round before it when the run converged earlier (noted)."""
    metrics = read_json_or_none(src_slam / "metrics.json") or {}
    rounds = sorted(int(k) for k in metrics.get("rounds", {}))
    if r in rounds:
        return r, None
    earlier = [k for k in rounds if k < r]
    if not earlier:
        raise CellDependencyError(f"{src_slam}: no round <= {r} finished")
    return earlier[-1], f"round {r} was not run (converged or stopped after round {earlier[-1]}): its scans used"


def _scans_mismatch(cell: Cell, cfg: Any) -> str | None:
    """How the source run's configuration ``cfg`` (a :class:`gr_graph.config.SlamConfig`) reads other
    scans than the registration ``cell`` is defined on (frames, channels, world seed), or None."""
    frames = None if cfg.data.frames is None else tuple(int(f) for f in cfg.data.frames)
    diffs = [f"{name} {have} (the cell: {want})" for name, have, want in (
        ("frames", frames, tuple(cell.frames)), ("channels", cfg.data.channels, cell.channels),
        ("seed", cfg.seed, cell.seed)) if have != want]
    return ", ".join(diffs) or None


def _run_registration_cell(root: Path, d: Path, cell: Cell, device: str) -> dict[str, Any]:
    from gr_graph.config import load_config
    from gr_graph.densify import densified_sequence
    from gr_graph.global_registration import evaluate_pairs, sample_pairs, save_pairs, write_results

    assert cell.source is not None
    src = Path(root) / cell.source
    source_doc = read_result(src / CELL_JSON)
    table, key = cell.source.split("/")
    if source_doc is None:
        raise CellDependencyError(f"{cell.table}/{cell.key} needs {cell.source} finished in this root (its models; "
                                  "a published record of it holds figures only): run "
                                  f"`python -m gr_graph.experiments {table} --cell {key}` (same --root, --budget) first")
    if cell.source_fingerprint is not None and source_doc.get("fingerprint") != cell.source_fingerprint:
        raise CellDependencyError(f"{cell.table}/{cell.key} needs {cell.source} of this budget (fingerprint "
                                  f"{cell.source_fingerprint}); this root's was made with another definition "
                                  f"({source_doc.get('fingerprint')}, another budget or an older one): run "
                                  f"`python -m gr_graph.experiments {table} --cell {key}` (same --root, --budget) first")
    cfg = load_config(src / "slam" / "config.yaml", {"device": device})
    why = _scans_mismatch(cell, cfg)
    if why is not None:  # raw-scan cells have no source fingerprint: the scans themselves are checked
        raise CellDependencyError(f"{cell.table}/{cell.key} renders the scans of {cell.source}, whose run in this root "
                                  f"has {why}: another budget's or an older definition; run `python -m "
                                  f"gr_graph.experiments {table} --cell {key}` (same --root, --budget) first")
    seq, desc = open_cell_sequence(cfg)
    gt = np.asarray(seq.gt_poses, np.float64)[: len(seq)]
    pairs = sample_pairs(gt, cell.params["n_pairs"], cell.params["max_distance"], seed=cell.seed)
    save_pairs(d / "pairs.json", pairs, {"sequence": desc, "seed": cell.seed, "n_pairs": cell.params["n_pairs"],
                                         "max_distance_m": cell.params["max_distance"]})
    r, note = _source_round(src / "slam", cell.params["round"])
    scans: Any = seq
    stats = None
    if r > 0:
        model = src / "slam" / f"round_{r}" / "training" / "model.pt"
        if not model.is_file():
            raise CellDependencyError(f"{model} not found (the Table I cell's round-{r} model)")
        scans = densified_sequence(seq, model, cfg.training, device=device, preprocess=cfg.preprocess)
    res = evaluate_pairs(scans, gt, pairs, cell.params["solvers"], seed=cell.seed, progress=False)
    if r > 0:
        stats = scans.stats()
    res["settings"].update(sequence=desc, channels=cell.channels, round_used=r, note=note)
    write_results(d / "registration.json", res)
    return {"summary": res["summary"], "round_used": r, "note": note, "densify": stats, "source": desc}


def cpu_seconds() -> float:
    """CPU time of this process and of its child processes [s]: ``time.process_time``, the finished
    children's user and system time where ``getrusage`` exists (the synthetic world's render process),
    and the solves of the KISS-Matcher worker, which lives on until this process ends."""
    from gr_graph.global_solvers import worker_cpu_seconds

    total = time.process_time() + worker_cpu_seconds()
    try:
        import resource
    except ImportError:  # not on Windows
        return total
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return total + children.ru_utime + children.ru_stime


def peak_rss_mb() -> float | None:
    """Peak resident memory of this process so far plus the largest peak of its finished child
    processes (the synthetic world's render process) [MiB] (``getrusage``; None where it is not
    available): an upper bound of the memory used at once, as the two peaks need not coincide.
    With several cells in one process, the peak of all run so far."""
    try:
        import resource
    except ImportError:  # not on Windows
        return None
    usage = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
             + resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
    return usage / 1024.0  # KiB on Linux


def run_cell(root: str | Path, cell: Cell, device: str = "cpu", command: str = "",
             budget: str | None = None) -> dict[str, Any]:
    """Run ``cell`` under ``root`` unless it is finished; return its ``cell.json`` content.

    ``budget`` (the harness passes it) is stored in ``cell.json``: a finished cell of another budget in
    the same folder is then never deleted to make room (:class:`CellConflictError`). One process at a
    time runs a cell: another one holding it raises :class:`~gr_graph.experiments.cell_lock.CellBusyError`
    (:mod:`gr_graph.experiments.cell_lock`)."""
    root = Path(root)
    done = read_cell_result(root, cell)
    if done is not None:
        log.info("%s/%s: finished; skipped", cell.table, cell.key)
        return done
    with cell_lock(cell_dir(root, cell)):  # CellBusyError when another process runs it
        done = read_cell_result(root, cell)  # finished by another process since the first look
        if done is not None:
            log.info("%s/%s: finished meanwhile by another process; skipped", cell.table, cell.key)
            return done
        return _run_locked(root, cell, device, command, budget)


def _run_locked(root: Path, cell: Cell, device: str, command: str, budget: str | None) -> dict[str, Any]:
    """:func:`run_cell`'s work once the cell's lock is held."""
    d = _start(root, cell, budget)
    log.info("%s/%s: %s", cell.table, cell.key, cell.what)
    t0, c0 = time.perf_counter(), cpu_seconds()
    if cell.kind == "slam":
        result = _run_slam_cell(root, d, cell, device)
    else:
        result = _run_registration_cell(root, d, cell, device)
    doc = {"table": cell.table, "key": cell.key, "what": cell.what, "fingerprint": cell.fingerprint(),
           "definition": cell.definition(), "device": device, "command": command,
           "finished_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "wall_s": time.perf_counter() - t0, "cpu_s": cpu_seconds() - c0,
           "est_minutes": cell.est_minutes, "peak_rss_mb": peak_rss_mb(), "git": git_state(),
           "machine": machine_line(), **result}
    if cell.source_fingerprint is not None:
        doc["source_fingerprint"] = cell.source_fingerprint
    if budget is not None:
        doc["budget"] = budget
    atomic_write_json(d / CELL_JSON, doc)
    return doc


def prune_cell(root: str | Path, cell: Cell) -> list[Path]:
    """Delete the memories and training checkpoints of a finished SLAM cell; return what was deleted."""
    if cell.kind != "slam" or not is_done(root, cell):
        return []
    slam = cell_dir(root, cell) / "slam"
    gone: list[Path] = []
    for p in sorted(slam.glob("round_*/memory")):
        shutil.rmtree(p)
        gone.append(p)
    for p in sorted(slam.glob("round_*/training/checkpoint.pt")):
        p.unlink()
        gone.append(p)
    if (slam / "frames").is_dir():  # a frame cache left by an interrupted run (gr_graph.datasets.frame_cache)
        shutil.rmtree(slam / "frames")
        gone.append(slam / "frames")
    return gone


def prune_finished(root: str | Path, cells: list[Cell]) -> list[Path]:
    """Prune every finished SLAM cell of ``cells`` whose reusing cells (in ``cells``) are finished too."""
    gone: list[Path] = []
    for c in cells:
        users = [u for u in cells if u.source == f"{c.table}/{c.key}" and u.params.get("reuse")]
        if is_done(root, c) and all(is_done(root, u) for u in users):
            gone += prune_cell(root, c)
    return gone
