"""Command line and library entry point of the trainer (Algorithm 1).

CLI::

    python -m training.train --memory DIR [DIR ...] [--epochs N] [--out DIR] [--device cpu|cuda] [--seed S]
                             [--config cfg.yaml] [--no-resume]

Library (used by ``gr_graph.slam`` between reciprocal rounds)::

    from training.train import train_from_memory
    model_path = train_from_memory(memory_dir, out_dir, {"epochs": 2})

An existing ``out_dir/checkpoint.pt`` written with the same configuration is resumed, so an
interrupted run is continued by simply running the same command again.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import sys
from pathlib import Path
from collections.abc import Sequence
from typing import Any

from gr_graph.cli_common import (
    add_config,
    add_device,
    add_log_level,
    add_no_progress,
    add_out,
    add_seed,
    add_threads,
    make_parser,
    setup_logging,
)
from gr_graph.memory import Memory, load_memory
from training.config import TrainConfig, load_train_config
from training.trainer import Trainer, TrainingError

log = logging.getLogger(__name__)

__all__ = ["train_from_memory", "main"]


def train_from_memory(
    memory_dir: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    config: TrainConfig | dict[str, Any] | None = None,
    resume: bool = True,
) -> Path:
    """Train f_theta on the memory in ``memory_dir``; return the path of the final ``model.pt``.

    Parameters
    ----------
    memory_dir : path or sequence of paths
        A memory written by ``gr_graph.memory.Memory.save`` (e.g. by ``gr_graph.slam``), or
        several: their edges are trained on together (several sequences, sensors, channel counts).
    out_dir : path
        Output folder: ``model.pt`` (load with ``training.trainer.load_model`` or pass it to
        ``training.predict.predict_covariances``), ``checkpoint.pt``, ``train_log.jsonl``,
        ``summary.json``.
    config : TrainConfig, dict or pydantic model, optional
        Training hyper-parameters (keys as :class:`training.config.TrainConfig`, with
        ``"net"`` a dict of :class:`training.config.NetConfig`); an unknown key is an error.
        Use ``init_checkpoint`` to continue from the previous round's ``model.pt``.
    resume : bool
        Continue from ``out_dir/checkpoint.pt`` if it exists (same configuration required).

    Raises
    ------
    gr_graph.memory.MemoryFormatError
        If the memory cannot be read.
    training.config.TrainConfigError
        On a bad configuration (unknown key, value out of range).
    training.trainer.TrainingError
        On an incompatible checkpoint or too many unusable pairs.
    """
    cfg = config if isinstance(config, TrainConfig) else TrainConfig.from_dict(config)
    dirs = [memory_dir] if isinstance(memory_dir, (str, os.PathLike)) else list(memory_dir)
    if not dirs:
        raise ValueError("train_from_memory: no memory given")
    memories = [load_training_memory(d) for d in dirs]
    return Trainer(memories if len(memories) > 1 else memories[0], out_dir, cfg).fit(resume=resume)


def load_training_memory(memory_dir: str | os.PathLike[str]) -> Memory:
    """The memory in ``memory_dir`` (logged), refused naming the folder when it has no edge to train on."""
    memory = load_memory(memory_dir)
    log.info("training on %s: %d scans, %d edges", memory_dir, memory.n_scans, memory.n_edges)
    if memory.n_edges == 0:
        raise TrainingError(f"{memory_dir}: the memory has no edges to train on (fewer than two usable scans?)")
    if len(memory.flagged_edges) == memory.n_edges:
        raise TrainingError(f"{memory_dir}: all {memory.n_edges} edges of the memory are flagged (their registration "
                            "failed in SLAM): none to train on")
    return memory


#: Default output folder's name, beside the memory's folder: not ``training``, which in a gr-slam run's
#: ``round_<r>`` folder holds the model that round used.
DEFAULT_OUT_NAME = "gr_train"


def refuse_pipeline_training_folder(out: str | os.PathLike[str]) -> None:
    """Raise ValueError when ``out`` is a gr-slam round's ``round_<r>/training`` folder: training into it
    would replace (or, on a checkpoint mismatch, refuse) the model that round used and the next warm-starts from."""
    p = Path(out).resolve()
    if p.name == "training" and re.fullmatch(r"round_\d+", p.parent.name):
        raise ValueError(f"{out}: the training folder of a gr-slam round (its model.pt is what {p.parent.name} "
                         "used); use another --out")


EXAMPLES = (
    "python -m training.train --memory runs/slam/round_0/memory --out runs/train --epochs 2",
    "python -m training.train --memory runs/slam/round_0/memory --out runs/train --config train.yaml --device cuda",
    "python -m training.train --memory runs/slam/round_0/memory --out runs/train --seed 1 --threads 1 --no-progress",
    "python -m training.train --memory runs/a/round_0/memory runs/b/round_0/memory --out runs/train_ab",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m training.train``; options left out keep ``--config``'s value."""
    d = TrainConfig()
    ap = make_parser("python -m training.train", __doc__.split("\n\n")[0] + " Options override --config.", EXAMPLES)
    ap.add_argument("--memory", required=True, nargs="+", metavar="DIR",
                    help="memory directory (written by gr_graph.slam); several: trained on together")
    add_out(ap, f"output directory (default: <memory>/../{DEFAULT_OUT_NAME}; a gr-slam round's own "
                "round_<r>/training folder is refused)")
    add_config(ap, "YAML/JSON file with TrainConfig keys (an unknown key is an error)")
    ap.add_argument("--epochs", type=int, default=None, metavar="N", help=f"epochs (default: {d.epochs})")
    add_seed(ap, f"seed of the weights and of all sampling (default: {d.seed})", default=None)
    add_device(ap, f"torch device (default: {d.device})", default=None)
    add_threads(ap, "torch threads (default: torch's own choice)", default=None)
    ap.add_argument("--no-resume", action="store_true", help="ignore an existing checkpoint")
    add_no_progress(ap)
    add_log_level(ap)
    return ap


def _parse(argv: list[str] | None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """CLI entry; returns the exit code."""
    args = _parse(argv)
    setup_logging(args.log_level)
    overrides: dict[str, Any] = {}
    for key, val in (("epochs", args.epochs), ("device", args.device), ("seed", args.seed), ("num_threads", args.threads)):
        if val is not None:
            overrides[key] = val
    if args.no_progress:
        overrides["progress"] = False
    out = Path(args.out) if args.out else Path(args.memory[0]).resolve().parent / DEFAULT_OUT_NAME
    try:
        refuse_pipeline_training_folder(out)
        cfg = load_train_config(args.config, overrides)
        if cfg.epochs == 0 and not cfg.init_checkpoint:
            log.warning("--epochs 0 without an init_checkpoint: %s will hold the untrained network's random "
                        "weights", out / "model.pt")
        path = train_from_memory(args.memory, out, cfg, resume=not args.no_resume)
    except (ValueError, RuntimeError, OSError) as exc:  # OSError: a full disk, a file where a folder goes
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
