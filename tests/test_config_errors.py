"""Bad configurations are refused the same way by gr_graph.slam and training.train: the
message names the bad key (by its dotted path and the file) and, for an unknown key, lists
the valid keys of its section, at any nesting level."""

from __future__ import annotations

import json
import re

import pytest
import yaml

from gr_graph.config import ConfigError, SlamConfig, TrainingConfig, load_config
from gr_graph.slam import main as slam_main
from training.config import NetConfig, TrainConfig, TrainConfigError, TrainOptions, load_train_config
from training.train import main as train_main


def _valid_keys(message: str, section: str) -> list[str]:
    """The keys listed after 'valid keys of <section>:' (or 'valid keys:' at the top)."""
    head = f"valid keys of {section}: " if section else "valid keys: "
    m = re.search(re.escape(head) + r"([^)]*)\)", message)
    assert m, message
    return m.group(1).split(", ")


@pytest.mark.parametrize("section, body, key, model", [
    ("", {"epochz": 3}, "epochz", TrainConfig),
    ("net", {"net": {"n_point": 512}}, "net.n_point", NetConfig),
])
def test_train_cli_refuses_unknown_keys_and_lists_valid_ones(tmp_path, capsys, section, body, key, model):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(body))
    rc = train_main(["--memory", str(tmp_path / "unused"), "--out", str(tmp_path / "out"), "--config", str(cfg)])
    err = capsys.readouterr().err
    assert rc == 2
    assert f"unknown key '{key}'" in err and str(cfg) in err
    assert _valid_keys(err, section) == list(model.model_fields)  # exactly the model's keys
    assert not (tmp_path / "out").exists()  # refused before anything was written


