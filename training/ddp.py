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
import logging
import os
import sys
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist

from gr_graph.memory import load_memory
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
    trainer = Trainer(load_memory(memory_dir), out_dir, cfg, rank=rank, world_size=world)
    path = trainer.fit(resume=resume)
    dist.barrier()
    return path


def main(argv: list[str] | None = None) -> int:
    """torchrun entry point."""
    ap = argparse.ArgumentParser(prog="torchrun ... -m training.ddp")
    ap.add_argument("--memory", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--epochs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--backend", default=None, help="gloo (default on CPU) or nccl")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    backend = args.backend or ("nccl" if args.device == "cuda" else "gloo")
    dist.init_process_group(backend)
    try:
        cfg = {"epochs": args.epochs, "seed": args.seed, "device": args.device, "num_threads": args.threads,
               "progress": dist.get_rank() == 0}
        path = train_distributed(args.memory, args.out, cfg)
        if dist.get_rank() == 0:
            print(path)
    finally:
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
