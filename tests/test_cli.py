"""Every command line: the same flag for the same thing, help with defaults and examples that
parse, fixed choices that fail with exit code 2 and a message."""

from __future__ import annotations

import argparse
import logging
import os
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from gr_graph import densify_cli, global_registration, slam
from gr_graph.cli_common import LOG_LEVELS, setup_logging
from gr_graph.datasets import realism
from gr_graph.datasets.synthetic import __main__ as synthetic_export
from gr_graph.datasets.synthetic import plots as synthetic_plots
from gr_graph.experiments import cli as experiments_cli
from gr_graph.trajectory import read_kitti_poses
from training import ddp, train

REPO = Path(__file__).resolve().parents[1]

# module, its main, the arguments it requires, the shared flags it must have
CLIS: dict[str, tuple[Callable[[], argparse.ArgumentParser], Callable[[list[str]], int], list[str], set[str]]] = {
    "gr_graph.slam": (slam.build_parser, slam.main, [],
                      {"--config", "--out", "--seed", "--device", "--frames", "--channels", "--data-root",
                       "--point-format", "--no-progress", "--log-level"}),
    "training.train": (train.build_parser, train.main, ["--memory", "M"],
                       {"--config", "--out", "--seed", "--device", "--threads", "--no-progress", "--log-level"}),
    "training.ddp": (ddp.build_parser, ddp.main, ["--memory", "M", "--out", "O"],
                     {"--out", "--seed", "--device", "--threads", "--no-progress", "--log-level"}),
    "gr_graph.global_registration": (global_registration.build_parser, global_registration.main, ["--out", "O"],
                                     {"--out", "--seed", "--channels", "--data-root", "--point-format",
                                      "--no-progress", "--log-level"}),
    "gr_graph.datasets.synthetic": (synthetic_export.build_parser, synthetic_export.main, ["--out", "O"],
                                    {"--out", "--seed", "--frames", "--channels", "--point-format", "--threads",
                                     "--no-progress", "--log-level"}),
    "gr_graph.datasets.synthetic.plots": (synthetic_plots.build_parser, synthetic_plots.main, [],
                                          {"--out", "--seed", "--log-level"}),
    "gr_graph.densify_cli": (densify_cli.build_parser, densify_cli.main, ["IN.pcd", "OUT.ply", "--weights", "W"],
                             {"--seed", "--device", "--point-format", "--log-level"}),
    "gr_graph.experiments": (experiments_cli.build_parser, experiments_cli.main, ["table1"],
                             {"--device", "--log-level"}),
    "gr_graph.datasets.realism": (realism.build_parser, realism.main, ["DIR"],
                                  {"--out", "--point-format", "--no-progress", "--log-level"}),
}
OLD_SPELLINGS = {"--quiet", "--n-rings"}


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {opt: a for a in parser._actions for opt in a.option_strings if a.help != argparse.SUPPRESS}


@pytest.mark.parametrize("module", sorted(CLIS))
def test_help_exits_0_and_shows_the_shared_flags_defaults_and_examples(module, capsys) -> None:
    build, main, _, shared = CLIS[module]
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for flag in shared:
        assert flag in text, f"{module} --help lacks {flag}"
    assert not OLD_SPELLINGS & set(text.split()), f"{module} --help shows an old spelling"
    assert "--log-level {DEBUG,INFO,WARNING,ERROR}" in text and "examples:" in text
    # every option with a default says it (written in its help or added by the formatter)
    parser = build()
    formatter = parser._get_formatter()
    for opt, action in _options(parser).items():
        if action.default is not None and action.default is not False and action.nargs != 0:
            assert "default:" in formatter._get_help_string(action), f"{module} {opt}"


@pytest.mark.parametrize("module", sorted(CLIS))
def test_the_help_examples_parse(module) -> None:
    build, *_ = CLIS[module]
    parser = build()
    examples = [line.strip() for line in parser.epilog.splitlines()[1:] if line.strip()]
    assert 2 <= len(examples) <= 6
    for cmd in examples:
        words = shlex.split(cmd)
        assert module in words, cmd
        parser.parse_args(words[words.index(module) + 1:])  # SystemExit (a test failure) if invalid


def test_a_shared_flag_means_the_same_everywhere() -> None:
    seen: dict[str, tuple[str, object, object, str]] = {}
    for module, (build, *_rest) in CLIS.items():
        for opt, a in _options(build()).items():
            if opt in ("-h", "--help"):
                continue
            sig = (a.dest, tuple(a.choices) if a.choices else None, getattr(a.type, "__name__", a.type), module)
            if opt in seen:
                assert seen[opt][:3] == sig[:3], f"{opt}: {seen[opt]} vs {sig}"
            seen[opt] = sig


