"""Opening sequences: KITTI when found, synthetic otherwise, frame ranges and channel views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.registry import KITTI_ROOT_ENV, open_sequence, parse_frames


def test_parse_frames() -> None:
    assert parse_frames(None, 10) == (0, 10)
    assert parse_frames("2:5", 10) == (2, 5)
    assert parse_frames(":4", 10) == (0, 4)
    assert parse_frames("7:", 10) == (7, 10)
    assert parse_frames((1, 3), 10) == (1, 3)
    with pytest.raises(DatasetError):
        parse_frames("a:b", 10)
    with pytest.raises(DatasetError):
        parse_frames("1:2:3", 10)
    assert parse_frames((np.int64(1), np.int64(3)), 10) == (1, 3)
    for bad in ((1.5, 9), (True, 10), ("1", 3)):  # a YAML list [1.5, 9] was floored to (1, 9)
        with pytest.raises(DatasetError, match="must be integers"):
            parse_frames(bad, 10)


def test_kitti_root_view(kitti_root: Path) -> None:
    seq, source = open_sequence("00", data_root=kitti_root, channels=16, frames="1:4")
    assert "KITTI sequence 00" in source and "16 channels" in source
    assert len(seq) == 3
    frame = seq[0]
    assert frame.index == 1 and frame.n_rings == 16
    assert seq.gt_poses.shape == (3, 4, 4)
    full, _ = open_sequence("00", data_root=kitti_root)
    np.testing.assert_array_equal(seq.gt_poses, full.gt_poses[1:4])
    np.testing.assert_array_equal(seq.timestamps, full.timestamps[1:4])
    assert abs(len(frame) / len(full[1]) - 0.25) < 0.05


def test_kitti_root_from_environment(kitti_root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(KITTI_ROOT_ENV, str(kitti_root))
    seq, source = open_sequence("00")
    assert str(kitti_root) in source and len(seq) == 6


def test_explicit_root_without_sequence_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no sequences/00/velodyne"):
        open_sequence("00", data_root=tmp_path)


def test_unknown_sequence_without_kitti(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv(KITTI_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path))
    with pytest.raises(DatasetError, match="synthetic fallback exists for sequence 00 only"):
        open_sequence("05")


def test_bad_channels() -> None:
    with pytest.raises(DatasetError, match="channels"):
        open_sequence("00", channels=8)


def test_bad_range(kitti_root: Path) -> None:
    with pytest.raises(DatasetError, match=r"frames 4:4: need 0 <= A < B <= 6"):
        open_sequence("00", data_root=kitti_root, frames="4:4")
    with pytest.raises(DatasetError, match=r"frames 2:9: need 0 <= A < B <= 6"):
        open_sequence("00", data_root=kitti_root, frames="2:9")


def test_out_of_range_frames_are_an_error_not_clipped() -> None:
    with pytest.raises(DatasetError, match="need 0 <= A < B <= 10"):
        parse_frames("0:99", 10)
    with pytest.raises(DatasetError, match="need 0 <= A < B <= 10"):
        parse_frames((-3, 5), 10)
    with pytest.raises(DatasetError, match="need 0 <= A < B <= 10"):
        parse_frames("6:6", 10)
    with pytest.raises(DatasetError, match="steps"):
        parse_frames(slice(0, 10, 2), 10)
    for bad in ("5", "7:3", "0:11", "a:b"):
        with pytest.raises(DatasetError):
            parse_frames(bad, 10)


def test_frames_without_the_sequence_length() -> None:
    """A configuration's range is parsed before the sequence is opened: B is required."""
    assert parse_frames("2330:2480") == (2330, 2480) and parse_frames(":5") == (0, 5)
    for bad, msg in (("7:", "B is needed"), ("5:5", "need 0 <= A < B"), ("-1:4", "need 0 <= A < B"),
                     (None, "sequence length")):
        with pytest.raises(DatasetError, match=msg):
            parse_frames(bad)


def test_synthetic_route_seed_and_trajectory(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Without KITTI: the generated route of route_seed, or a given trajectory; never both
    a trajectory and a KITTI root."""
    from gr_graph.datasets.synthetic.route import generate_route
    from gr_graph.trajectory import write_tum_poses

    monkeypatch.delenv(KITTI_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path))
    seq, source = open_sequence("00", frames="10:20", route_seed=1, synthetic_seed=3)
    assert "generated route, route seed 1, town seed 3" in source and len(seq) == 10
    np.testing.assert_array_equal(seq.gt_poses, generate_route(1).T_w_velo[10:20])
    T = np.asarray(generate_route(0).T_w_velo[:50])
    f = write_tum_poses(tmp_path / "t.tum", np.arange(50) * 0.1, T)
    seq, source = open_sequence("00", trajectory=f)
    assert f"trajectory {f} (TUM format" in source and len(seq) == 50
    root = tmp_path / "kitti"
    (root / "sequences" / "00" / "velodyne").mkdir(parents=True)
    with pytest.raises(DatasetError, match="cannot be combined with the KITTI root"):
        open_sequence("00", data_root=root, trajectory=f)


def test_synthetic_vertical_correction_raises_every_point(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The synthetic presets carry KITTI's vertical-angle error: the correction applies to them
    as to KITTI scans (same points as correcting the uncorrected frame), and the source says so."""
    from gr_graph.datasets.base import release_render_cache
    from gr_graph.datasets.kitti import correct_vertical_angle

    monkeypatch.delenv(KITTI_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path))
    plain, src_plain = open_sequence("00", frames="740:741", channels=16, synthetic_preset="clean")
    fixed, src_fixed = open_sequence("00", frames="740:741", channels=16, synthetic_preset="clean",
                                     kitti_vertical_correction_deg=0.22)
    assert "vertical-angle correction" not in src_plain and "vertical-angle correction 0.22 deg" in src_fixed
    a, b = plain[0], fixed[0]
    np.testing.assert_array_equal(b.points, correct_vertical_angle(a.points, 0.22))
    np.testing.assert_array_equal(b.ring, a.ring)
    elevation = np.degrees(np.arctan2(b.points[:, 2], np.hypot(b.points[:, 0], b.points[:, 1])) -
                           np.arctan2(a.points[:, 2], np.hypot(a.points[:, 0], a.points[:, 1])))
    assert np.allclose(elevation, 0.22, atol=1e-9)
    assert release_render_cache(fixed)  # the town is still reachable through the correcting view


def test_vertical_correction_applies_to_a_folder_of_scans_too(tmp_path: Path) -> None:
    """Given with a path (a folder here, a KITTI raw drive or a bag likewise), the correction is applied
    and named in the source, not dropped without a word."""
    from gr_graph.datasets.kitti import correct_vertical_angle

    rng = np.random.default_rng(6)
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(3):
        np.save(folder / f"{k:06d}.npy", rng.uniform(-20, 20, (500, 3)).astype(np.float32))
    plain, src_plain = open_sequence(path=folder)
    fixed, src_fixed = open_sequence(path=folder, kitti_vertical_correction_deg=0.205)
    assert "vertical-angle correction" not in src_plain and "), vertical-angle correction 0.205 deg" in src_fixed
    np.testing.assert_array_equal(fixed[1].points, correct_vertical_angle(plain[1].points, 0.205))
    assert len(fixed) == 3 and fixed[2].index == 2
