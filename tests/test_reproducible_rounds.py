"""A whole ``--rounds 1`` run is reproducible: two processes, same seed -> the same round 1.

Before training was made deterministic, round 1's trajectory of this run differed between
two processes (the network's weights did), while round 0's did not.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

REPO = Path(__file__).resolve().parents[1]

# 10 synthetic frames at 16 channels, one epoch of a small network with two torch threads
# (the race that made training vary needs more than one thread).
CONFIG = {
    "training": {
        "epochs": 1,
        "trainer": {"max_corr": 300, "lr": 3e-3, "num_threads": 2,
                    "net": {"n_points": 512, "k0": 8, "k1": 8, "k2": 8, "c0": 16, "c1": 32, "c2": 32, "kw": 8}},
    },
    "output": {"plot": False},
}


@pytest.mark.slow
def test_two_rounds_runs_give_identical_round_1(tmp_path):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(CONFIG))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    runs = []
    for name in ("a", "b"):
        out = tmp_path / name
        r = subprocess.run([sys.executable, "-m", "gr_graph.slam", "--frames", "0:10", "--channels", "16", "--rounds", "1",
                            "--synthetic-preset", "clean",
                            "--out", str(out), "--config", str(cfg), "--quiet", "--log-level", "WARNING"],
                           cwd=REPO, capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        runs.append(out)
    a, b = runs
    for r in ("round_0", "round_1"):
        with np.load(a / r / "marginals.npz") as za, np.load(b / r / "marginals.npz") as zb:
            for key in ("poses", "covariance", "edge_information"):
                np.testing.assert_array_equal(za[key], zb[key], err_msg=f"{r}: {key}")
        assert (a / r / "poses_tum.txt").read_bytes() == (b / r / "poses_tum.txt").read_bytes(), r
    model_a, model_b = (torch.load(x / "round_1" / "training" / "model.pt", weights_only=False) for x in runs)
    for key, value in model_a["model_state"].items():
        assert torch.equal(value, model_b["model_state"][key]), key
    assert (a / "round_1" / "training" / "model.pt").read_bytes() == (b / "round_1" / "training" / "model.pt").read_bytes()
    with np.load(a / "round_0" / "marginals.npz") as z0, np.load(a / "round_1" / "marginals.npz") as z1:
        assert not np.array_equal(z0["poses"], z1["poses"])  # round 1 is a new trajectory, not a copy
