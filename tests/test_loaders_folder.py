"""Folders of .bin / .pcd / .ply / .npy scans: rendered frames written with open3d and numpy come back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.folder import FolderSequence, natural_key
from gr_graph.datasets.point_files import read_pcd, read_ply
from gr_graph.datasets.registry import guess_dataset, open_sequence
from loader_support import FRAME_PERIOD_S, drive, float32_frame

N_FRAMES = 3


@pytest.fixture(scope="module")
def frames(tmp_path_factory: pytest.TempPathFactory) -> list:
    seq = drive("raw", N_FRAMES, str(tmp_path_factory.mktemp("drive")))
    return [seq[i] for i in range(N_FRAMES)]


def _o3d_cloud(frame, with_time: bool = True):
    import open3d as o3d

    pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(frame.points.astype(np.float32)))
    pc.point.intensity = o3d.core.Tensor(frame.intensity[:, None])
    pc.point.ring = o3d.core.Tensor(frame.ring.astype(np.uint16)[:, None])
    if with_time:
        pc.point.t = o3d.core.Tensor((frame.time * FRAME_PERIOD_S).astype(np.float32)[:, None])
    return pc


def _write_o3d(folder: Path, frames: list, suffix: str, names: list[str], **kwargs) -> Path:
    import open3d as o3d

    folder.mkdir()
    for frame, name in zip(frames, names):
        assert o3d.t.io.write_point_cloud(str(folder / f"{name}{suffix}"), _o3d_cloud(frame), **kwargs)
    return folder


def test_natural_sort() -> None:
    names = ["frame10.pcd", "frame2.pcd", "frame1.pcd", "Frame3.pcd"]
    assert sorted(names, key=natural_key) == ["frame1.pcd", "frame2.pcd", "Frame3.pcd", "frame10.pcd"]


@pytest.mark.parametrize("suffix,kwargs", [(".pcd", {}), (".pcd", {"write_ascii": True}), (".ply", {}),
                                           (".ply", {"write_ascii": True})])
def test_open3d_files_round_trip(tmp_path: Path, frames: list, suffix: str, kwargs: dict) -> None:
    # frame2 must come before frame10: the names are sorted naturally, not as strings
    folder = _write_o3d(tmp_path / "scans", frames, suffix, ["frame2", "frame10", "frame11"], **kwargs)
    assert guess_dataset(folder) == "folder"
    seq = FolderSequence(folder)
    assert [p.name for p in seq.files] == [f"frame{k}{suffix}" for k in (2, 10, 11)]
    assert seq.motion_compensated is False  # the files carry a per-point time field "t"
    for i, frame in enumerate(frames):
        back = seq[i]
        if not kwargs:  # binary: bit-exact float32
            np.testing.assert_array_equal(back.points, float32_frame(frame))
        elif suffix == ".pcd":  # open3d's ASCII PCD has 10 significant digits: float32 round-trips
            np.testing.assert_array_equal(back.points.astype(np.float32), frame.points.astype(np.float32))
        else:  # open3d's ASCII PLY writes 6 significant digits
            np.testing.assert_allclose(back.points, frame.points, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(back.intensity, frame.intensity, rtol=1e-5)
        np.testing.assert_array_equal(back.ring, frame.ring)
        np.testing.assert_allclose(back.time, frame.time - frame.time.min(), atol=1e-6)
    # no times file: 0.1 s apart; moved to the sweeps' middles (times from the sweep's start: + half a sweep)
    assert seq.stamps_moved_by_s == pytest.approx(FRAME_PERIOD_S / 2, abs=1e-3)
    np.testing.assert_allclose(seq.timestamps, np.arange(N_FRAMES) * FRAME_PERIOD_S + seq.stamps_moved_by_s)


def test_compressed_pcd_through_open3d(tmp_path: Path, frames: list) -> None:
    """binary_compressed PCDs keep every field: the same frames as binary ones, per-point time and
    ring included (before, only x, y, z and intensity: raw sweeps passed as motion-compensated)."""
    folder = _write_o3d(tmp_path / "c", frames, ".pcd", ["a", "b", "c"], compressed=True)
    plain = FolderSequence(_write_o3d(tmp_path / "b", frames, ".pcd", ["a", "b", "c"]))
    seq = FolderSequence(folder)
    assert b"binary_compressed" in (folder / "a.pcd").read_bytes()[:400]
    assert seq.motion_compensated is False and seq.n_rings == plain.n_rings
    for i in range(N_FRAMES):
        back, ref = seq[i], plain[i]
        np.testing.assert_array_equal(back.points, float32_frame(frames[i]))
        np.testing.assert_array_equal(back.intensity, frames[i].intensity)
        np.testing.assert_array_equal(back.ring, ref.ring)
        np.testing.assert_array_equal(back.time, ref.time)
    assert read_pcd(folder / "a.pcd").time_field == "t"


def test_a_runs_own_poses_are_not_taken_for_ground_truth(tmp_path: Path, frames: list,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    """``slam drive/scans --out drive``: the run writes poses_kitti.txt into drive/, and the next
    run on drive/scans must not read that estimate as ground truth (a perfect ATE)."""
    import logging

    from gr_graph.trajectory import write_kitti_poses

    drive_dir = tmp_path / "drive"
    drive_dir.mkdir()
    scans = _write_o3d(drive_dir / "scans", frames, ".pcd", ["0", "1", "2"])
    estimate = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    estimate[:, 0, 3] = np.arange(N_FRAMES)
    write_kitti_poses(drive_dir / "poses_kitti.txt", estimate)
    assert FolderSequence(scans).gt_poses is not None  # a poses file beside the scans is found ...
    (drive_dir / "round_0").mkdir()
    (drive_dir / "metrics.json").write_text("{}")
    with caplog.at_level(logging.WARNING):
        assert FolderSequence(scans).gt_poses is None  # ... but not from a run's output
    assert "holds a gr_graph run's output" in caplog.text and "--poses" in caplog.text
    given = FolderSequence(scans, poses=drive_dir / "poses_kitti.txt")  # given: taken
    np.testing.assert_allclose(given.gt_poses[:, 0, 3], np.arange(N_FRAMES))
    write_kitti_poses(drive_dir / "poses.txt", estimate)  # a name a run never writes: still ground truth there
    assert FolderSequence(scans).gt_poses is not None


def test_npy_bin_and_side_files(tmp_path: Path, frames: list) -> None:
    from gr_graph.trajectory import write_kitti_poses, write_tum_poses

    gt = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    gt[:, :3, 3] = np.arange(N_FRAMES)[:, None] * [1.0, 0.5, 0.0] + [10.0, 0.0, 0.0]
    times = np.array([3.0, 3.11, 3.2])
    npy4, npy3, structured, bin4, bin3 = (tmp_path / n for n in ("npy4", "npy3", "npys", "bin4", "bin3"))
    for folder in (npy4, npy3, structured, bin4, bin3):
        folder.mkdir()
    for k, f in enumerate(frames):
        xyzi = np.column_stack([f.points, f.intensity]).astype(np.float32)
        np.save(npy4 / f"{k}.npy", xyzi)
        np.save(npy3 / f"{k}.npy", f.points)
        arr = np.zeros(len(f), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f4"), ("ring", "u1"),
                                      ("time", "f8")])
        for c, col in zip("xyz", f.points.T):
            arr[c] = col
        arr["intensity"], arr["ring"], arr["time"] = f.intensity, f.ring, 1e3 + f.time * FRAME_PERIOD_S
        np.save(structured / f"{k}.npy", arr)
        xyzi.tofile(bin4 / f"{k:06d}.bin")
        xyzi[:, :3].copy().tofile(bin3 / f"{k:06d}.bin")
    np.savetxt(npy4 / "times.txt", times)
    write_kitti_poses(npy4 / "poses.txt", gt)
    write_tum_poses(tmp_path / "gt.tum", times, gt)

    seq, source = open_sequence(path=npy4)
    assert "ground truth" in source
    np.testing.assert_allclose(seq.timestamps, times - 3.0)
    np.testing.assert_allclose(seq.gt_poses[:, :3, 3], gt[:, :3, 3] - gt[0, :3, 3], atol=1e-12)
    np.testing.assert_array_equal(seq[1].points, float32_frame(frames[1]))
    np.testing.assert_array_equal(seq[1].intensity, frames[1].intensity)
    assert seq[1].ring is None and seq[1].time is None and seq.motion_compensated is True

    tum_seq, _ = open_sequence(path=npy3, poses=tmp_path / "gt.tum")
    np.testing.assert_allclose(tum_seq.timestamps, times - 3.0)  # the TUM times, for want of a times file
    # TUM poses beside a times file: their times must follow the scans' (another clock's offset is fine)
    write_tum_poses(tmp_path / "gt_other_clock.tum", times + 1.7e9, gt)
    assert FolderSequence(npy4, poses=tmp_path / "gt_other_clock.tum").gt_poses is not None
    write_tum_poses(tmp_path / "gt_resampled.tum", np.array([3.0, 3.2, 3.4]), gt)  # same rows, other instants
    with pytest.raises(DatasetError, match=r"gt_resampled.tum: .*row by row.*times.txt.*row 2 is \+0.2 s off"):
        FolderSequence(npy4, poses=tmp_path / "gt_resampled.tum")
    np.testing.assert_array_equal(tum_seq[2].points, frames[2].points)  # float64 kept
    assert not tum_seq[2].intensity.any()

    s = FolderSequence(structured)
    assert s.motion_compensated is False
    np.testing.assert_array_equal(s[0].points, frames[0].points)
    np.testing.assert_array_equal(s[0].ring, frames[0].ring)
    np.testing.assert_allclose(s[0].time, frames[0].time - frames[0].time.min(), atol=1e-9)

    np.testing.assert_array_equal(FolderSequence(bin4)[2].points, float32_frame(frames[2]))
    np.testing.assert_array_equal(FolderSequence(bin3, point_format="xyz")[2].points, float32_frame(frames[2]))
    with pytest.raises(DatasetError, match=r"bin3/000000.bin"):
        FolderSequence(bin3)  # 12-byte points read as 16-byte ones: the layout check names the file


def test_broken_folders_name_the_file(tmp_path: Path, frames: list) -> None:
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    np.save(mixed / "0.npy", frames[0].points)
    np.save(mixed / "1.npy", frames[1].points)
    (mixed / "2.pcd").write_text("junk")
    with pytest.raises(DatasetError, match=r"mixed: mixed file types \(2 \.npy, 1 \.pcd\)"):
        open_sequence(path=mixed)

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "0.pcd").write_text("VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nPOINTS 1\nDATA ascii\n1 2\n")
    with pytest.raises(DatasetError, match=r"bad/0.pcd: no field z"):
        FolderSequence(bad)
    (bad / "0.pcd").write_bytes(b"\x89\xff\x00garbage" * 10)
    with pytest.raises(DatasetError, match=r"bad/0.pcd: "):
        FolderSequence(bad)

    short = tmp_path / "short.pcd"
    _write = _o3d_cloud(frames[0])
    import open3d as o3d

    o3d.t.io.write_point_cloud(str(short), _write)
    short.write_bytes(short.read_bytes()[:-100])
    with pytest.raises(DatasetError, match=r"short.pcd: .* truncated or wrong field layout"):
        read_pcd(short)
    (tmp_path / "x.ply").write_text("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int v\nend_header\n")
    with pytest.raises(DatasetError, match=r"x.ply: the first PLY element is not 'vertex'"):
        read_ply(tmp_path / "x.ply")

    wrong = tmp_path / "wrong"
    wrong.mkdir()
    np.save(wrong / "0.npy", np.zeros((5, 7)))
    with pytest.raises(DatasetError, match=r"wrong/0.npy: array of shape \(5, 7\)"):
        FolderSequence(wrong)
    np.save(wrong / "0.npy", np.ones((5, 3)) * (1 + 1j))  # complex: its imaginary part would be lost
    with pytest.raises(DatasetError, match=r"wrong/0.npy: array of shape \(5, 3\) and dtype complex128"):
        FolderSequence(wrong)

    counted = tmp_path / "counted"
    counted.mkdir()
    np.save(counted / "0.npy", frames[0].points)
    np.savetxt(counted / "times.txt", [0.0, 0.1])
    with pytest.raises(DatasetError, match=r"counted/times.txt: 2 timestamps for 1 frames"):
        FolderSequence(counted)

    with pytest.raises(DatasetError, match=r"empty_dir: not a recognised dataset"):
        (tmp_path / "empty_dir").mkdir()
        open_sequence(path=tmp_path / "empty_dir")
    with pytest.raises(DatasetError, match=r"nowhere: no such file or folder"):
        open_sequence(path=tmp_path / "nowhere")


def test_real_ply_pair_matches_open3d(small_gicp_pair_dir: Path) -> None:
    """CloudCompare's binary PLY (x, y, z, scalar_intensity) of a real scan, against open3d's reader."""
    import open3d as o3d

    path = small_gicp_pair_dir / "source.ply"
    cloud = read_ply(path)
    reference = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    no_return = np.all(reference == 0.0, axis=1)  # the organized cloud's beams without a return (7 %)
    assert len(reference) == 69792 and no_return.sum() == cloud.dropped_nonfinite == 5107
    np.testing.assert_array_equal(cloud.points, reference[~no_return])
    assert cloud.intensity is not None and np.ptp(cloud.intensity) > 0


def test_real_kitti_velodyne_folder_matches_the_odometry_loader(kitti_root: Path) -> None:
    from gr_graph.datasets.kitti import KittiSequence

    folder = kitti_root / "sequences" / "00" / "velodyne"
    assert guess_dataset(folder) == "kitti"  # opened by path: the sequence, with its calibration and GT
    seq = FolderSequence(folder)  # read as a plain folder of scans, the points are the same
    kitti = KittiSequence(kitti_root, "00")
    assert len(seq) == len(kitti) == 6
    for i in (0, 5):
        np.testing.assert_array_equal(seq[i].points, kitti[i].points)
        np.testing.assert_array_equal(seq[i].intensity, kitti[i].intensity)


def test_a_kitti_raw_data_folder_names_the_drive_folder(tmp_path: Path, frames: list) -> None:
    """``velodyne_points/data`` opened as a folder finds ``velodyne_points/timestamps.txt`` (date-times):
    the error says to open the drive folder instead of only that a row has two values."""
    data = tmp_path / "2011_09_26_drive_0001_sync" / "velodyne_points" / "data"
    data.mkdir(parents=True)
    for k, f in enumerate(frames):
        np.column_stack([f.points, f.intensity]).astype(np.float32).tofile(data / f"{k:010d}.bin")
    (data.parent / "timestamps.txt").write_text("".join(f"2011-09-26 13:02:25.{k}64389445\n" for k in range(N_FRAMES)))
    with pytest.raises(DatasetError, match=r"velodyne_points/timestamps.txt:1: .*date-time stamps.*drive folder"):
        FolderSequence(data)


@pytest.mark.parametrize("suffix", [".pcd", ".ply", ".npy"])
def test_a_scan_cut_short_in_the_middle_is_refused_when_the_folder_opens(tmp_path: Path, frames: list,
                                                                          suffix: str) -> None:
    """A binary PCD / PLY or a .npy in the middle of a folder cut short (a copy or a recorder that stopped)
    is refused when the folder opens, naming the file, not when SLAM reaches it (the probe scans, the
    first and a few spread over the folder, do not include it); frames outside the range asked for are
    not looked at, and a complete folder opens."""
    import open3d as o3d

    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(13):  # probe scans 0, 3, 6, 9, 12
        frame = frames[k % len(frames)]
        if suffix == ".npy":
            arr = np.zeros(len(frame.points), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<f4")])
            for i, c in enumerate("xyz"):
                arr[c] = frame.points[:, i]
            arr["t"] = frame.time * FRAME_PERIOD_S
            np.save(folder / f"{k:02d}.npy", arr)
        else:
            assert o3d.t.io.write_point_cloud(str(folder / f"{k:02d}{suffix}"), _o3d_cloud(frame))
    assert len(open_sequence(path=folder)[0]) == 13
    cut = folder / f"04{suffix}"
    cut.write_bytes(cut.read_bytes()[:-1000])
    with pytest.raises(DatasetError, match=rf"04\{suffix}: \d+ data bytes, header promises .* cut short .*"
                                           r"\(1 of the 13 scans to read are cut short"):
        open_sequence(path=folder)
    assert len(open_sequence(path=folder, frames="0:4")[0]) == 4