def test_slam_cli_refuses_unknown_keys_at_any_level(tmp_path, capsys):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump({"training": {"trainer": {"net": {"hed": "geometric"}}}, "loops": {"radiuss": 3}}))
    rc = slam_main(["--frames", "0:3", "--out", str(tmp_path / "run"), "--config", str(cfg), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and str(cfg) in err
    assert "unknown key 'training.trainer.net.hed'" in err and "unknown key 'loops.radiuss'" in err
    assert _valid_keys(err, "training.trainer.net") == list(NetConfig.model_fields)
    assert "head" in NetConfig.model_fields
    assert _valid_keys(err, "loops") == list(SlamConfig.model_fields["loops"].annotation.model_fields)
    assert not (tmp_path / "run").exists()


def test_slam_config_top_level_and_trainer_section(tmp_path):
    with pytest.raises(ConfigError, match="unknown key 'trainig'") as info:
        load_config(overrides={"trainig": {}})
    assert _valid_keys(str(info.value), "") == list(SlamConfig.model_fields)
    with pytest.raises(ConfigError, match="unknown key 'training.trainer.lrr'") as info:
        load_config(overrides={"training": {"trainer": {"lrr": 1}}})
    assert _valid_keys(str(info.value), "training.trainer") == list(TrainOptions.model_fields)
    assert "epochs" not in TrainOptions.model_fields  # run settings are the pipeline's
    with pytest.raises(ConfigError, match=r"training.trainer: \['seed'\] are set by the pipeline"):
        load_config(overrides={"training": {"trainer": {"seed": 1}}})


def test_ranges_are_validated_with_the_key_named():
    with pytest.raises(TrainConfigError, match="lr: Input should be greater than 0"):
        TrainConfig.from_dict({"lr": 0})
    with pytest.raises(TrainConfigError, match="net.head: Input should be 'geometric' or 'cholesky' \\(got 'spread'\\)"):
        TrainConfig.from_dict({"net": {"head": "spread"}})
    with pytest.raises(TrainConfigError, match="lambda_corr and lambda_pose must not both be 0"):
        TrainConfig.from_dict({"lambda_corr": 0, "lambda_pose": 0})
    with pytest.raises(TrainConfigError, match="device: must be 'cpu', 'cuda' or 'cuda:N'"):
        TrainConfig.from_dict({"device": "gpu"})
    assert TrainConfig.from_dict({"device": "cuda:1"}).device == "cuda:1"
    with pytest.raises(ConfigError, match="training.trainer.max_skip_fraction: Input should be less than or equal to 1"):
        load_config(overrides={"training": {"trainer": {"max_skip_fraction": 1.5}}})
    cfg = TrainConfig()
    with pytest.raises(ValueError, match="min_corr"):
        cfg.min_corr = 2  # assignment is validated too


def test_load_train_config_file_and_overrides(tmp_path):
    f = tmp_path / "cfg.json"
    f.write_text(json.dumps({"lr": 2e-3, "net": {"n_points": 256}}))
    cfg = load_train_config(f, {"epochs": 4})
    assert (cfg.lr, cfg.net.n_points, cfg.epochs, cfg.net.head) == (2e-3, 256, 4, "geometric")
    f.write_text("[1, 2]")
    with pytest.raises(TrainConfigError, match=re.escape(str(f)) + ": a training config file must hold a mapping"):
        load_train_config(f)
    with pytest.raises(FileNotFoundError, match="missing.yaml"):
        load_train_config(tmp_path / "missing.yaml")
    f.write_text("epochs: 010\n")  # leading zeros: decimal, as in the SLAM config (YAML 1.1 read 8)
    assert load_train_config(f).epochs == 10


def test_pipeline_trainer_config_combines_section_and_run_settings():
    tc = TrainingConfig(epochs=2, seed=7, trainer={"lr": 5e-4, "net": {"kw": 4}})
    cfg = tc.trainer_config("cpu", progress=False, init_checkpoint=None)
    assert isinstance(cfg, TrainConfig)
    assert (cfg.epochs, cfg.seed, cfg.lr, cfg.net.kw, cfg.progress) == (2, 7, 5e-4, 4, False)
    # the resolved SLAM configuration round-trips through YAML with the full trainer section
    slam = SlamConfig(training=tc)
    assert SlamConfig.model_validate(yaml.safe_load(yaml.safe_dump(slam.model_dump(mode="json")))) == slam


def test_yaml_on_off_and_sequence_numbers_are_read_as_meant(tmp_path):
    """YAML 1.1 turns an unquoted `off` into False and `05` into 5: the spelling the README uses works."""
    path = tmp_path / "c.yaml"
    for text, deskew, seq in [("odometry: {deskew: off}\ndata: {seq: 05}\n", "off", "05"),
                              ("odometry: {deskew: on}\ndata: {seq: 00}\n", "on", "00"),
                              ("odometry: {deskew: auto}\ndata: {seq: '08'}\n", "auto", "08"),
                              # leading zeros: decimal (YAML 1.2), not YAML 1.1's octal (010 was sequence 08)
                              ("odometry: {deskew: auto}\ndata: {seq: 010}\n", "auto", "10"),
                              ("odometry: {deskew: auto}\ndata: {seq: 08}\n", "auto", "08")]:
        path.write_text(text)
        cfg = load_config(path, {})
        assert (cfg.odometry.deskew, cfg.data.seq) == (deskew, seq), text
    path.write_text("training: {rounds: 010}\ndata: {route_seed: 0x10}\n")  # other integers alike; hex stays hex
    cfg = load_config(path, {})
    assert (cfg.training.rounds, cfg.data.route_seed) == (10, 16)
    path.write_text("data: {frames: 10:50}\n")  # a frame range, not YAML 1.1's base 60 (650)
    assert load_config(path, {}).data.frames == (10, 50)


@pytest.mark.parametrize("content, want", [
    (b"epochs: [1\n", "not valid YAML"),
    (b"\x89PNG\r\n\x1a\n\x00\x00", "not a UTF-8 text file"),
])
def test_train_cli_names_a_config_that_is_not_yaml(tmp_path, capsys, content, want):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_bytes(content)
    rc = train_main(["--memory", str(tmp_path / "unused"), "--out", str(tmp_path / "out"), "--config", str(cfg)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith(f"error: {cfg}: {want}")
    assert not (tmp_path / "out").exists()


def test_train_cli_refuses_a_slam_rounds_own_training_folder(tmp_path, capsys):
    """Default --out beside the memory is not round_<r>/training, which holds the model round r used; that
    folder given as --out is refused before anything is read or written."""
    from training.train import DEFAULT_OUT_NAME, build_parser

    run = tmp_path / "runs" / "slam"
    rc = train_main(["--memory", str(run / "round_1" / "memory"), "--out", str(run / "round_1" / "training")])
    err = capsys.readouterr().err
    assert rc == 2 and "the training folder of a gr-slam round" in err and not run.exists()
    assert DEFAULT_OUT_NAME != "training" and f"<memory>/../{DEFAULT_OUT_NAME}" in build_parser().format_help()
    # a folder merely called training elsewhere is the user's to choose
    rc = train_main(["--memory", str(tmp_path / "missing"), "--out", str(tmp_path / "training")])
    assert rc == 2 and "gr-slam round" not in capsys.readouterr().err
