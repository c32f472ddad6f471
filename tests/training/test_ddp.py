"""Data-parallel training with torch DDP on CPU (gloo, 2 processes)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from gr_graph.memory import load_memory
from training.toy_scenes import make_memory, pose_xy_yaw, street_scene
from training.trainer import TrainConfig, Trainer

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parents[2]
NET = {"n_points": 384, "k0": 8, "k1": 8, "k2": 8, "c0": 16, "c1": 32, "c2": 32}
CFG = dict(epochs=1, lr=3e-3, max_corr=200, seed=5, progress=False, net=NET, num_threads=1)


def _worker(rank: int, world: int, mem_dir: str, out: str, init_file: str) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=world)
    try:
        tr = Trainer(load_memory(mem_dir), out, TrainConfig.from_dict(dict(CFG, pairs_per_step=1)), rank=rank, world_size=world)
        tr.fit(resume=False)
        torch.save({"state": tr.model.state_dict(), "grads": [p.grad.clone() for p in tr.model.parameters()]},
                   Path(out) / f"rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def memory_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("ddp") / "memory"
    poses = [pose_xy_yaw(1.0 * k, 0.0, 1.73, 0.02 * k) for k in range(5)]
    mem, _ = make_memory(street_scene(seed=2), poses, [(k, k + 1) for k in range(4)], seed=1, n_corr=400, n_azimuth=360)
    mem.save(d)
    return d


@pytest.mark.slow
def test_ddp_two_processes_average_gradients_like_one_process_on_both_pairs(memory_dir, tmp_path):
    out = tmp_path / "ddp"
    out.mkdir()
    mp.spawn(_worker, args=(2, str(memory_dir), str(out), str(tmp_path / "init")), nprocs=2, join=True)
    r0 = torch.load(out / "rank0.pt", weights_only=False)
    r1 = torch.load(out / "rank1.pt", weights_only=False)
    for k in r0["state"]:
        assert torch.equal(r0["state"][k], r1["state"][k]), k  # identical weights on both ranks
    # the same run in one process with 2 pairs per step (4 pairs -> 2 steps)
    single = Trainer(load_memory(memory_dir), tmp_path / "single", TrainConfig.from_dict(dict(CFG, pairs_per_step=2)))
    single.fit(resume=False)
    for g_ddp, p in zip(r0["grads"], single.model.parameters()):
        np.testing.assert_allclose(g_ddp.numpy(), p.grad.numpy(), rtol=1e-4, atol=1e-6 * p.grad.abs().max().item() + 1e-12)
    for k, v in single.model.state_dict().items():
        np.testing.assert_allclose(r0["state"][k].numpy(), v.numpy(), atol=1e-5)
    assert (out / "model.pt").is_file() and (out / "train_log.jsonl").is_file() and (out / "train_log.rank1.jsonl").is_file()
    edges0 = [int(line.split('"edge": ')[1].split(",")[0]) for line in (out / "train_log.jsonl").read_text().splitlines()]
    edges1 = [int(line.split('"edge": ')[1].split(",")[0]) for line in (out / "train_log.rank1.jsonl").read_text().splitlines()]
    assert sorted(edges0 + edges1) == [0, 1, 2, 3]  # each pair seen exactly once per epoch


@pytest.mark.slow
def test_torchrun_entry_point(memory_dir, tmp_path):
    torchrun = Path(sys.executable).with_name("torchrun")
    cmd = ([str(torchrun)] if torchrun.exists() else [sys.executable, "-m", "torch.distributed.run"])
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run(cmd + ["--standalone", "--nproc_per_node=2", "-m", "training.ddp", "--memory", str(memory_dir),
                              "--out", str(tmp_path / "o"), "--epochs", "1"],
                       cwd=REPO, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "o" / "model.pt").is_file()
