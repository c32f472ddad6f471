"""Trainer (Algorithm 1): learning signal, exact resume, CLI / library entry, robustness."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gr_graph.memory import Memory, load_memory
from training.dataset import PairDataset, SkipSample
from training.network import NetConfig
from training.predict import predict_covariances
from training.toy_scenes import make_memory, pose_xy_yaw, street_scene
from training.train import main as train_main
from training.train import train_from_memory
from training.trainer import (
    CHECKPOINT_FORMAT,
    CheckpointMismatch,
    TrainConfig,
    TrainConfigError,
    Trainer,
    TrainingError,
    load_model,
)

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parents[2]
SMALL_NET = {"n_points": 512, "k0": 8, "k1": 8, "k2": 8, "c0": 16, "c1": 32, "c2": 32}


def _memory(n_scans=4, seed=0, extra_edges=()):
    scene = street_scene(seed=1)
    poses = [pose_xy_yaw(1.0 * k, 0.2 * np.sin(k), 1.73, 0.02 * k) for k in range(n_scans)]
    edges = [(k, k + 1) for k in range(n_scans - 1)] + list(extra_edges)
    mem, normals = make_memory(scene, poses, edges, seed=seed, n_corr=600, n_azimuth=360)
    return mem


@pytest.fixture(scope="module")
def memory_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("mem") / "memory"
    _memory(extra_edges=[(0, 2), (1, 3)]).save(d)
    return d


def _cfg(**kw):
    base = dict(epochs=2, lr=3e-3, max_corr=300, seed=3, checkpoint_every=2, progress=False, net=SMALL_NET)
    base.update(kw)
    return TrainConfig.from_dict(base)


class _Kill(Exception):
    """Stands for a kill of the training process."""


def _kill_at(key: str, value: int):
    """A ``fit`` callback that kills the run at the first step record whose ``key`` is ``value``."""
    def callback(rec):
        if rec[key] == value:
            raise _Kill()
    return callback


def _log(out):
    return [json.loads(line) for line in (Path(out) / "train_log.jsonl").read_text().splitlines()]


def test_dataset_sample_is_consistent_and_deterministic(memory_dir):
    mem = load_memory(memory_dir)
    ds = PairDataset(mem, NetConfig(**SMALL_NET), max_corr=300, seed=0)
    s = ds.sample(1, epoch=0)
    e = mem.edge(1)
    Q = np.asarray(mem.scan(e.l))
    assert len(s.q_points) == 512 and len(s.p_corr) <= 300
    # the network input row of every correspondence holds exactly its target point
    np.testing.assert_array_equal(s.q_points[s.q_index].astype(np.float64), s.q_corr)
    assert np.isin(s.q_corr, Q).all()
    s2 = ds.sample(1, epoch=0)
    np.testing.assert_array_equal(s.q_points, s2.q_points)
    assert not np.array_equal(ds.sample(1, epoch=1).q_points, s.q_points)


def test_edges_whose_registration_failed_are_not_trained_on(memory_dir):
    """Flagged edges (info["flagged_edges"]: the odometry's constant-velocity fallback) are left out; every
    other edge gives the sample it gave before, drawn with its own edge number."""
    mem = load_memory(memory_dir)
    net = NetConfig(**SMALL_NET)
    every = PairDataset(mem, net, max_corr=300, seed=0)
    flagged = dataclasses.replace(mem, info={**mem.info, "flagged_edges": [1, 3, 5, -1]})  # 5, -1: no such edge
    assert flagged.flagged_edges == {1, 3} and mem.flagged_edges == frozenset()
    ds = PairDataset(flagged, net, max_corr=300, seed=0)
    assert len(every) == mem.n_edges == 5 and len(ds) == 3
    assert [ds.sample(i).edge for i in range(len(ds))] == [0, 2, 4]
    for i, e in enumerate((0, 2, 4)):
        np.testing.assert_array_equal(ds.sample(i, epoch=1).q_points, every.sample(e, epoch=1).q_points)
    d = ds.describe()
    assert (d["n_edges"], d["n_flagged_left_out"], d["n_odometry"] + d["n_loop"]) == (3, 2, 3)
    assert "n_flagged_left_out" not in every.describe()  # a checkpoint written before still resumes
    for outside in (3, -1):
        with pytest.raises(IndexError):
            ds.sample(outside)


def test_training_logs_memory_edge_numbers_and_refuses_a_memory_of_flagged_edges(memory_dir, tmp_path):
    from training.train import load_training_memory

    mem = load_memory(memory_dir)
    flagged = dataclasses.replace(mem, info={**mem.info, "flagged_edges": [1, 3]})
    Trainer(flagged, tmp_path / "run", _cfg(epochs=1)).fit(resume=False)
    assert sorted(r["edge"] for r in _log(tmp_path / "run")) == [0, 2, 4]  # the memory's, not positions 0-2
    dataclasses.replace(mem, info={**mem.info, "flagged_edges": list(range(mem.n_edges))}).save(tmp_path / "all")
    with pytest.raises(TrainingError, match=r"all: all 5 edges of the memory are flagged"):
        load_training_memory(tmp_path / "all")


def test_losses_decrease_on_short_run(memory_dir, tmp_path):
    cfg = _cfg(epochs=6, corr_likelihood="gaussian")  # the paper's NLL (the t's scale moves less: not this bound)
    Trainer(load_memory(memory_dir), tmp_path, cfg).fit(resume=False)
    recs = _log(tmp_path)
    first = np.mean([r["corr"] for r in recs if r["epoch"] == 0])
    last = np.mean([r["corr"] for r in recs if r["epoch"] == 5])
    assert last < first - 1.0, (first, last)  # nats per correspondence
    pf = np.mean([r["pose"] for r in recs if r["epoch"] == 0])
    pl = np.mean([r["pose"] for r in recs if r["epoch"] == 5])
    assert pl < pf, (pf, pl)
    assert all(r.get("skipped") is None for r in recs)


def test_resume_after_kill_equals_uninterrupted_run(memory_dir, tmp_path):
    mem = load_memory(memory_dir)
    cfg = _cfg(epochs=2)
    ref_path = Trainer(mem, tmp_path / "a", cfg).fit(resume=False)

    class Kill(Exception):
        pass

    n = {"steps": 0}

    def killer(rec):
        n["steps"] += 1
        if n["steps"] == 7:  # mid epoch 2 (5 pairs per epoch), checkpoint at step 2 of epoch 2
            raise Kill()

    with pytest.raises(Kill):
        Trainer(mem, tmp_path / "b", cfg).fit(resume=False, callback=killer)
    ck = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    assert (ck["epoch"], ck["step"]) == (1, 2)
    path = Trainer(mem, tmp_path / "b", cfg).fit(resume=True)
    a = torch.load(ref_path, weights_only=False)["model_state"]
    b = torch.load(path, weights_only=False)["model_state"]
    for k in a:
        assert torch.equal(a[k], b[k]), k
    la, lb = _log(tmp_path / "a"), _log(tmp_path / "b")
    assert [(r["epoch"], r["step"], r["edge"]) for r in la] == [(r["epoch"], r["step"], r["edge"]) for r in lb]
    assert [r["loss"] for r in la] == [r["loss"] for r in lb]
    # a different configuration must not silently resume
    with pytest.raises(TrainingError, match="different configuration"):
        Trainer(mem, tmp_path / "b", _cfg(epochs=3, lr=1e-2)).fit(resume=True)


def test_a_finished_training_run_again_keeps_the_summary_of_the_run_that_trained(memory_dir, tmp_path, caplog):
    mem = load_memory(memory_dir)
    cfg = _cfg(epochs=1, num_threads=1)
    out = tmp_path / "t"
    Trainer(mem, out, cfg).fit(resume=False)
    first = json.loads((out / "summary.json").read_text())
    assert first["runtime_s"]["steps"] == 5 and first["threads_used"] == [1]
    model_bytes = (out / "model.pt").read_bytes()
    try:  # the same finished run again, with another thread count: nothing to train, nothing rewritten
        Trainer(mem, out, _cfg(epochs=1, num_threads=2)).fit(resume=True)
    finally:
        torch.set_num_threads(1)
    again = json.loads((out / "summary.json").read_text())
    assert again == first and (out / "model.pt").read_bytes() == model_bytes
    # from scratch (no resume) the summary is rewritten with this run's steps
    Trainer(mem, out, cfg).fit(resume=False)
    assert json.loads((out / "summary.json").read_text())["runtime_s"]["steps"] == 5


def test_a_resumed_run_never_keeps_another_runs_model(memory_dir, tmp_path):
    """Run A finished in a folder; run B starts there from scratch, is killed after its first epoch, and is
    resumed asking for that one epoch: the result is B's weights and summary, not A's files."""
    mem = load_memory(memory_dir)
    out = tmp_path / "t"
    Trainer(mem, out, _cfg(epochs=1, lr=3e-3)).fit(resume=False)
    with pytest.raises(_Kill):
        Trainer(mem, out, _cfg(epochs=2, lr=1e-2)).fit(resume=False, callback=_kill_at("epoch", 1))
    assert not (out / "model.pt").exists() and not (out / "summary.json").exists()  # A's: gone at B's start
    ck = torch.load(out / "checkpoint.pt", weights_only=False)
    assert ck["epoch"] == 1
    # even with A's files put back, they are not taken for B's
    a_dir = tmp_path / "a"
    Trainer(mem, a_dir, _cfg(epochs=1, lr=3e-3)).fit(resume=False)
    for name in ("model.pt", "summary.json"):
        (out / name).write_bytes((a_dir / name).read_bytes())
    path = Trainer(mem, out, _cfg(epochs=1, lr=1e-2)).fit(resume=True)
    got = torch.load(path, weights_only=False)["model_state"]
    assert all(torch.equal(got[k], ck["model_state"][k]) for k in got)
    assert json.loads((out / "summary.json").read_text())["config"]["lr"] == 1e-2


def test_a_resume_with_another_thread_count_says_so_and_records_both(memory_dir, tmp_path, caplog):
    mem = load_memory(memory_dir)
    out = tmp_path / "t"
    with pytest.raises(_Kill):
        Trainer(mem, out, _cfg(epochs=1, num_threads=1)).fit(resume=False, callback=_kill_at("step", 2))
    assert torch.load(out / "checkpoint.pt", weights_only=False)["threads_used"] == [1]
    try:
        with caplog.at_level("WARNING", logger="training.trainer"):
            Trainer(mem, out, _cfg(epochs=1, num_threads=2)).fit(resume=True)
    finally:
        torch.set_num_threads(1)
    assert "resumed with 2 torch thread(s), the steps before ran with [1]" in caplog.text
    assert json.loads((out / "summary.json").read_text())["threads_used"] == [1, 2]


def test_train_cli_names_a_path_that_cannot_be_a_folder(memory_dir, tmp_path, capsys):
    blocker = tmp_path / "afile"
    blocker.write_text("not a folder")
    code = train_main(["--memory", str(memory_dir), "--out", str(blocker / "sub"), "--epochs", "1", "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "afile" in err


def test_train_cli_warns_that_zero_epochs_write_an_untrained_network(memory_dir, tmp_path, caplog):
    with caplog.at_level("WARNING", logger="training.train"):
        assert train_main(["--memory", str(memory_dir), "--out", str(tmp_path / "t"), "--epochs", "0",
                           "--no-progress"]) == 0
    assert "--epochs 0 without an init_checkpoint" in caplog.text and (tmp_path / "t" / "model.pt").is_file()


@pytest.mark.slow
def test_train_from_memory_cli_and_predict(memory_dir, tmp_path):
    cfg = {"epochs": 1, "progress": False, "max_corr": 200, "net": SMALL_NET}
    path = train_from_memory(memory_dir, tmp_path / "lib", cfg)
    assert path.name == "model.pt" and path.is_file()
    assert torch.load(path, weights_only=False)["format_version"] == CHECKPOINT_FORMAT
    summary = json.loads((tmp_path / "lib" / "summary.json").read_text())
    assert summary["epochs_done"] == 1 and summary["dataset"]["n_edges"] == 5
    prov = summary["provenance"]  # what made these weights
    assert prov["seeds"] == {"training": 0} and prov["device"] == "cpu"
    assert prov["num_threads"] == torch.get_num_threads() == 1  # set at the top of this module
    assert prov["packages"]["torch"] == torch.__version__ and prov["packages"]["numpy"] == np.__version__
    assert set(prov["git"]) == {"commit", "dirty"}
    assert summary["runtime_s"]["steps"] == 5 and summary["runtime_s"]["total"] > 0
    assert all("time_s" not in r for r in _log(tmp_path / "lib"))  # wall time never in the log
    pts = np.asarray(load_memory(memory_dir).scan(0))[:1500]
    C = predict_covariances(path, pts)
    assert C.shape == (1500, 3, 3) and np.all(np.linalg.eigvalsh(C) > 0)
    np.testing.assert_array_equal(C, predict_covariances(load_model(path), pts))  # deterministic
    # CLI (in-process and as a module)
    cfg_file = tmp_path / "cfg.yaml"
    cfg_file.write_text(json.dumps({"max_corr": 200, "net": SMALL_NET}))
    assert train_main(["--memory", str(memory_dir), "--epochs", "1", "--out", str(tmp_path / "cli"), "--config", str(cfg_file), "--no-progress"]) == 0
    a = torch.load(path, weights_only=False)["model_state"]
    b = torch.load(tmp_path / "cli" / "model.pt", weights_only=False)["model_state"]
    assert all(torch.equal(a[k], b[k]) for k in a)  # same seed, same config -> same weights
    r = subprocess.run([sys.executable, "-m", "training.train", "--memory", str(tmp_path / "missing")],
                       cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 2 and "no meta.json" in r.stderr


def test_bad_config_is_rejected():
    with pytest.raises(TrainConfigError, match="unknown key 'epochz'.*valid keys: lr, .*epochs, seed"):
        TrainConfig.from_dict({"epochz": 1})
    with pytest.raises(TrainConfigError, match="corr_reduction: Input should be 'mean' or 'sum'"):
        TrainConfig.from_dict({"corr_reduction": "median"})
    with pytest.raises(TrainConfigError, match="seed: Input should be greater than or equal to 0"):
        TrainConfig.from_dict({"seed": -1})  # numpy's generators take no negative seed: refused at once


def test_a_memory_without_edges_is_refused_by_name(tmp_path):
    scans = [np.asarray(_memory(n_scans=2).scan(0))]
    Memory.from_scans(scans, np.eye(4)[None], [], [], [], [], []).save(tmp_path / "empty")
    with pytest.raises(TrainingError, match=r"empty: the memory has no edges to train on"):
        train_from_memory(tmp_path / "empty", tmp_path / "out", _cfg())


def test_student_t_correspondence_likelihood_reaches_the_loss(memory_dir, tmp_path):
    """``corr_likelihood: student_t`` makes a pair's correspondence term the t's (losses.corr_nll, checked
    against scipy there); the options enter the checkpoint resume key only when set."""
    from training.losses import corr_nll

    mem = load_memory(memory_dir)
    terms = {}
    for name, kw in {"gaussian": {"corr_likelihood": "gaussian"}, "t4": {},  # the t is the default
                     "t9": {"corr_likelihood": "student_t", "corr_dof": 9.0}}.items():
        tr = Trainer(mem, tmp_path / name, _cfg(lambda_pose=0.0, **kw))
        sample = tr.dataset.sample(1, epoch=0)
        with torch.no_grad():
            C = tr.forward(sample)
            _, info = tr.pair_loss(sample, C)
        T = torch.as_tensor(sample.T_hat)
        d = torch.as_tensor(sample.q_corr) - torch.as_tensor(sample.p_corr) @ T[:3, :3].T - T[:3, 3]
        Cq = C.to(torch.float64)[torch.as_tensor(sample.q_index)]
        want = corr_nll(Cq, d, "mean", tr.config.corr_likelihood, tr.config.corr_dof).item()
        assert info["corr"] == pytest.approx(want, rel=1e-12)
        terms[name] = info["corr"]
        key = tr.config.resume_key()
        assert ("corr_likelihood" in key) == (name != "gaussian") and ("corr_dof" in key) == (name == "t9")
    assert len({round(v, 9) for v in terms.values()}) == 3
    with pytest.raises(TrainConfigError, match="corr_likelihood: Input should be 'gaussian' or 'student_t'"):
        TrainConfig.from_dict({"corr_likelihood": "cauchy"})
    with pytest.raises(TrainConfigError, match="corr_dof"):
        TrainConfig.from_dict({"corr_likelihood": "student_t", "corr_dof": 0})


def _memory_with_bad_pairs():
    """3 good scans and 2 of a line: edges 0-1 train, edge 2 has no correspondences (empty_pair), edge 3
    lies on a line (degenerate_H)."""
    mem = _memory(n_scans=3)
    # edge 2: no correspondences; edge 3: correspondences on 20 collinear-ish points only
    scans = [np.asarray(mem.scan(k)) for k in range(3)]
    line = np.zeros((40, 3), np.float32)
    line[:, 0] = np.linspace(1, 20, 40)
    scans.append(line)
    scans.append(line.copy())
    edges = [tuple(map(int, mem.edges[e])) for e in range(mem.n_edges)] + [(0, 2), (3, 4)]
    corr = [mem.edge(e).corr for e in range(mem.n_edges)] + [np.zeros((0, 2), np.int32), np.stack([np.arange(40)] * 2, 1)]
    return Memory.from_scans(scans, np.stack([np.eye(4)] * 5), edges, [0] * 4,
                             [mem.edge_T[0], mem.edge_T[1], np.eye(4), np.eye(4)], [np.eye(6)] * 4, corr)


def test_empty_and_degenerate_pairs_are_skipped_and_counted(tmp_path):
    m2 = _memory_with_bad_pairs()
    tr = Trainer(m2, tmp_path, _cfg(epochs=1, net={**SMALL_NET, "n_points": 256}))
    with pytest.raises(SkipSample):
        tr.dataset.sample(2)
    tr.fit(resume=False)
    assert tr.skip_counts["empty_pair"] == 1 and tr.skip_counts["degenerate_H"] == 1
    assert all(torch.isfinite(p).all() for p in tr.model.parameters())
    recs = _log(tmp_path)
    assert sorted(r.get("skipped") or "" for r in recs) == ["", "", "degenerate_H", "empty_pair"]
    # too many bad pairs abort with a clear error
    with pytest.raises(TrainingError, match="skipped"):
        Trainer(m2, tmp_path / "x", _cfg(epochs=1, max_skip_fraction=0.2, net={**SMALL_NET, "n_points": 256})).fit(resume=False)


def test_a_failed_epoch_fails_again_when_its_run_is_repeated(tmp_path):
    """The epoch's skipped pairs are in the checkpoint: a rerun resumes from the last one written in the
    failed epoch and fails again, not only counting the pairs after it."""
    m2 = _memory_with_bad_pairs()
    cfg = _cfg(epochs=1, checkpoint_every=1, max_skip_fraction=0.3, net={**SMALL_NET, "n_points": 256})
    with pytest.raises(TrainingError, match="2 of ~4 pairs skipped"):
        Trainer(m2, tmp_path, cfg).fit(resume=False)
    st = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert (st["epoch"], st["step"]) == (0, 3)  # the last checkpoint written before the epoch's end
    with pytest.raises(TrainingError, match="2 of ~4 pairs skipped"):
        Trainer(m2, tmp_path, cfg).fit(resume=True)
    assert not (tmp_path / "model.pt").exists()


def test_steps_lost_to_nonfinite_gradients_count_as_skipped_pairs(memory_dir, tmp_path):
    """Every gradient non-finite: no weight moves, and the run fails instead of writing the initial weights."""
    tr = Trainer(load_memory(memory_dir), tmp_path, _cfg(epochs=1))
    tr.model.head.weight.register_hook(lambda grad: grad * float("nan"))
    with pytest.raises(TrainingError, match="5 of ~5 pairs skipped"):
        tr.fit(resume=False)
    assert tr.skip_counts["nonfinite_grad"] == 5 and not (tmp_path / "model.pt").exists()


def test_checkpoints_that_cannot_be_continued_are_refused_by_name(memory_dir, tmp_path):
    mem = load_memory(memory_dir)
    Trainer(mem, tmp_path, _cfg(epochs=2)).fit(resume=False)
    ck = tmp_path / "checkpoint.pt"
    # 2 epochs trained are not a 1-epoch model
    with pytest.raises(CheckpointMismatch, match=r"checkpoint.pt.*2 epochs trained, 1 asked for"):
        Trainer(mem, tmp_path, _cfg(epochs=1)).fit(resume=True)
    # more epochs continue it (epochs are not part of the resume key)
    Trainer(mem, tmp_path, _cfg(epochs=3)).fit(resume=True)
    assert torch.load(tmp_path / "model.pt", weights_only=True)["epochs_done"] == 3
    # an unreadable checkpoint names the file; training from scratch replaces it
    ck.write_bytes(ck.read_bytes()[:200])
    with pytest.raises(CheckpointMismatch, match=r"checkpoint.pt: unreadable checkpoint"):
        Trainer(mem, tmp_path, _cfg(epochs=1)).fit(resume=True)
    Trainer(mem, tmp_path, _cfg(epochs=1)).fit(resume=False)
    assert torch.load(ck, weights_only=True)["epoch"] == 1
    # other training data with the same counts (two memories of 5 edges): not resumed
    other = tmp_path / "other_memory"
    _memory(seed=5, extra_edges=[(0, 2), (1, 3)]).save(other)
    with pytest.raises(CheckpointMismatch, match="other training data"):
        Trainer(load_memory(other), tmp_path, _cfg(epochs=2)).fit(resume=True)
    # a checkpoint written before the hash was kept (counts only) still resumes on the same counts
    Trainer(mem, tmp_path, _cfg(epochs=1)).fit(resume=False)
    st = torch.load(ck, weights_only=True)
    st["dataset"] = {k: v for k, v in st["dataset"].items() if k != "edges_sha256"}
    torch.save(st, ck)
    Trainer(mem, tmp_path, _cfg(epochs=2)).fit(resume=True)
    assert torch.load(tmp_path / "model.pt", weights_only=True)["epochs_done"] == 2


def test_damaged_or_newer_checkpoints_are_refused_by_name_and_leave_the_start_alone(memory_dir, tmp_path):
    """A readable checkpoint of bad content (weights of another shape, a broken RNG state) or of a newer
    format is a CheckpointMismatch naming it (the pipeline retrains on it), not a bare error; the
    trainer's weights stay its starting weights."""
    mem = load_memory(memory_dir)
    Trainer(mem, tmp_path, _cfg(epochs=1)).fit(resume=False)
    ck = tmp_path / "checkpoint.pt"
    good = torch.load(ck, weights_only=True)
    damaged = {
        "weights": {**good, "model_state": {k: v for k, v in good["model_state"].items() if not k.endswith("bias")}},
        "rng": {**good, "torch_rng": torch.zeros(3, dtype=torch.uint8)},
        "newer": {**good, "format_version": good["format_version"] + 1},
        "version": {**good, "format_version": "x"},
        "epoch": {**good, "epoch": "one"},
        "device": {**good, "device": "no-such-device"},
    }
    for name, st in damaged.items():
        torch.save(st, ck)
        tr = Trainer(mem, tmp_path, _cfg(epochs=2))
        start = {k: v.clone() for k, v in tr.model.state_dict().items()}
        want = "newer than this gr_graph reads" if name == "newer" else "damaged checkpoint"
        with pytest.raises(CheckpointMismatch, match=rf"checkpoint.pt: .*{want}.*--no-resume"):
            tr.try_resume()
        assert all(torch.equal(start[k], v) for k, v in tr.model.state_dict().items()), name
        assert tr.optimizer.state_dict()["state"] == {}, name  # the checkpoint's Adam moments not kept
        assert tr.epoch == 0 and tr.step == 0


def test_a_run_killed_before_its_first_checkpoint_leaves_no_log_lines_behind(memory_dir, tmp_path):
    mem = load_memory(memory_dir)
    cfg = _cfg(epochs=1, checkpoint_every=100)
    Trainer(mem, tmp_path / "a", cfg).fit(resume=False)

    class Kill(Exception):
        pass

    def killer(rec):
        if rec["step"] == 2:
            raise Kill()

    with pytest.raises(Kill):
        Trainer(mem, tmp_path / "b", cfg).fit(resume=False, callback=killer)
    assert not (tmp_path / "b" / "checkpoint.pt").exists() and len(_log(tmp_path / "b")) == 3
    Trainer(mem, tmp_path / "b", cfg).fit(resume=True)
    assert _log(tmp_path / "b") == _log(tmp_path / "a")


def test_nonfinite_network_output_and_gradient_never_reach_the_weights(memory_dir, tmp_path):
    mem = load_memory(memory_dir)
    # 2 pairs skipped and 1 step's pair lost of 5: allowed here
    tr = Trainer(mem, tmp_path, _cfg(epochs=1, checkpoint_every=100, max_skip_fraction=0.8))
    before = {k: v.clone() for k, v in tr.model.state_dict().items()}
    real_forward = tr.model.forward
    calls = {"n": 0}

    def bad_forward(points, nb):
        calls["n"] += 1
        L, C = real_forward(points, nb)
        if calls["n"] in (1, 2):
            C = C.clone()
            C[5, 0, 0] = float("nan")
        return L, C

    tr.model.forward = bad_forward
    hooks = []
    # a NaN gradient in step 3: the update must not be applied
    state = {"step": 0}

    def hook(grad):
        return grad * float("nan") if state["step"] == 2 else grad

    hooks.append(tr.model.head.weight.register_hook(hook))

    def cb(rec):
        state["step"] += 1
        if state["step"] == 2:  # the two poisoned steps must not have moved any weight
            for k, v in tr.model.state_dict().items():
                assert torch.equal(v, before[k]), k

    tr.fit(resume=False, callback=cb)
    assert tr.skip_counts["nonfinite_output"] == 2
    assert tr.skip_counts["nonfinite_grad"] == 1
    assert all(torch.isfinite(v).all() for v in tr.model.state_dict().values())
    assert any(not torch.equal(v, before[k]) for k, v in tr.model.state_dict().items())  # later steps trained


def test_trains_from_a_memory_written_by_gr_graph_slam(kitti_root, tmp_path):
    """Integration: gr_graph.slam on real KITTI frames (16 channels) -> memory -> trainer."""
    config = pytest.importorskip("gr_graph.config")
    r = subprocess.run([sys.executable, "-m", "gr_graph.slam", "--data-root", str(kitti_root), "--frames", "0:6",
                        "--channels", "16", "--out", str(tmp_path / "slam"), "--quiet", "--no-loops"],
                       cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    mem_dir = tmp_path / "slam" / "round_0" / "memory"
    mem = load_memory(mem_dir)
    assert mem.n_edges >= 5
    # the pipeline's configuration of a learning round, from its pydantic `training` section
    section = config.SlamConfig().training
    cfg = section.trainer_config("cpu", progress=False)
    cfg.epochs, cfg.max_corr = 1, 300
    cfg.net = NetConfig(**SMALL_NET)
    path = train_from_memory(mem_dir, tmp_path / "train", cfg)
    summary = json.loads((tmp_path / "train" / "summary.json").read_text())
    assert summary["skip_counts"] == {} and summary["epochs_done"] == 1
    recs = _log(tmp_path / "train")
    assert len(recs) == mem.n_edges and all(np.isfinite(r["loss"]) for r in recs)
    C = predict_covariances(path, np.asarray(mem.scan(0)))
    assert C.shape == (len(mem.scan(0)), 3, 3) and np.linalg.eigvalsh(C).min() > 0


@pytest.mark.slow
def test_sigkill_mid_epoch_then_resume_equals_uninterrupted_cli_run(memory_dir, tmp_path):
    """A real kill (SIGKILL) of ``python -m training.train``; rerunning the command resumes."""
    import os
    import signal
    import time

    cfg_file = tmp_path / "cfg.yaml"
    cfg_file.write_text(json.dumps({"max_corr": 200, "checkpoint_every": 1, "net": SMALL_NET}))
    base = [sys.executable, "-m", "training.train", "--memory", str(memory_dir), "--epochs", "12", "--seed", "4",
            "--config", str(cfg_file), "--threads", "1", "--no-progress"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    ref = subprocess.run(base + ["--out", str(tmp_path / "ref")], cwd=REPO, capture_output=True, text=True, env=env)
    assert ref.returncode == 0, ref.stderr[-2000:]
    out = tmp_path / "killed"
    proc = subprocess.Popen(base + ["--out", str(out)], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    ck = out / "checkpoint.pt"
    t0 = time.time()
    while time.time() - t0 < 120:
        if ck.exists():
            st = torch.load(ck, weights_only=False)
            if st["epoch"] >= 2 and st["step"] >= 2:
                break
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "model.pt").exists(), "the run finished before it could be killed"
    st = torch.load(ck, weights_only=False)
    assert st["epoch"] < 12
    again = subprocess.run(base + ["--out", str(out)], cwd=REPO, capture_output=True, text=True, env=env)
    assert again.returncode == 0, again.stderr[-2000:]
    a = torch.load(tmp_path / "ref" / "model.pt", weights_only=False)["model_state"]
    b = torch.load(out / "model.pt", weights_only=False)["model_state"]
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert [r["loss"] for r in _log(tmp_path / "ref")] == [r["loss"] for r in _log(out)]
