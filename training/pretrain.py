"""Build the weights shipped with gr_graph (``--weights pretrained``) and their model card.

Steps (each resumable: finished SLAM runs and training checkpoints are reused)::

    python -m training.pretrain memories --root runs/pretrain      # round 0 on the training windows
    python -m training.pretrain train    --root runs/pretrain      # one network on all their memories
    python -m training.pretrain evaluate --root runs/pretrain      # held-out seeds: round 0 vs the weights
    python -m training.pretrain per-count --root runs/pretrain     # ablation: one model vs one per count (16)
    python -m training.pretrain install  --root runs/pretrain      # gr_graph/data/pretrained.{pt,json}
    python -m training.pretrain all      --root runs/pretrain --jobs 2

The training windows are windows of the default synthetic world (the ``kitti`` preset) with
their own town and route seeds, sensors and channel counts (:data:`TRAIN_WINDOWS`); each is a
``gr_graph.slam`` round-0 run whose memory the trainer reads (:func:`training.train.train_from_memory`
on all memories at once). The evaluation runs, on world seeds never used in training
(:data:`EVAL_WINDOWS`), round 0 and one learning round that densifies with the weights as
they are (``gr-slam --weights ... --densify``): what a user gets without training. Its table
goes into ``pretrained.json`` (the model card) and ``benchmarks/results/pretrained.md``.
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.atomic import atomic_write_json, atomic_write_text, read_json_or_none
from gr_graph.cli_common import add_log_level, make_parser, setup_logging
from gr_graph.pretrained import weights_sha256

log = logging.getLogger(__name__)

__all__ = ["Window", "TRAIN_WINDOWS", "EVAL_WINDOWS", "main"]

REPO = Path(__file__).resolve().parents[1]
RESULTS_MD = REPO / "benchmarks" / "results" / "pretrained.md"


@dataclass(frozen=True)
class Window:
    """One ``gr_graph.slam`` run on the synthetic world: seeds, sensor, channels, frames."""

    name: str
    seed: int  # town seed (and training seed of a learning round)
    route_seed: int
    sensor: str
    channels: int | None  # None: every beam of the sensor
    frames: str

    def args(self) -> list[str]:
        a = ["--seq", "00", "--seed", str(self.seed), "--route-seed", str(self.route_seed), "--sensor", self.sensor,
             "--frames", self.frames, "--synthetic-preset", "kitti"]
        return a + (["--channels", str(self.channels)] if self.channels else [])


#: Where the shipped weights learn: five worlds, three sensors, 64/32/16 HDL-64E channels.
TRAIN_WINDOWS = (
    Window("s1_hdl64e_64", 1, 1, "hdl64e", 64, "0:250"),
    Window("s2_hdl64e_32", 2, 2, "hdl64e", 32, "0:250"),
    Window("s3_hdl64e_16", 3, 3, "hdl64e", 16, "0:250"),
    Window("s4_vlp16", 4, 4, "vlp16", None, "0:250"),
    Window("s5_os1_64", 5, 5, "os1-64", None, "0:250"),
)
#: Held-out worlds (seeds never used in training) for the model card's figures.
EVAL_WINDOWS = tuple(Window(f"s{s}_hdl64e_{c}", s, s, "hdl64e", c, "0:400") for s in (11, 12, 13) for c in (64, 16))
EPOCHS = 2
TRAIN_SEED = 0
#: trainer options of the shipped weights where the trainer's defaults have changed since they were
#: trained (2026-12-01, the Gaussian likelihood; the Student t became the default on 2026-12-05)
SHIPPED_TRAINER: dict[str, Any] = {"corr_likelihood": "gaussian"}
METRICS = ("rpe300_all_pairs_mean", "rpe300_consecutive_mean", "ate_rmse", "kitti_t_err_percent")


def _slam(out: Path, window: Window, extra: list[str]) -> dict[str, Any]:
    """``python -m gr_graph.slam`` on ``window`` into ``out`` (resumes); its metrics.json."""
    cmd = [sys.executable, "-m", "gr_graph.slam", *window.args(), "--out", str(out), "--no-progress", *extra]
    log.info("%s", " ".join(cmd[1:]))
    out.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".log"), "a") as fh:
        subprocess.run(cmd, check=True, cwd=REPO, stdout=fh, stderr=subprocess.STDOUT)
    return json.loads((out / "metrics.json").read_text())


def _parallel(jobs: int, fn, items) -> list[Any]:
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        return list(pool.map(fn, items))


def _memory_dir(root: Path, window: Window) -> Path:
    return root / "windows" / window.name / "round_0" / "memory"


def memories(root: Path, jobs: int = 1, windows: tuple[Window, ...] = TRAIN_WINDOWS) -> list[Path]:
    """Round 0 on every window (default: the training windows); the memory folders."""
    _parallel(jobs, lambda w: _slam(root / "windows" / w.name, w, ["--rounds", "0"]), windows)
    return [_memory_dir(root, w) for w in windows]


def _train_on(root: Path, windows: tuple[Window, ...], out: Path, epochs: int, seed: int = TRAIN_SEED) -> Path:
    """One network (the trainer's defaults but :data:`SHIPPED_TRAINER`) on the round-0 memories of
    ``windows``; ``out/model.pt``."""
    from gr_graph.config import TrainingConfig
    from training.train import train_from_memory

    mems = [_memory_dir(root, w) for w in windows]
    missing = [str(m) for m in mems if not m.is_dir()]
    if missing:
        raise FileNotFoundError(f"run `python -m training.pretrain memories --root {root}` first: missing {missing}")
    cfg = TrainingConfig(epochs=epochs, seed=seed, trainer=SHIPPED_TRAINER).trainer_config("cpu", progress=True)
    return train_from_memory(mems, out, cfg)


def train(root: Path, epochs: int = EPOCHS, seed: int = TRAIN_SEED) -> Path:
    """One network trained on every training window's memory; ``root/training/model.pt``."""
    return _train_on(root, TRAIN_WINDOWS, root / "training", epochs, seed)


def _mean_std(x: np.ndarray) -> list[float]:
    return [float(np.mean(x)), float(np.std(x))]


def _figures(metrics: dict[str, Any], r: int) -> dict[str, Any]:
    s = metrics["rounds"].get(str(r))
    if s is None:
        return {}
    out = {k: s.get("slam", {}).get(k) for k in METRICS}
    out["accepted"] = s.get("accepted")
    out["mean_points"] = s.get("mean_points")
    if "acceptance" in s:
        out["mean_entropy"] = s["acceptance"].get("mean_entropy")
        out["reference_mean_entropy"] = s["acceptance"].get("reference_mean_entropy")
    if "covariance_failures" in s:
        out["covariance_failures"] = s["covariance_failures"]
    return out


def evaluate(root: Path, weights: Path | None = None, jobs: int = 1) -> dict[str, Any]:
    """Round 0 and the weights without training (``--densify``) on the held-out windows."""
    weights = weights or root / "training" / "model.pt"
    if not weights.is_file():
        raise FileNotFoundError(f"{weights}: train first (`python -m training.pretrain train --root {root}`)")

    def one(w: Window) -> dict[str, Any]:
        m = _slam(root / "eval" / w.name, w, ["--rounds", "1", "--weights", str(weights), "--densify"])
        return {"window": asdict(w), "round0": _figures(m, 0), "pretrained": _figures(m, 1),
                "final_round": m.get("final_round")}

    sha = weights_sha256(weights)  # before the runs: weights replaced meanwhile make the card refuse them
    rows = _parallel(jobs, one, EVAL_WINDOWS)
    res = {"weights": str(weights), "weights_sha256": sha, "rows": rows, "summary": summarize(rows)}
    atomic_write_json(root / "evaluation.json", res)
    return res


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per channel count: mean ± std over seeds of round 0, the weights, and the relative change."""
    out: dict[str, Any] = {}
    for ch in sorted({r["window"]["channels"] for r in rows}, reverse=True):
        sel = [r for r in rows if r["window"]["channels"] == ch]
        d: dict[str, Any] = {"n_seeds": len(sel), "accepted": sum(bool(r["pretrained"].get("accepted")) for r in sel)}
        for k in METRICS:
            a = np.array([r["round0"].get(k) for r in sel], float)
            b = np.array([r["pretrained"].get(k) for r in sel], float)
            rel = (b - a) / a
            d[k] = {"round0": _mean_std(a), "pretrained": _mean_std(b), "relative_change": _mean_std(rel),
                    "better_in": int(np.sum(b < a))}
        out[str(ch)] = d
    return out


def per_count_windows(channels: int) -> tuple[Window, ...]:
    """The training windows' worlds and frames, all seen by the HDL-64E at ``channels`` channels."""
    return tuple(Window(f"s{w.seed}_hdl64e_{channels}_only", w.seed, w.route_seed, "hdl64e", channels, w.frames)
                 for w in TRAIN_WINDOWS)


def per_count(root: Path, channels: int = 16, epochs: int = EPOCHS, jobs: int = 1) -> dict[str, Any]:
    """Ablation: one model for all channel counts (the shipped one) against a model trained only
    on ``channels``-channel scans of the same worlds and frames (same number of edges and epochs),
    both used without training on the held-out windows at that channel count. Round 0 of each
    held-out run is reused from :func:`evaluate` (copied), so only round 1 differs."""
    wins = per_count_windows(channels)
    memories(root, jobs, wins)
    weights = _train_on(root, wins, root / f"training_{channels}_only", epochs)
    evals = [w for w in EVAL_WINDOWS if w.channels == channels]

    def one(w: Window) -> dict[str, Any]:
        src, dst = root / "eval" / w.name, root / f"eval_{channels}_only" / w.name
        if not (dst / "round_0" / "round.json").is_file():
            if not (src / "round_0" / "round.json").is_file():
                raise FileNotFoundError(f"{src}: run `python -m training.pretrain evaluate` first")
            shutil.copytree(src / "round_0", dst / "round_0", dirs_exist_ok=True)
        m = _slam(dst, w, ["--rounds", "1", "--weights", str(weights), "--densify"])
        shared = json.loads((src / "metrics.json").read_text())
        return {"window": asdict(w), "round0": _figures(m, 0), "per_count": _figures(m, 1),
                "all_counts": _figures(shared, 1)}

    evaluation = read_json_or_none(root / "evaluation.json") or {}  # the all-counts figures are evaluate's
    rows = _parallel(jobs, one, evals)
    summary: dict[str, Any] = {"channels": channels, "n_seeds": len(rows)}
    for k in METRICS:
        a = np.array([r["all_counts"].get(k) for r in rows], float)
        b = np.array([r["per_count"].get(k) for r in rows], float)
        summary[k] = {"all_counts": _mean_std(a), "per_count": _mean_std(b), "per_count_better_in": int(np.sum(b < a))}
    res = {"weights_per_count": str(weights), "weights_per_count_sha256": weights_sha256(weights),
           "all_counts_weights_sha256": evaluation.get("weights_sha256"), "rows": rows, "summary": summary}
    atomic_write_json(root / f"per_count_{channels}.json", res)
    return res


def _of_these_weights(path: Path, sha: str, key: str = "weights_sha256") -> dict[str, Any] | None:
    """The record in ``path`` (None when missing), refused when the weights it names under ``key`` are not
    ``sha``'s (``train`` rerun after ``evaluate``, or a record of before the hash was kept): a card's
    figures describe the weights it ships."""
    record = read_json_or_none(path)
    if record is None:
        return None
    if record.get(key) != sha:
        made_with = record.get(key) or "weights not recorded"
        raise ValueError(f"{path}: made with other weights ({made_with}) than training/model.pt ({sha[:12]}...); "
                         "rerun `python -m training.pretrain evaluate` (and `per-count`) before `install`")
    return record


def card(root: Path) -> dict[str, Any]:
    """The model card: data, sensors, channels, epochs, seeds, evaluation (``pretrained.json``)."""
    tsum = json.loads((root / "training" / "summary.json").read_text())
    sha = weights_sha256(root / "training" / "model.pt")
    ev = _of_these_weights(root / "evaluation.json", sha)
    per_count_files = sorted(root.glob("per_count_*.json"), key=lambda f: (f.name != "per_count_16.json", f.name))
    pc = _of_these_weights(per_count_files[0], sha, "all_counts_weights_sha256") if per_count_files else None
    return {
        "name": "gr_graph pretrained covariance network",
        "format": "training checkpoint (training.trainer.CHECKPOINT_FORMAT), loaded by training.trainer.load_model",
        "built_by": "python -m training.pretrain all --root runs/pretrain",
        "training_data": {"world": "gr_graph synthetic world, 'kitti' preset (residential town, moving actors, "
                                   "KITTI-like sensor errors)",
                          "windows": [asdict(w) for w in TRAIN_WINDOWS],
                          "memories": "round 0 (SLAM on raw scans) of each window: odometry and loop edges",
                          "edges": tsum["dataset"]},
        "epochs": tsum["epochs_done"], "training_seed": tsum["config"]["seed"],
        "net": tsum["config"]["net"], "corr_likelihood": tsum["config"].get("corr_likelihood", "gaussian"),
        "skip_counts": tsum["skip_counts"],
        "training_runtime_s": tsum["runtime_s"]["total"], "provenance": tsum["provenance"],
        "one_model_for_all_channel_counts": pc,
        "evaluation": None if ev is None else {
            "what": "held-out world seeds (never in training): round 0 against one learning round that densifies "
                    "with these weights without training (gr-slam --weights pretrained --densify), "
                    "mean ± std over seeds; relative_change < 0 is better",
            "windows": [asdict(w) for w in EVAL_WINDOWS], "summary": ev["summary"]},
    }


def write_markdown(root: Path, card_doc: dict[str, Any]) -> Path:
    """``benchmarks/results/pretrained.md``: the model card's evaluation as a table."""
    lines = ["# The shipped weights (`--weights pretrained`): model card figures", "",
             f"Built by `{card_doc['built_by']}`; trained {card_doc['epochs']} epochs (seed "
             f"{card_doc['training_seed']}) on {card_doc['training_data']['edges']['n_edges']} edges of "
             f"{len(TRAIN_WINDOWS)} windows: " + ", ".join(
                 f"{w.sensor}{'' if w.channels is None else f' {w.channels} ch'} (seed {w.seed}, frames {w.frames})"
                 for w in TRAIN_WINDOWS) + ".", ""]
    ev = card_doc.get("evaluation")
    if ev:
        lines += [ev["what"] + ".", "",
                  "| channels | seeds | metric | round 0 | pretrained, no training | relative change | better in | "
                  "accepted |", "|---|---|---|---|---|---|---|---|"]
        for ch, d in ev["summary"].items():
            for k in METRICS:
                m = d[k]
                lines.append(f"| {ch} | {d['n_seeds']} | {k} | {m['round0'][0]:.3f} ± {m['round0'][1]:.3f} | "
                             f"{m['pretrained'][0]:.3f} ± {m['pretrained'][1]:.3f} | "
                             f"{100 * m['relative_change'][0]:+.1f} ± {100 * m['relative_change'][1]:.1f} % | "
                             f"{m['better_in']}/{d['n_seeds']} | {d['accepted']}/{d['n_seeds']} |")
        lines.append("")
    pc = card_doc.get("one_model_for_all_channel_counts")
    if pc:
        sm = pc["summary"]
        lines += [f"One model for all channel counts (the shipped one) against one trained only on "
                  f"{sm['channels']}-channel scans of the same worlds and frames (same edges, epochs and seed), both "
                  f"used without training on the held-out {sm['channels']}-channel windows (`python -m training.pretrain "
                  f"per-count --channels {sm['channels']}`), mean ± std over {sm['n_seeds']} seeds:", "",
                  "| metric | all channel counts | per count | per count better in |", "|---|---|---|---|"]
        for k in METRICS:
            m = sm[k]
            lines.append(f"| {k} | {m['all_counts'][0]:.3f} ± {m['all_counts'][1]:.3f} | "
                         f"{m['per_count'][0]:.3f} ± {m['per_count'][1]:.3f} | {m['per_count_better_in']}/{sm['n_seeds']} |")
        lines.append("")
    atomic_write_text(RESULTS_MD, "\n".join(lines) + "\n")
    return RESULTS_MD


def install(root: Path) -> Path:
    """Copy ``root/training/model.pt`` and the card into ``gr_graph/data/`` (what ships)."""
    from gr_graph.pretrained import PRETRAINED_CARD, PRETRAINED_WEIGHTS
    from training.trainer import load_model

    model = root / "training" / "model.pt"
    load_model(model)  # refuse to ship a file that does not load
    doc = card(root)  # before the weights are replaced: a card that cannot be made ships nothing
    PRETRAINED_WEIGHTS.parent.mkdir(parents=True, exist_ok=True)
    tmp = PRETRAINED_WEIGHTS.with_suffix(".tmp")
    shutil.copyfile(model, tmp)
    tmp.replace(PRETRAINED_WEIGHTS)
    atomic_write_json(PRETRAINED_CARD, doc)
    write_markdown(root, doc)
    return PRETRAINED_WEIGHTS


def main(argv: list[str] | None = None) -> int:
    ap = make_parser("python -m training.pretrain", __doc__.split("\n\n")[0],
                     ("python -m training.pretrain all --root runs/pretrain --jobs 2",))
    ap.add_argument("step", choices=("memories", "train", "evaluate", "per-count", "install", "all"))
    ap.add_argument("--channels", type=int, default=16, help="per-count: the channel count of the ablation")
    ap.add_argument("--root", type=Path, default=Path("runs/pretrain"), help="working folder (default: runs/pretrain)")
    ap.add_argument("--jobs", type=int, default=1, help="SLAM runs in parallel (default: 1)")
    ap.add_argument("--epochs", type=int, default=EPOCHS, help=f"training epochs (default: {EPOCHS})")
    add_log_level(ap)
    a = ap.parse_args(argv)
    a.root = a.root.resolve()  # the SLAM runs work in the repository: every path they get is absolute
    setup_logging(a.log_level)
    t0 = time.perf_counter()
    if a.step in ("memories", "all"):
        memories(a.root, a.jobs)
    if a.step in ("train", "all"):
        print(train(a.root, a.epochs))
    if a.step in ("evaluate", "all"):
        print(json.dumps(evaluate(a.root, jobs=a.jobs)["summary"], indent=1))
    if a.step in ("per-count", "all"):
        print(json.dumps(per_count(a.root, a.channels, a.epochs, a.jobs)["summary"], indent=1))
    if a.step in ("install", "all"):
        print(install(a.root))
    log.info("done in %.1f min", (time.perf_counter() - t0) / 60)
    return 0


if __name__ == "__main__":
    sys.exit(main())
