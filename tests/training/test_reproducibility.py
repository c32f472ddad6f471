"""Reproducible training: same memory, configuration, seed and thread count -> the same bytes.

The cause of the differences this guards against: with more than one torch thread the
backward pass of ``features[index]`` accumulates with atomic float adds unless torch's
deterministic algorithms are on, so gradients were rounded differently from run to run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from training.toy_scenes import make_memory, pose_xy_yaw, street_scene
from training.trainer import deterministic_algorithms, save_atomic

REPO = Path(__file__).resolve().parents[2]
SMALL_NET = {"n_points": 512, "k0": 8, "k1": 8, "k2": 8, "c0": 16, "c1": 32, "c2": 32}


def _gather_backward(src: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    x = src.clone().requires_grad_(True)
    (x[idx] * w).sum().backward()
    return x.grad


def test_gather_backward_is_bitwise_repeatable_under_deterministic_algorithms():
    """The network's gather backward with many duplicate indices, two threads (where torch's
    default kernel adds atomically in a varying order), repeated: always the same bits."""
    g = torch.Generator().manual_seed(0)
    src = torch.randn(512, 32, generator=g)
    idx = torch.randint(0, 8, (512, 16), generator=g)  # ~1000 additions into each of 8 rows
    w = torch.randn(512, 16, 32, generator=g) * torch.logspace(-4, 4, 32)  # mixed magnitudes: rounding shows
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        before = torch.are_deterministic_algorithms_enabled()
        with deterministic_algorithms():
            assert torch.are_deterministic_algorithms_enabled()
            ref = _gather_backward(src, idx, w)
            assert all(torch.equal(ref, _gather_backward(src, idx, w)) for _ in range(30))
        assert torch.are_deterministic_algorithms_enabled() == before  # the setting is restored
        # independent reference: the same sums in float64, one row at a time
        expect = torch.zeros(512, 32, dtype=torch.float64)
        expect.index_add_(0, idx.reshape(-1), w.double().reshape(-1, 32))
        scale = expect.abs().amax(0)  # float32 rounding relative to each column's size
        assert bool(((ref.double() - expect).abs() <= 1e-5 * scale).all())
    finally:
        torch.set_num_threads(threads)


def test_save_atomic_bytes_do_not_depend_on_the_temporary_name(tmp_path):
    torch.manual_seed(0)
    obj = {"model_state": torch.nn.Linear(3, 4).state_dict(), "net_config": {"n_points": 8}}
    save_atomic(obj, tmp_path / "a" / "model.pt")
    save_atomic(obj, tmp_path / "b" / "model.pt")
    assert (tmp_path / "a" / "model.pt").read_bytes() == (tmp_path / "b" / "model.pt").read_bytes()
    back = torch.load(tmp_path / "a" / "model.pt", weights_only=False)
    assert all(torch.equal(back["model_state"][k], v) for k, v in obj["model_state"].items())


@pytest.mark.slow
def test_two_training_processes_give_identical_files(tmp_path):
    """``python -m training.train`` twice, two threads each: model.pt, checkpoint.pt and
    train_log.jsonl are byte-identical; summary.json records the provenance."""
    scene = street_scene(seed=1)
    poses = [pose_xy_yaw(1.0 * k, 0.2 * np.sin(k), 1.73, 0.02 * k) for k in range(4)]
    edges = [(0, 1), (1, 2), (2, 3), (0, 2), (1, 3)]
    mem, _ = make_memory(scene, poses, edges, seed=0, n_corr=600, n_azimuth=360)
    mem.save(tmp_path / "memory")
    cfg_file = tmp_path / "cfg.yaml"
    cfg_file.write_text(json.dumps({"max_corr": 300, "lr": 3e-3, "net": SMALL_NET}))
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    outs = []
    for name in ("a", "b"):
        out = tmp_path / name
        r = subprocess.run([sys.executable, "-m", "training.train", "--memory", str(tmp_path / "memory"), "--out", str(out),
                            "--epochs", "2", "--seed", "5", "--threads", "2", "--config", str(cfg_file), "--no-progress"],
                           cwd=REPO, capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        outs.append(out)
    a, b = outs
    log_a = (a / "train_log.jsonl").read_text().splitlines()
    assert len(log_a) == 10 and all("loss" in json.loads(line) for line in log_a)
    for name in ("model.pt", "checkpoint.pt", "train_log.jsonl"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    prov = json.loads((a / "summary.json").read_text())["provenance"]
    assert prov["num_threads"] == 2 and prov["seeds"] == {"training": 5} and prov["device"] == "cpu"
    assert prov["packages"]["torch"] == torch.__version__
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:
        assert prov["git"]["commit"] == head.stdout.strip()
