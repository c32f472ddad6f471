"""The registry's dataset choice: --dataset / data.dataset, guessing from a path, the CLI's PATH."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gr_graph.config import load_config
from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.registry import KITTI_ROOT_ENV, guess_dataset, open_configured_sequence, open_sequence
from gr_graph.slam import build_parser, main, overrides_from_args


def test_path_datasets_need_a_path_and_synthetic_takes_none(tmp_path: Path) -> None:
    for kind in ("folder", "rosbag", "kitti_raw"):
        with pytest.raises(DatasetError, match=f"dataset '{kind}' needs a path"):
            open_sequence(dataset=kind)
    with pytest.raises(DatasetError, match="synthetic sequence takes no path"):
        open_sequence(path=tmp_path, dataset="synthetic")
    with pytest.raises(DatasetError, match="dataset must be one of"):
        open_sequence(dataset="pcap")


def test_kitti_dataset_without_root_is_an_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(KITTI_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path))
    with pytest.raises(DatasetError, match="dataset 'kitti': no KITTI root with sequence 00 found"):
        open_sequence(dataset="kitti")


def test_kitti_odometry_root_and_sequence_folder_as_path(kitti_root: Path) -> None:
    assert guess_dataset(kitti_root) == "kitti"
    seq, source = open_sequence(path=kitti_root, frames="0:2")
    assert "KITTI sequence 00" in source and len(seq) == 2
    seq2, source2 = open_sequence(path=kitti_root / "sequences" / "00", frames="0:2")
    assert "KITTI sequence 00" in source2
    np.testing.assert_array_equal(seq[1].points, seq2[1].points)
    velodyne = kitti_root / "sequences" / "00" / "velodyne"  # the scans' folder: still the sequence, with its GT
    assert guess_dataset(velodyne) == "kitti"
    seq3, source3 = open_sequence(path=velodyne, frames="0:2")
    assert "KITTI sequence 00" in source3 and seq3.gt_poses is not None
    np.testing.assert_array_equal(seq[1].points, seq3[1].points)


def test_config_and_cli_reach_the_loader(tmp_path: Path) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        np.save(folder / f"scan{k}.npy", rng.normal(0, 5, (200, 3)))
    args = build_parser().parse_args([str(folder), "--dataset", "folder", "--frames", "1:3"])
    cfg = load_config(None, overrides_from_args(args))
    assert cfg.data.path == str(folder) and cfg.data.dataset == "folder"
    seq, source = open_configured_sequence(cfg.data)
    assert source.startswith(f"folder {folder} (3 .npy files)") and len(seq) == 2 and seq[0].index == 1
    cfg_bag = load_config(None, {"data": {"path": str(folder), "dataset": "rosbag"}})
    with pytest.raises(DatasetError, match="scans: not a ROS bag"):
        open_configured_sequence(cfg_bag.data)


def test_cli_error_names_the_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    folder = tmp_path / "mixed"
    folder.mkdir()
    np.save(folder / "a.npy", np.zeros((5, 3)))
    (folder / "b.ply").write_text("ply\n")
    assert main([str(folder), "--out", str(tmp_path / "out")]) == 2
    assert f"error: {folder}: mixed file types (1 .npy, 1 .ply)" in capsys.readouterr().err


def test_options_other_data_ignore_are_named_in_one_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = tmp_path / "scans"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(2):
        np.save(folder / f"scan{k}.npy", rng.normal(0, 5, (200, 3)))
    (tmp_path / "t.txt").write_text("0.0\n0.1\n")
    args = build_parser().parse_args([str(folder), "--synthetic-preset", "clean", "--route-seed", "3", "--seq", "05",
                                      "--topic", "/points", "--timestamps", str(tmp_path / "t.txt")])
    cfg = load_config(None, overrides_from_args(args))
    with caplog.at_level("WARNING", logger="gr_graph.datasets.registry"):
        seq, _ = open_configured_sequence(cfg.data)
    assert len(seq) == 2
    warnings = [r.getMessage() for r in caplog.records if "ignored for" in r.getMessage()]
    assert warnings == ["ignored for folder data (they concern other kinds of data): seq=05, topic=/points, "
                        "route_seed=3, synthetic_preset=clean"]  # timestamps concern folders: not named
    caplog.clear()
    with caplog.at_level("WARNING", logger="gr_graph.datasets.registry"):
        open_configured_sequence(load_config(None, {"data": {"path": str(folder)}}).data)  # nothing extra given
    assert not [r for r in caplog.records if "ignored for" in r.getMessage()]


def test_ignored_options_by_kind() -> None:
    from gr_graph.datasets.registry import ignored_options

    assert ignored_options("synthetic", topic="/p", poses="gt.txt", point_format="xyz", seq="00",
                           route_seed=2) == ["topic=/p", "poses=gt.txt", "point_format=xyz"]
    assert ignored_options("kitti", seq="05", route_seed=1, synthetic_preset="raw", point_format="xyz") == [
        "route_seed=1", "synthetic_preset=raw"]
    assert ignored_options("rosbag", topic="/p", poses="gt.txt", timestamps="t.txt", point_format="xyz") == [
        "timestamps=t.txt", "point_format=xyz"]
    assert ignored_options("kitti_raw", poses="gt.txt", data_root="/kitti") == ["data_root=/kitti", "poses=gt.txt"]
    assert ignored_options("folder", route_seed=0, point_format="xyzi", seq="00") == []  # defaults: never named
    with pytest.raises(KeyError, match="frames"):
        ignored_options("folder", frames=(0, 2))


def test_the_description_says_how_many_rings_the_data_hold_when_no_sensor_is_named(tmp_path) -> None:
    """A folder of 16-ring scans opened without --sensor: the description names the data's 16 rings
    beside the default sensor whose figures apply (it said only "64 channels" before), and a run's
    summary records them (``counted_rings``); a named sensor's beams are what it says, and 64 rings
    kept to 16 with --channels need no remark."""
    import numpy as np

    from gr_graph.datasets.registry import counted_rings, open_sequence

    rng = np.random.default_rng(1)

    def folder_of(name: str, n_rings: int):
        folder = tmp_path / name
        folder.mkdir()
        for k in range(3):
            arr = np.zeros(n_rings * 200, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("ring", "u2")])
            arr["ring"] = np.repeat(np.arange(n_rings), 200)
            elevation = np.radians(np.linspace(15.0, -15.0, n_rings))[arr["ring"]]
            azimuth = np.tile(np.linspace(-np.pi, np.pi, 200, endpoint=False), n_rings)
            r = rng.uniform(5.0, 20.0, len(arr))
            arr["x"], arr["y"], arr["z"] = (r * np.cos(elevation) * np.cos(azimuth),
                                            r * np.cos(elevation) * np.sin(azimuth), r * np.sin(elevation))
            np.save(folder / f"{k}.npy", arr)
        return folder

    vlp16 = folder_of("vlp16", 16)
    seq, desc = open_sequence(path=vlp16)
    assert counted_rings(seq) == 16
    assert desc.endswith("64 channels (16 rings in the data; no sensor named: the hdl64e's figures apply)"), desc
    named, desc_named = open_sequence(path=vlp16, sensor="vlp16")
    assert counted_rings(named) is None and desc_named.endswith(", 16 channels"), desc_named
    sub, desc_sub = open_sequence(path=folder_of("hdl64", 64), channels=16)
    assert counted_rings(sub) == 64 and desc_sub.endswith(", 16 channels"), desc_sub
