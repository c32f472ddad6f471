"""The shipped weights (``--weights pretrained``): resolution, model card, one densification;
``gr-slam --weights PATH [--densify]``; training on several memories at once."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from gr_graph.config import SlamConfig, TrainingConfig
from gr_graph.densify import densify_cloud
from gr_graph.memory import load_memory
from gr_graph.pipeline import check_learning_config, round_fingerprint
from gr_graph.pretrained import PRETRAINED_CARD, PRETRAINED_WEIGHTS, model_card, resolve_weights
from gr_graph.slam import full_method_hint
from gr_graph.slam import main as slam_main
from training.dataset import ConcatPairDataset, PairDataset, SkipSample
from training.network import CovarianceNet, NetConfig
from training.toy_scenes import make_memory, pose_xy_yaw, street_scene
from training.train import train_from_memory
from training.trainer import CHECKPOINT_FORMAT, TrainConfig, load_model, save_atomic

torch.set_num_threads(1)
SMALL_NET = {"n_points": 512, "k0": 8, "k1": 8, "k2": 8, "c0": 16, "c1": 32, "c2": 32}


def street_cloud(seed: int = 0) -> np.ndarray:
    """Ground, two walls and clutter around the origin."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-15, 15, (8000, 2))
    xy = xy[np.linalg.norm(xy, axis=1) > 4.0]
    ground = np.column_stack([xy, -1.73 + rng.normal(0, 0.01, len(xy))])
    wall = np.column_stack([rng.uniform(-15, 15, 3000), np.full(3000, 9.0), rng.uniform(-1.7, 4, 3000)])
    clutter = rng.uniform([-10, -10, 0], [10, 10, 3], (500, 3))
    return np.vstack([ground, wall, wall * [1, -1, 1], clutter])


# ---------------------------------------------------------------- the shipped weights
def test_shipped_weights_load_and_densify_one_cloud() -> None:
    path = resolve_weights("pretrained")
    assert path == PRETRAINED_WEIGHTS and path.stat().st_size < 5_000_000  # "a few MB at most"
    model = load_model(path)
    card = model_card()
    assert card["net"] == model.config.to_dict()  # the card describes this checkpoint
    assert card["epochs"] >= 1 and len(card["training_data"]["windows"]) >= 3
    sensors = {w["sensor"] for w in card["training_data"]["windows"]}
    assert {"hdl64e", "vlp16", "os1-64"} <= sensors
    pts = street_cloud()
    dense = densify_cloud(pts)  # default weights: the shipped ones
    C = dense.covariances
    assert dense.fallback is None and len(dense.points) > 0
    assert np.isfinite(dense.points).all() and np.isfinite(C).all()
    assert (np.linalg.eigvalsh(C)[:, 0] > 0).all()
    # a trained model: the wall's covariances are thin across the wall (y) and wide along it
    on_wall = np.abs(np.abs(dense.points[:, 1]) - 9.0) < 0.3
    assert on_wall.sum() > 50
    Cw = C[on_wall]
    assert np.median(Cw[:, 1, 1]) < 0.5 * np.median(Cw[:, 0, 0]), (np.median(Cw[:, 1, 1]), np.median(Cw[:, 0, 0]))


def test_model_card_has_the_evaluation_on_held_out_seeds() -> None:
    card = json.loads(PRETRAINED_CARD.read_text())
    ev = card["evaluation"]
    assert ev is not None
    train_seeds = {w["seed"] for w in card["training_data"]["windows"]}
    eval_seeds = {w["seed"] for w in ev["windows"]}
    assert not train_seeds & eval_seeds and len(eval_seeds) >= 3
    assert ev["summary"]
    for per_channel in ev["summary"].values():
        assert per_channel["n_seeds"] >= 3
        assert np.isfinite(per_channel["rpe300_all_pairs_mean"]["relative_change"]).all()