BAD_CHOICES = {"--log-level": "nonsense", "--channels": "48", "--device": "tpu", "--point-format": "xyzrgb",
               "--backend": "tcp", "--solvers": "icp", "--deskew": "sometimes", "--synthetic-preset": "noisy",
               "--preset": "noisy", "--world": "urban", "--dataset": "pcap", "--sensor": "hdl32e", "--budget": "huge",
               "--loop-variance": "sometimes", "--registration-covariance": "sandwich",
               "--learned-noise-covariance": "sandwich"}
BAD_CASES = [(module, flag) for module, (build, *_) in sorted(CLIS.items()) for flag in BAD_CHOICES
             if flag in _options(build())]


@pytest.mark.parametrize(("module", "flag"), BAD_CASES)
def test_bad_choices_exit_2_with_a_message(module, flag, capsys) -> None:
    _, main, required, _ = CLIS[module]
    with pytest.raises(SystemExit) as exc:
        main(required + [flag, BAD_CHOICES[flag]])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: invalid choice" in err and "choose from" in err


def test_every_flag_with_choices_is_exercised() -> None:
    for module, (build, *_) in CLIS.items():
        with_choices = {opt for opt, a in _options(build()).items() if a.choices}
        assert with_choices <= set(BAD_CHOICES), f"{module}: add bad values for {with_choices - set(BAD_CHOICES)}"


def test_slam_choices_are_the_configurations_values() -> None:
    from gr_graph.config import DataConfig, GraphConfig, OdometryConfig, TrainingConfig, option_choices

    expected = {"--synthetic-preset": (DataConfig, "synthetic_preset", ("clean", "kitti", "raw")),  # optional: no None
                "--deskew": (OdometryConfig, "deskew", ("auto", "on", "off")),
                "--loop-variance": (GraphConfig, "loop_variance", ("fixed", "estimated", "estimated_axes")),
                "--registration-covariance": (GraphConfig, "registration_covariance",
                                              ("scaled_hessian", "cluster_robust")),
                "--learned-noise-covariance": (TrainingConfig, "learned_noise_covariance",
                                               ("hessian", "cluster_robust", "cluster_robust_offset"))}
    actions = _options(slam.build_parser())
    for flag, (section, option, values) in expected.items():
        assert option_choices(section, option) == values
        assert tuple(actions[flag].choices) == values, flag
    with pytest.raises(TypeError, match="GraphConfig.cluster_size is not a Literal"):
        option_choices(GraphConfig, "cluster_size")


def test_log_level_is_case_insensitive_and_applied() -> None:
    for module, (build, _, required, _) in CLIS.items():
        assert build().parse_args(required + ["--log-level", "warning"]).log_level == "WARNING"
        assert build().parse_args(required).log_level in LOG_LEVELS
    root = logging.getLogger()
    before = root.level
    try:
        for level in LOG_LEVELS:
            setup_logging(level.lower())
            assert root.level == getattr(logging, level)
    finally:
        root.setLevel(before)
    with pytest.raises(ValueError, match="choose one of DEBUG, INFO, WARNING, ERROR"):
        setup_logging("nonsense")


def test_python_m_slam_refuses_a_bad_log_level() -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-m", "gr_graph.slam", "--log-level", "nonsense"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "--log-level: invalid choice: 'NONSENSE'" in proc.stderr


