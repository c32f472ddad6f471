"""Multi-process data-parallel training with torch DDP (launch with torchrun).

::

    torchrun --nproc_per_node=2 -m training.ddp --memory DIR --out DIR [--epochs N] [--backend gloo]

Every process loads the memory (memory-mapped, so the scans are shared through the page
cache), builds the same network from the same seed and trains its share of each step's pairs
(see :mod:`training.trainer`); DDP averages the gradients so all ranks keep identical
weights. Rank 0 writes ``checkpoint.pt``, ``model.pt``, ``train_log.jsonl``; other ranks log to
``train_log.rank<r>.jsonl``. Use ``gloo`` on CPU and ``nccl`` with ``--device cuda``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

import torch.distributed as dist

from gr_graph.cli_common import (
    add_device,
    add_log_level,
    add_no_progress,
    add_out,
    add_seed,
    add_threads,
    make_parser,
    setup_logging,
)
from training.train import load_training_memory
from training.trainer import TrainConfig, Trainer

__all__ = ["train_distributed", "main"]


def train_distributed(memory_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str], config: TrainConfig | dict[str, Any] | None = None, resume: bool = True) -> Path:
    """Train inside an initialised process group (one call per rank); returns ``model.pt``'s path."""
    if not dist.is_initialized():
        raise RuntimeError("train_distributed needs torch.distributed to be initialised (use torchrun)")
    cfg = config if isinstance(config, TrainConfig) else TrainConfig.from_dict(config)
    rank, world = dist.get_rank(), dist.get_world_size()
    if cfg.device.startswith("cuda"):
        cfg.device = f"cuda:{int(os.environ.get('LOCAL_RANK', rank))}"
    trainer = Trainer(load_training_memory(memory_dir), out_dir, cfg, rank=rank, world_size=world)
    path = trainer.fit(resume=resume)
    dist.barrier()
    return path


EXAMPLES = (
    "torchrun --nproc_per_node=2 -m training.ddp --memory runs/slam/round_0/memory --out runs/ddp",
    "torchrun --nproc_per_node=2 -m training.ddp --memory runs/slam/round_0/memory --out runs/ddp --epochs 3 --seed 1",
    "torchrun --nproc_per_node=2 -m training.ddp --memory runs/slam/round_0/memory --out runs/ddp_gpu "
    "--device cuda --backend nccl",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``torchrun ... -m training.ddp``."""
    ap = make_parser("torchrun ... -m training.ddp", __doc__.split("\n\n")[0], EXAMPLES)
    ap.add_argument("--memory", required=True, metavar="DIR", help="memory directory (written by gr_graph.slam)")
    add_out(ap, "output directory", required=True)
    ap.add_argument("--epochs", type=int, default=1, metavar="N", help="epochs")
    add_seed(ap, "seed of the weights and of all sampling (the same on every rank)")
    add_device(ap, "torch device (cuda: one GPU per rank)")
    ap.add_argument("--backend", choices=("gloo", "nccl", "mpi", "ucc"), default=None,
                    help="process-group backend (default: gloo on CPU, nccl with --device cuda)")
    add_threads(ap, "torch threads per process", default=1)
    add_no_progress(ap)
    add_log_level(ap)
    return ap


def main(argv: list[str] | None = None) -> int:
    """torchrun entry point."""
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level)
    backend = args.backend or ("nccl" if args.device == "cuda" else "gloo")
    dist.init_process_group(backend)
    try:
        cfg = {"epochs": args.epochs, "seed": args.seed, "device": args.device, "num_threads": args.threads,
               "progress": dist.get_rank() == 0 and not args.no_progress}
        path = train_distributed(args.memory, args.out, cfg)
        if dist.get_rank() == 0:
            print(path)
    finally:
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
