"""12-byte x,y,z files vs 16-byte x,y,z,intensity files: detected from the data, refused with a
clear error, readable with point_format="xyz".

Two sources of scans: the real KITTI 00 frames in ../shared/data/kitti (skipped when absent)
and frames of the synthetic renderer (always available).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import ks_2samp

from gr_graph.config import load_config
from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.kitti import KittiSequence, read_velodyne_bin
from gr_graph.datasets.point_layout import (
    MIN_ROWS,
    MIXED_KS,
    ORDERED_LOCALITY,
    _largest_ks_distance,
    check_point_layout,
    stride_evidence,
)
from gr_graph.datasets.registry import open_configured_sequence
from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.datasets.synthetic.__main__ import main as export_main

SUGGEST_XYZ = r"point_format='xyz' \(command line --point-format xyz, config data.point_format: xyz\)"


@pytest.fixture(scope="module")
def synthetic_xyzi() -> np.ndarray:
    """A rendered 16-channel frame as a KITTI (N, 4) float32 array."""
    frame = SyntheticSequence(seed=0, n_rings=16, preset="clean")[40]
    arr = np.empty((len(frame), 4), np.float32)
    arr[:, :3] = frame.points
    arr[:, 3] = frame.intensity
    return arr


def _real_frames(kitti_root: Path) -> list[np.ndarray]:
    return [np.fromfile(f, np.float32).reshape(-1, 4)
            for f in sorted((kitti_root / "sequences/00/velodyne").glob("*.bin"))]


def _xyz_multiple_of_16(xyzi: np.ndarray) -> np.ndarray:
    """The x,y,z columns of a multiple of 4 points: 12 N bytes, also a multiple of 16."""
    return np.ascontiguousarray(xyzi[: len(xyzi) // 4 * 4, :3])


def _write(path: Path, arr: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.ascontiguousarray(arr, np.float32).tofile(path)
    return path


def _kitti_copy_with(kitti_root: Path, dst: Path, frames: list[np.ndarray]) -> Path:
    """A KITTI root with the calib/times/poses of the real excerpt and the given scans."""
    shutil.copytree(kitti_root, dst, ignore=shutil.ignore_patterns("*.bin"))
    for p in dst.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
    for i, arr in enumerate(frames):
        _write(dst / f"sequences/00/velodyne/{i:06d}.bin", arr)
    return dst


# ------------------------------------------------------------------ the statistics


def test_column_ks_matches_scipy_within_the_grid_resolution(synthetic_xyzi: np.ndarray) -> None:
    sample = synthetic_xyzi[:4096].astype(np.float64)
    exact = max(ks_2samp(sample[:, i], sample[:, j]).statistic for i in range(4) for j in range(i + 1, 4))
    approx = _largest_ks_distance(sample)
    assert exact - 1 / 128 - 1e-12 <= approx <= exact + 1e-12


def test_statistics_separate_the_layouts_on_rendered_frames(synthetic_xyzi: np.ndarray) -> None:
    right = stride_evidence(synthetic_xyzi.ravel(), 4)
    wrong = stride_evidence(_xyz_multiple_of_16(synthetic_xyzi).ravel(), 4)
    assert right.ordered and not right.mixed and wrong.mixed and not wrong.ordered
    # margins: at least 2x from each threshold (measured 0.002-0.004 vs > 0.5; > 0.4 vs < 0.05)
    assert right.locality < ORDERED_LOCALITY / 10 and wrong.locality > 2 * ORDERED_LOCALITY
    assert right.column_ks > 2 * MIXED_KS and wrong.column_ks < MIXED_KS / 2


# ------------------------------------------------------------------ synthetic frames (fresh clone)


def test_rendered_xyzi_loads_with_intensity_0_1_and_0_255(synthetic_xyzi: np.ndarray, tmp_path: Path) -> None:
    for scale in (1.0, 255.0):
        arr = synthetic_xyzi.copy()
        arr[:, 3] = np.round(arr[:, 3] * scale)
        raw = read_velodyne_bin(_write(tmp_path / f"i{scale:g}.bin", arr))
        np.testing.assert_array_equal(raw, arr)


def test_rendered_12_byte_file_is_refused_and_reads_as_xyz(synthetic_xyzi: np.ndarray, tmp_path: Path) -> None:
    xyz = _xyz_multiple_of_16(synthetic_xyzi)
    path = _write(tmp_path / "000000.bin", xyz)
    assert path.stat().st_size % 16 == 0
    with pytest.raises(DatasetError, match=r"000000\.bin: looks like 12-byte x,y,z points.*" + SUGGEST_XYZ):
        read_velodyne_bin(path)
    raw = read_velodyne_bin(path, "xyz")
    np.testing.assert_array_equal(raw[:, :3], xyz)
    assert not raw[:, 3].any()


def test_rendered_12_byte_file_whose_size_is_not_a_multiple_of_16(synthetic_xyzi: np.ndarray,
                                                                  tmp_path: Path) -> None:
    xyz = _xyz_multiple_of_16(synthetic_xyzi)[:-1]
    path = _write(tmp_path / "000007.bin", xyz)
    with pytest.raises(DatasetError, match=r"000007\.bin: size \d+ bytes is not a multiple of 16 .* multiple of 12, "
                                           r"and read that way it looks like a LiDAR scan .*" + SUGGEST_XYZ):
        read_velodyne_bin(path)
    np.testing.assert_array_equal(read_velodyne_bin(path, "xyz")[:, :3], xyz)
    path.write_bytes(path.read_bytes()[:-2])  # fits neither layout
    with pytest.raises(DatasetError, match=r"000007\.bin: size \d+ bytes is not a multiple of 16 .*truncated"):
        read_velodyne_bin(path)


def test_shuffled_files_are_judged_by_their_columns_alone(synthetic_xyzi: np.ndarray, tmp_path: Path) -> None:
    shuffled = synthetic_xyzi[np.random.default_rng(0).permutation(len(synthetic_xyzi))]
    assert not stride_evidence(shuffled.ravel(), 4).ordered
    np.testing.assert_array_equal(read_velodyne_bin(_write(tmp_path / "a.bin", shuffled)), shuffled)
    with pytest.raises(DatasetError, match="looks like 12-byte x,y,z points"):
        read_velodyne_bin(_write(tmp_path / "b.bin", _xyz_multiple_of_16(shuffled)))


def test_no_return_padding_does_not_decide(synthetic_xyzi: np.ndarray, tmp_path: Path) -> None:
    """Organised clouds pad missing returns with zeros: a third of the rows zero, in runs."""
    padded = np.zeros((len(synthetic_xyzi) * 3 // 2, 4), np.float32)
    keep = (np.arange(len(padded)) // 50) % 3 != 2
    padded[np.flatnonzero(keep)[: len(synthetic_xyzi)]] = synthetic_xyzi[: keep.sum()]
    np.testing.assert_array_equal(read_velodyne_bin(_write(tmp_path / "a.bin", padded)), padded)
    with pytest.raises(DatasetError, match="looks like 12-byte x,y,z points"):
        read_velodyne_bin(_write(tmp_path / "b.bin", _xyz_multiple_of_16(padded)))


def test_20_byte_file_is_named_as_such(synthetic_xyzi: np.ndarray, tmp_path: Path) -> None:
    n4 = len(synthetic_xyzi) // 4 * 4
    five = np.concatenate([synthetic_xyzi[:n4], np.zeros((n4, 1), np.float32)], axis=1)
    with pytest.raises(DatasetError, match=r"looks like 20-byte .* reads only x,y,z,intensity and x,y,z"):
        read_velodyne_bin(_write(tmp_path / "a.bin", five))


def test_too_few_points_to_judge_are_trusted(synthetic_xyzi: np.ndarray) -> None:
    small = _xyz_multiple_of_16(synthetic_xyzi[: MIN_ROWS - 8])
    check_point_layout(small.ravel(), "xyzi", "small.bin")  # no error: below MIN_ROWS rows
    with pytest.raises(DatasetError):
        check_point_layout(_xyz_multiple_of_16(synthetic_xyzi).ravel(), "xyzi", "big.bin")


def test_exporter_writes_12_byte_files_that_the_loader_reads_only_as_xyz(tmp_path: Path) -> None:
    out = tmp_path / "synth"
    assert export_main(["--out", str(out), "--frames", "40:42", "--channels", "16", "--point-format", "xyz",
                        "--no-progress", "--preset", "clean"]) == 0
    rendered = SyntheticSequence(seed=0, n_rings=16, preset="clean")
    seq = KittiSequence(out, "00", point_format="xyz")
    for k in range(2):
        np.testing.assert_array_equal(seq[k].points, rendered[40 + k].points.astype(np.float32).astype(np.float64))
        assert (out / f"sequences/00/velodyne/{k:06d}.bin").stat().st_size == 12 * len(seq[k])
    default = KittiSequence(out, "00")
    with pytest.raises(DatasetError, match=r"000000\.bin: .*" + SUGGEST_XYZ):
        default[0]
    with pytest.raises(DatasetError, match=r"\.bin: .*" + SUGGEST_XYZ):  # by its size when it opens, or its data
        seq, _ = open_configured_sequence(load_config(None, {"data": {"data_root": str(out)}}).data)
        seq[0]


def test_config_and_registry_pass_the_point_format(synthetic_xyzi: np.ndarray, tmp_path: Path) -> None:
    root = tmp_path / "kitti"
    seq_dir = root / "sequences/00"
    _write(seq_dir / "velodyne/000000.bin", _xyz_multiple_of_16(synthetic_xyzi))
    (seq_dir / "calib.txt").write_text("Tr: " + " ".join(["1", "0", "0", "0"] * 3) + "\n")
    cfg = load_config(None, {"data": {"data_root": str(root), "point_format": "xyz"}})
    seq, desc = open_configured_sequence(cfg.data)
    assert "xyz points" in desc
    np.testing.assert_array_equal(seq[0].points, _xyz_multiple_of_16(synthetic_xyzi).astype(np.float64))
    seq, _ = open_configured_sequence(load_config(None, {"data": {"data_root": str(root)}}).data)
    with pytest.raises(DatasetError, match="looks like 12-byte"):
        seq[0]
    with pytest.raises(ValueError, match="point_format"):
        load_config(None, {"data": {"point_format": "xyzrgb"}})


# ------------------------------------------------------------------ real KITTI 00 frames


def test_real_frames_load_with_intensity_0_1_and_0_255(kitti_root: Path, tmp_path: Path) -> None:
    frames = _real_frames(kitti_root)
    scaled = [f.copy() for f in frames]
    for f in scaled:
        f[:, 3] = np.round(f[:, 3] * 255)
    assert max(f[:, 3].max() for f in scaled) > 200
    for variant in (frames, scaled):
        root = _kitti_copy_with(kitti_root, tmp_path / f"k{len(list(tmp_path.iterdir()))}", variant)
        seq = KittiSequence(root, "00")
        for i, arr in enumerate(variant):
            np.testing.assert_array_equal(seq[i].intensity, arr[:, 3])


def test_real_frames_as_12_byte_files_are_refused_and_read_as_xyz(kitti_root: Path, tmp_path: Path) -> None:
    frames = [_xyz_multiple_of_16(f) for f in _real_frames(kitti_root)]
    root = _kitti_copy_with(kitti_root, tmp_path / "kitti", frames)
    seq = KittiSequence(root, "00")
    xyz = KittiSequence(root, "00", point_format="xyz")
    for i, arr in enumerate(frames):
        with pytest.raises(DatasetError, match=rf"{i:06d}\.bin: looks like 12-byte x,y,z points.*"
                                               r"'intensity' column is \d+% negative.*" + SUGGEST_XYZ):
            seq[i]
        np.testing.assert_array_equal(xyz[i].points, arr.astype(np.float64))


def test_real_12_byte_file_whose_size_is_not_a_multiple_of_16(kitti_root: Path, tmp_path: Path) -> None:
    xyz = _real_frames(kitti_root)[0][:, :3]
    xyz = xyz[: len(xyz) // 4 * 4 - 1]  # 4k - 1 points: 12 (4k - 1) bytes is not a multiple of 16
    path = _write(tmp_path / "000000.bin", xyz)
    with pytest.raises(DatasetError, match=r"000000\.bin: size \d+ bytes is not a multiple of 16 .* multiple of 12, "
                                           r"and read that way it looks like a LiDAR scan .*" + SUGGEST_XYZ):
        read_velodyne_bin(path)


def test_real_xyzi_file_read_as_xyz_is_refused(kitti_root: Path) -> None:
    files = sorted((kitti_root / "sequences/00/velodyne").glob("*.bin"))
    fits_12 = [f for f in files if f.stat().st_size % 12 == 0]
    assert fits_12, "need a real frame whose size is a multiple of 12 and 16"
    with pytest.raises(DatasetError, match=r"looks like 16-byte x,y,z,intensity points, not 12-byte x,y,z.*"
                                           r"point_format='xyzi'"):
        read_velodyne_bin(fits_12[0], "xyz")
    odd = [f for f in files if f.stat().st_size % 12]
    for f in odd:
        with pytest.raises(DatasetError, match=r"not a multiple of 12 .* multiple of 16.*point_format='xyzi'"):
            read_velodyne_bin(f, "xyz")