def test_weights_that_are_missing_or_broken_are_named(tmp_path: Path, capsys) -> None:
    with pytest.raises(FileNotFoundError, match="nothere.pt"):
        resolve_weights(tmp_path / "nothere.pt")
    junk = tmp_path / "junk.pt"
    junk.write_text("not a checkpoint")
    assert slam_main(["--weights", str(junk), "--frames", "0:5", "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert "junk.pt" in capsys.readouterr().err
    assert slam_main(["--densify", "--frames", "0:5", "--out", str(tmp_path / "run")]) == 2
    assert "(--densify) needs training.weights (--weights pretrained|PATH)" in capsys.readouterr().err
    assert slam_main(["--weights", str(junk), "--rounds", "0", "--out", str(tmp_path / "run")]) == 2
    assert "cannot go with --rounds 0" in capsys.readouterr().err
    assert slam_main(["--weights", str(junk), "--densify", "--rounds", "2", "--out", str(tmp_path / "run")]) == 2
    assert "exactly one learning round" in capsys.readouterr().err
    assert slam_main(["--weights", str(junk), "--densify", "--no-memory", "--out", str(tmp_path / "run")]) == 2
    assert "write_memory" in capsys.readouterr().err
    assert not (tmp_path / "run" / "metrics.json").exists()
    given = tmp_path / "weights.yaml"  # the weights from --config: --densify takes them
    given.write_text(f"training:\n  weights: {junk}\n")
    assert slam_main(["--config", str(given), "--densify", "--frames", "0:5", "--out", str(tmp_path / "run")]) == 2
    assert "junk.pt" in capsys.readouterr().err  # refused for what the file is, not for a missing --weights


def test_densify_runs_one_round_and_fine_tuning_needs_the_same_network(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="one learning round"):
        TrainingConfig(weights="pretrained", fine_tune=False, rounds=2)
    with pytest.raises(ValueError, match="needs training.weights"):
        TrainingConfig(fine_tune=False, rounds=1)
    torch.manual_seed(0)
    net = CovarianceNet(NetConfig(**{**SMALL_NET, "c1": 16}))
    path = tmp_path / "other_net.pt"
    save_atomic({"format_version": CHECKPOINT_FORMAT, "model_state": net.state_dict(),
                 "net_config": net.config.to_dict()}, path)
    cfg = SlamConfig.model_validate({"training": {"rounds": 1, "weights": str(path),
                                                  "trainer": {"net": SMALL_NET}}})
    with pytest.raises(ValueError, match="differs from training.trainer.net"):
        check_learning_config(cfg)
    cfg.training.fine_tune = False  # using them as they are needs no matching trainer network
    check_learning_config(cfg)


def test_round_fingerprint_follows_the_weights_file(tmp_path: Path) -> None:
    path = tmp_path / "m.pt"
    torch.manual_seed(0)
    net = CovarianceNet(NetConfig(**SMALL_NET))
    save_atomic({"format_version": CHECKPOINT_FORMAT, "model_state": net.state_dict(),
                 "net_config": net.config.to_dict()}, path)
    cfg = SlamConfig.model_validate({"training": {"rounds": 1, "weights": str(path), "fine_tune": False}})
    before = round_fingerprint(cfg, 1), round_fingerprint(cfg, 0)
    torch.manual_seed(1)
    net2 = CovarianceNet(NetConfig(**SMALL_NET))
    save_atomic({"format_version": CHECKPOINT_FORMAT, "model_state": net2.state_dict(),
                 "net_config": net2.config.to_dict()}, path)
    assert round_fingerprint(cfg, 1) != before[0]  # same name, other weights: round 1 is redone
    assert round_fingerprint(cfg, 0) == before[1]  # round 0 does not depend on them


def test_the_hint_after_round_0_is_the_same_command_with_a_learning_round() -> None:
    hint = full_method_hint(["my bag/", "--seq", "00", "--out", "runs/x", "--viz", "--rounds", "0", "--no-resume",
                             "--no-memory", "--weights=old.pt"])
    cmd = hint.split(": ", 1)[1]
    assert cmd.startswith("python -m gr_graph.slam 'my bag/' --seq 00 --out runs/x --rounds 1")
    for gone in ("--viz", "--rounds 0", "--no-resume", "--no-memory", "old.pt"):
        assert gone not in cmd
    assert cmd.count("--rounds") == 1
    assert "--weights" not in cmd  # trained from scratch: fine-tuning the shipped weights gained less (README)
    import shlex

    from gr_graph.slam import build_parser

    args = build_parser().parse_args(shlex.split(cmd)[3:])  # the hint parses as a command
    assert args.rounds == 1 and args.out == "runs/x" and args.weights is None


# ---------------------------------------------------------------- --weights PATH --densify in a run
def _rerun_with_weights(learning_run, out: Path, *extra: str) -> tuple[Path, Path]:
    """The short learning run's command into ``out`` with ``--weights`` (its round-1 model) and
    ``extra``; returns (the original run dir, the weights)."""
    run, argv = learning_run
    weights = run / "round_1" / "training" / "model.pt"
    args = list(argv)
    args[args.index("--out") + 1] = str(out)
    assert slam_main([*args, "--weights", str(weights), *extra]) == 0
    return run, weights


@pytest.mark.slow
def test_densify_with_given_weights_skips_training(learning_run, tmp_path: Path) -> None:
    out = tmp_path / "densify_run"
    run, _ = _rerun_with_weights(learning_run, out, "--densify")
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["rounds"]) == {"0", "1"}
    r1 = m["rounds"]["1"]
    assert not (out / "round_1" / "training").exists()  # no training
    assert r1["densify"]["frames"] == m["n_frames"] and "accepted" in r1
    # the same weights on the same scans densify alike: as many points as the trained run's round 1
    ref = json.loads((run / "metrics.json").read_text())["rounds"]["1"]
    assert r1["densify"] == ref["densify"]


@pytest.mark.slow
def test_weights_start_the_learning_round(learning_run, tmp_path: Path) -> None:
    out = tmp_path / "finetune_run"
    run, weights = _rerun_with_weights(learning_run, out)
    summary = json.loads((out / "round_1" / "training" / "summary.json").read_text())
    assert summary["config"]["init_checkpoint"] == str(weights)
    start = load_model(weights).state_dict()
    tuned = load_model(out / "round_1" / "training" / "model.pt").state_dict()
    assert any(not torch.equal(start[k], tuned[k]) for k in start)  # trained further, from those weights
    # the first training step starts from the given weights: its loss is the trained model's, far
    # below the first loss of the run that started from random weights
    def first_loss(d: Path) -> tuple[int, float]:
        recs = [json.loads(x) for x in (d / "round_1" / "training" / "train_log.jsonl").read_text().splitlines()]
        rec = next(r for r in recs if "loss" in r)
        return rec["edge"], rec["loss"]

    (edge, loss), (edge_scratch, loss_scratch) = first_loss(out), first_loss(run)
    assert edge == edge_scratch and loss < loss_scratch, (loss, loss_scratch)  # same seed: same first pair


# ---------------------------------------------------------------- training on several memories
def _memory(seed: int, n_scans: int = 3):
    scene = street_scene(seed=seed)
    poses = [pose_xy_yaw(1.0 * k, 0.2 * np.sin(k), 1.73, 0.02 * k) for k in range(n_scans)]
    mem, _ = make_memory(scene, poses, [(k, k + 1) for k in range(n_scans - 1)], seed=seed, n_corr=600,
                         n_azimuth=360)
    return mem


def test_concat_dataset_maps_global_edges_to_their_memory(tmp_path: Path) -> None:
    mems = [_memory(1, 3), _memory(2, 4)]
    ds = ConcatPairDataset(mems, NetConfig(**SMALL_NET), max_corr=300, seed=5)
    parts = [PairDataset(m, NetConfig(**SMALL_NET), max_corr=300, seed=ConcatPairDataset.memory_seed(5, i))
             for i, m in enumerate(mems)]
    assert len({ConcatPairDataset.memory_seed(5, i) for i in range(2)}) == 2
    assert len(ds) == 2 + 3
    assert [ds.locate(e) for e in range(5)] == [(0, 0), (0, 1), (1, 0), (1, 1), (1, 2)]
    s = ds.sample(3, epoch=1)
    ref = parts[1].sample(1, epoch=1)
    assert s.edge == 3 and (s.k, s.l) == (ref.k, ref.l)
    np.testing.assert_array_equal(s.q_points, ref.q_points)
    assert ds.describe()["n_edges"] == 5 and ds.describe()["n_memories"] == 2
    with pytest.raises(IndexError):
        ds.sample(5)
    with pytest.raises(ValueError):
        ConcatPairDataset([], NetConfig(**SMALL_NET))
    ds.datasets[0].min_corr = 10_000  # every pair of memory 0 too small: the skip names the memory
    with pytest.raises(SkipSample, match="memory 0"):
        ds.sample(0)


def test_train_from_several_memories(tmp_path: Path) -> None:
    dirs = []
    for s in (1, 2):
        d = tmp_path / f"mem{s}"
        _memory(s).save(d)
        dirs.append(d)
    cfg = TrainConfig.from_dict(dict(epochs=1, lr=3e-3, max_corr=300, seed=0, progress=False, net=SMALL_NET))
    model = train_from_memory(dirs, tmp_path / "train", cfg)
    summary = json.loads((tmp_path / "train" / "summary.json").read_text())
    n = sum(load_memory(d).n_edges for d in dirs)
    assert summary["dataset"]["n_edges"] == n and summary["dataset"]["n_memories"] == 2
    log = [json.loads(x) for x in (tmp_path / "train" / "train_log.jsonl").read_text().splitlines()]
    assert sorted(r["edge"] for r in log) == list(range(n))  # every edge of both memories, once
    assert load_model(model).config.to_dict() == NetConfig(**SMALL_NET).to_dict()
    # the finished checkpoint is not resumed for other training data (one memory instead of two)
    with pytest.raises(RuntimeError, match="other training data"):
        train_from_memory(dirs[:1], tmp_path / "train", cfg)


def test_resume_key_follows_the_starting_weights(tmp_path: Path) -> None:
    path = tmp_path / "init.pt"
    path.write_bytes(b"one")
    cfg = TrainConfig.from_dict(dict(init_checkpoint=str(path), net=SMALL_NET))
    before = cfg.resume_key()
    path.write_bytes(b"two")  # same path, other weights: a finished fine-tuning is not resumed
    assert cfg.resume_key() != before


def test_pretrain_summary_is_mean_and_spread_over_seeds() -> None:
    from training.pretrain import EVAL_WINDOWS, TRAIN_WINDOWS, per_count_windows, summarize

    assert not {w.seed for w in TRAIN_WINDOWS} & {w.seed for w in EVAL_WINDOWS}  # held out
    assert [w.seed for w in per_count_windows(16)] == [w.seed for w in TRAIN_WINDOWS]
    rows = [{"window": {"channels": 16}, "round0": {"ate_rmse": a}, "pretrained": {"ate_rmse": b, "accepted": b < a}}
            for a, b in ((1.0, 0.5), (2.0, 3.0), (4.0, 2.0))]
    s = summarize(rows)["16"]
    assert s["n_seeds"] == 3 and s["accepted"] == 2
    ate = s["ate_rmse"]
    np.testing.assert_allclose(ate["round0"], [7 / 3, np.std([1.0, 2.0, 4.0])])
    np.testing.assert_allclose(ate["relative_change"], [np.mean([-0.5, 0.5, -0.5]), np.std([-0.5, 0.5, -0.5])])
    assert ate["better_in"] == 2


def test_pretrain_trains_with_the_shipped_weights_likelihood(tmp_path: Path, monkeypatch) -> None:
    """The shipped weights were trained with the Gaussian likelihood (the default until 2026-12-05):
    ``training.pretrain`` rebuilds them with it, and the card says which."""
    import training.pretrain as pretrain
    import training.train as train_mod

    seen = {}

    def fake_train(mems, out, cfg, **kw):
        seen["cfg"] = cfg
        return out / "model.pt"

    monkeypatch.setattr(train_mod, "train_from_memory", fake_train)
    for w in pretrain.TRAIN_WINDOWS:
        pretrain._memory_dir(tmp_path, w).mkdir(parents=True)
    pretrain.train(tmp_path, epochs=1)
    assert seen["cfg"].corr_likelihood == "gaussian" and TrainConfig().corr_likelihood == "student_t"


def test_pretrain_install_ships_nothing_when_the_card_cannot_be_made(tmp_path: Path, monkeypatch) -> None:
    import gr_graph.pretrained as pretrained
    import training.pretrain as pretrain

    weights, card_path = tmp_path / "ship" / "pretrained.pt", tmp_path / "ship" / "pretrained.json"
    weights.parent.mkdir()
    weights.write_bytes(b"the weights that ship now")
    monkeypatch.setattr(pretrained, "PRETRAINED_WEIGHTS", weights)
    monkeypatch.setattr(pretrained, "PRETRAINED_CARD", card_path)
    root = tmp_path / "root"
    (root / "training").mkdir(parents=True)
    save_atomic({"format_version": CHECKPOINT_FORMAT, "model_state": CovarianceNet(NetConfig(**SMALL_NET)).state_dict(),
                 "net_config": NetConfig(**SMALL_NET).to_dict()}, root / "training" / "model.pt")
    with pytest.raises(FileNotFoundError, match="summary.json"):  # killed before the summary was written
        pretrain.install(root)
    assert weights.read_bytes() == b"the weights that ship now" and not card_path.exists()
    # an evaluation of other weights (train rerun after evaluate, or of before the hash was kept) is refused
    summary = {"dataset": {"n_edges": 1}, "epochs_done": 1, "config": {"seed": 0, "net": SMALL_NET},
               "skip_counts": {}, "runtime_s": {"total": 1.0}, "provenance": {}}
    (root / "training" / "summary.json").write_text(json.dumps(summary))
    sha = pretrain.weights_sha256(root / "training" / "model.pt")
    for recorded in ("0" * 64, None):
        (root / "evaluation.json").write_text(json.dumps({"weights_sha256": recorded, "summary": {}}))
        with pytest.raises(ValueError, match=r"evaluation.json: made with other weights .*rerun"):
            pretrain.install(root)
        assert weights.read_bytes() == b"the weights that ship now" and not card_path.exists()
    (root / "evaluation.json").write_text(json.dumps({"weights_sha256": sha, "summary": {}}))
    (root / "per_count_32.json").write_text(json.dumps({"all_counts_weights_sha256": "1" * 64, "summary": {}}))
    with pytest.raises(ValueError, match=r"per_count_32.json: made with other weights"):  # any channel count's
        pretrain.card(root)
    (root / "per_count_32.json").write_text(json.dumps({"all_counts_weights_sha256": sha,
                                                        "weights_per_count_sha256": "2" * 64,
                                                        "summary": {"channels": 32}}))
    doc = pretrain.card(root)
    assert doc["one_model_for_all_channel_counts"]["summary"]["channels"] == 32 and doc["evaluation"] is not None


def test_resume_key_holds_the_starting_weights_content_not_their_path(tmp_path: Path) -> None:
    """The same file named relative or absolute, or copied to a moved run folder, is the same start."""
    (tmp_path / "a").mkdir()
    path = tmp_path / "a" / "init.pt"
    path.write_bytes(b"one")
    copy = tmp_path / "b.pt"
    copy.write_bytes(b"one")
    keys = [TrainConfig.from_dict(dict(init_checkpoint=str(p), net=SMALL_NET)).resume_key()
            for p in (path, copy, Path(os.path.relpath(path)))]
    assert keys[0] == keys[1] == keys[2] and "init_checkpoint" not in keys[0]