def test_slam_flags_become_config_overrides(capsys) -> None:
    args = slam.build_parser().parse_args(["--seed", "7", "--point-format", "xyz", "--no-progress", "--channels", "16"])
    o = slam.overrides_from_args(args)
    assert o["seed"] == 7 and o["training"]["seed"] == 7
    assert o["data"] == {"point_format": "xyz", "channels": 16}
    assert o["output"] == {"progress": False}
    assert slam.overrides_from_args(slam.build_parser().parse_args([])) == {}
    o = slam.overrides_from_args(slam.build_parser().parse_args(["--deskew", "on", "--kitti-vertical-correction", "0.205"]))
    assert o == {"odometry": {"deskew": "on"}, "data": {"kitti_vertical_correction_deg": 0.205}}
    o = slam.overrides_from_args(slam.build_parser().parse_args(["--long-baseline-guard"]))
    assert o == {"training": {"acceptance": {"max_long_baseline_rotation_increase": 0.05}}}
    guard = slam.overrides_from_args(slam.build_parser().parse_args(["--long-baseline-guard", "0.1", "--rounds", "1"]))
    assert guard == {"training": {"rounds": 1, "acceptance": {"max_long_baseline_rotation_increase": 0.1}}}
    o = slam.overrides_from_args(slam.build_parser().parse_args(["--loop-variance", "estimated"]))
    assert o == {"graph": {"loop_variance": "estimated"}}
    o = slam.overrides_from_args(slam.build_parser().parse_args(["--registration-covariance", "cluster_robust"]))
    assert o == {"graph": {"registration_covariance": "cluster_robust"}}
    o = slam.overrides_from_args(slam.build_parser().parse_args(["--learned-noise-covariance", "cluster_robust"]))
    assert o == {"training": {"learned_noise_covariance": "cluster_robust"}}
    for flag, value in (("--ground-tilt-offset", True), ("--no-ground-tilt-offset", False)):
        o = slam.overrides_from_args(slam.build_parser().parse_args([flag]))
        assert o == {"graph": {"ground_tilt_offset": value}}
    assert slam.learning_flags_given(slam.build_parser().parse_args(["--learned-noise-covariance", "cluster_robust"])) \
        == ["--learned-noise-covariance cluster_robust"]  # named as ignored without learning rounds
    o = slam.overrides_from_args(slam.build_parser().parse_args(["--loop-min-path", "25"]))
    assert o == {"loops": {"min_path_length": 25.0}}
    o = slam.overrides_from_args(slam.build_parser().parse_args(["--map-keyframe", "0.1", "1"]))
    assert o == {"odometry": {"map_keyframe_translation": 0.1, "map_keyframe_rotation_deg": 1.0}}
    # --paper-method: the paper's Gaussian NLL and densification instead of the defaults, merged with the rest
    o = slam.overrides_from_args(slam.build_parser().parse_args(["--paper-method", "--rounds", "2"]))
    assert o == {"training": {"rounds": 2, "keep_original": False, "keep_dropped": False,
                              "trainer": {"corr_likelihood": "gaussian"}}}
    from gr_graph.config import load_config

    assert load_config(None, guard).training.acceptance.max_long_baseline_rotation_increase == 0.1
    assert load_config(None, {}).training.acceptance.max_long_baseline_rotation_increase is None
    paper, default = load_config(None, o).training, load_config(None, {"training": {"rounds": 2}}).training
    assert (paper.trainer.corr_likelihood, paper.keep_original, paper.keep_dropped) == ("gaussian", False, False)
    assert (default.trainer.corr_likelihood, default.keep_original, default.keep_dropped) == ("student_t", True, True)
    # the old spelling still works, hidden, and says which one to use
    assert slam.build_parser().parse_args(["--quiet"]).no_progress is True
    assert "--quiet is deprecated, use --no-progress" in capsys.readouterr().err


def test_slam_refuses_12_byte_scans_and_runs_them_as_xyz(kitti_root: Path, tmp_path: Path, capsys) -> None:
    """12-byte copies of the real frames: refused naming the file; with --point-format xyz the
    run gives exactly the poses of the original x,y,z,intensity files (SLAM uses no intensity)."""
    xyz_root = tmp_path / "kitti_xyz"
    shutil.copytree(kitti_root, xyz_root, ignore=shutil.ignore_patterns("*.bin"))
    for p in xyz_root.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
    for f in sorted((kitti_root / "sequences/00/velodyne").glob("*.bin")):
        np.fromfile(f, np.float32).reshape(-1, 4)[:, :3].tofile(xyz_root / "sequences/00/velodyne" / f.name)
    common = ["--frames", "0:4", "--no-loops", "--no-memory", "--no-progress"]
    assert slam.main(["--data-root", str(xyz_root), "--out", str(tmp_path / "refused")] + common) == 2
    err = capsys.readouterr().err
    assert re.search(r"velodyne/0000\d\d\.bin: size", err) and "point_format='xyz'" in err  # when the data open
    assert slam.main(["--data-root", str(xyz_root), "--point-format", "xyz", "--out", str(tmp_path / "xyz")]
                     + common) == 0
    assert slam.main(["--data-root", str(kitti_root), "--out", str(tmp_path / "xyzi")] + common) == 0
    np.testing.assert_array_equal(read_kitti_poses(tmp_path / "xyz/round_0/poses_kitti.txt"),
                                  read_kitti_poses(tmp_path / "xyzi/round_0/poses_kitti.txt"))


@pytest.mark.slow
def test_slam_on_exported_12_byte_scans(tmp_path: Path, capsys) -> None:
    """The same on the synthetic exporter's output (no real data needed): the x,y,z export is
    refused by default and gives the x,y,z,intensity export's poses with --point-format xyz."""
    frames = ["--frames", "100:104", "--no-progress", "--preset", "clean"]
    assert synthetic_export.main(["--out", str(tmp_path / "xyzi")] + frames) == 0
    assert synthetic_export.main(["--out", str(tmp_path / "xyz"), "--point-format", "xyz"] + frames) == 0
    common = ["--channels", "16", "--no-loops", "--no-memory", "--no-progress"]
    assert slam.main(["--data-root", str(tmp_path / "xyz"), "--out", str(tmp_path / "refused")] + common) == 2
    err = capsys.readouterr().err
    assert re.search(r"velodyne/0000\d\d\.bin: size", err) and "point_format='xyz'" in err  # when the data open
    for fmt in ("xyz", "xyzi"):
        assert slam.main(["--data-root", str(tmp_path / fmt), "--point-format", fmt,
                          "--out", str(tmp_path / f"run_{fmt}")] + common) == 0
    np.testing.assert_array_equal(read_kitti_poses(tmp_path / "run_xyz/round_0/poses_kitti.txt"),
                                  read_kitti_poses(tmp_path / "run_xyzi/round_0/poses_kitti.txt"))
