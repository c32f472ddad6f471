"""Folder loader robustness: float64 .bin files, timestamp units, float-stamp file names, hidden
files, empty clouds and non-finite intensity (gr_graph.datasets.point_files / folder / registry)."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.folder import FolderSequence, point_files, read_timestamps_file, sort_point_files
from gr_graph.datasets.point_files import read_npy, read_pcd, read_ply, read_point_file
from gr_graph.datasets.point_layout import float64_bin_problem
from gr_graph.datasets.registry import guess_dataset, open_sequence

RNG = np.random.default_rng(7)


def scan(n_rings: int = 32, n_az: int = 600, with_time: bool = False) -> np.ndarray:
    """A spinning-LiDAR-like scan in scan order: ``(N, 4)`` x, y, z, intensity (``(N, 5)`` with a
    time column in seconds)."""
    rows = []
    az = np.linspace(0.0, 2 * np.pi, n_az, endpoint=False)
    for ring in range(n_rings):
        elev = np.radians(2.0 - 0.8 * ring)
        r = 8.0 + 3.0 * np.sin(2 * az) + 0.05 * ring
        pts = np.column_stack([r * np.cos(az), r * np.sin(az), r * np.tan(elev), RNG.uniform(0, 1, n_az)])
        if with_time:
            pts = np.column_stack([pts, az / (2 * np.pi) * 0.1])
        rows.append(pts)
    return np.concatenate(rows)


def write_pcd(path: Path, arr: np.ndarray, n_points: int | None = None, ascii: bool = False) -> Path:
    """A PCD (binary or ascii) of structured float32 ``arr``; ``n_points`` overrides the POINTS line."""
    names = arr.dtype.names
    n = len(arr) if n_points is None else n_points
    header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {' '.join(names)}\nSIZE {' '.join('4' for _ in names)}\n"
              f"TYPE {' '.join('F' for _ in names)}\nCOUNT {' '.join('1' for _ in names)}\nWIDTH {n}\nHEIGHT 1\n"
              f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {'ascii' if ascii else 'binary'}\n")
    body = ("".join(" ".join(f"{v!r}" for v in row) + "\n" for row in arr.tolist()).encode() if ascii
            else arr.astype([(c, "<f4") for c in names]).tobytes())
    path.write_bytes(header.encode() + body)
    return path


def structured(cols: np.ndarray, names: str = "x y z intensity") -> np.ndarray:
    fields = names.split()
    out = np.zeros(len(cols), dtype=[(c, "<f4") for c in fields])
    for k, c in enumerate(fields):
        out[c] = cols[:, k]
    return out


def npy_folder(folder: Path, names: list[str], n: int = 300) -> Path:
    folder.mkdir()
    for name in names:
        np.save(folder / name, scan(4, n // 4)[:, :3])
    return folder


# ----------------------------------------------------------------------------- 1. float64 .bin


@pytest.mark.parametrize("cols,point_format,layout", [(4, "xyzi", "x,y,z,intensity"), (3, "xyzi", "x,y,z"),
                                                      (3, "xyz", "x,y,z"), (4, "xyz", "x,y,z,intensity")])
def test_float64_bin_is_refused_naming_the_file(tmp_path: Path, cols: int, point_format: str, layout: str) -> None:
    folder = tmp_path / "f64"
    folder.mkdir()
    for k in range(2):
        scan()[:, :cols].astype(np.float64).tofile(folder / f"{k:06d}.bin")
    path = folder / "000000.bin"
    problem = float64_bin_problem(path)
    assert problem is not None and problem.startswith(f"{path}: looks like float64 data, not float32")
    assert f"read as float64 it looks like {layout} points" in problem
    assert "astype(np.float32)" in problem
    with pytest.raises(DatasetError, match=re.escape(f"{path}: looks like float64 data")):
        read_point_file(path, point_format)
    with pytest.raises(DatasetError, match=re.escape(f"{path}: looks like float64 data")):
        FolderSequence(folder, point_format=point_format)
    from gr_graph.datasets.kitti import read_velodyne_bin  # KITTI roots read .bin the same way

    with pytest.raises(DatasetError, match=re.escape(f"{path}: looks like float64 data")):
        read_velodyne_bin(path, point_format)


def test_float32_bin_still_loads_exactly(tmp_path: Path) -> None:
    data = scan().astype(np.float32)
    data[::50, :3] = np.nan  # NaN rows of organized clouds are not float64 evidence
    path = tmp_path / "000000.bin"
    data.tofile(path)
    assert float64_bin_problem(path) is None
    cloud = read_point_file(path)
    keep = np.all(np.isfinite(data[:, :3]), axis=1)
    np.testing.assert_array_equal(cloud.points, data[keep, :3].astype(np.float64))
    np.testing.assert_array_equal(cloud.intensity, data[keep, 3])
    data[:, :3].copy().tofile(path)
    np.testing.assert_array_equal(read_point_file(path, "xyz").points, data[keep, :3].astype(np.float64))


def test_real_kitti_bins_are_not_float64(kitti_root: Path) -> None:
    from gr_graph.datasets.kitti import read_velodyne_bin

    files = sorted((kitti_root / "sequences" / "00" / "velodyne").glob("*.bin"))
    assert files
    for path in files:
        assert float64_bin_problem(path) is None
        raw = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        cloud = read_point_file(path)
        np.testing.assert_array_equal(cloud.points, raw[:, :3].astype(np.float64))
        np.testing.assert_array_equal(cloud.intensity, raw[:, 3])
        np.testing.assert_array_equal(read_velodyne_bin(path), raw)


# ----------------------------------------------------------------------------- 2. timestamp units


@pytest.mark.parametrize("values,unit", [
    (1700000000000 + 100 * np.arange(6), "ms"),             # epoch milliseconds (13 digits)
    (1700000000000000 + 100000 * np.arange(6), "us"),       # epoch microseconds (16 digits)
    (1700000000000000000 + 100000000 * np.arange(6), "ns"),  # epoch nanoseconds (19 digits)
    (1700000000.0 + 0.1 * np.arange(6), "s"),                # epoch seconds
    (3.0 + 0.1 * np.arange(6), "s"),                         # relative seconds
    (100 * np.arange(6), "ms"),                              # relative milliseconds
    (5e9 + 1e8 * np.arange(6), "ns"),                        # relative nanoseconds
])
def test_timestamp_unit_from_magnitude_and_spacing(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                   values: np.ndarray, unit: str) -> None:
    path = tmp_path / "times.txt"
    path.write_text("".join(f"{v}\n" for v in values.tolist()))
    with caplog.at_level(logging.INFO, logger="gr_graph.datasets.folder"):
        ts = read_timestamps_file(path, len(values))
    np.testing.assert_allclose(ts, 0.1 * np.arange(6), atol=1e-6)
    assert f"{path}: timestamps read in {unit} (median frame spacing 0.1 s)" in caplog.text


@pytest.mark.parametrize("values,unit,spacing", [
    (5.0 * np.arange(6), "s", 5.0),                           # a sequence subsampled to one frame in 5 s
    (1700000000.0 + 5.0 * np.arange(6), "s", 5.0),            # the same in epoch seconds
    (1700000000000 + 5000 * np.arange(6), "ms", 5.0),         # and in epoch milliseconds
    (2.5 * np.arange(6), "s", 2.5),
])
def test_sparse_frames_keep_their_unit(tmp_path: Path, caplog: pytest.LogCaptureFixture, values: np.ndarray,
                                      unit: str, spacing: float) -> None:
    path = tmp_path / "times.txt"
    path.write_text("".join(f"{v}\n" for v in values.tolist()))
    with caplog.at_level(logging.INFO, logger="gr_graph.datasets.folder"):
        ts = read_timestamps_file(path, len(values))
    np.testing.assert_allclose(ts, spacing * np.arange(6), rtol=1e-9)
    assert f"{path}: timestamps read in {unit} (median frame spacing {spacing:g} s)" in caplog.text


def test_epoch_milliseconds_times_file_in_a_folder(tmp_path: Path) -> None:
    folder = npy_folder(tmp_path / "ms", [f"{k:06d}.npy" for k in range(4)])
    (folder / "times.txt").write_text("".join(f"{1700000000000 + 100 * k}\n" for k in range(4)))
    seq = FolderSequence(folder)
    np.testing.assert_allclose(seq.timestamps, [0.0, 0.1, 0.2, 0.3], atol=1e-9)
    assert seq.scan_period == pytest.approx(0.1)


@pytest.mark.parametrize("values,why", [
    ([0, 0.001, 0.002, 0.003], r"no unit gives a LiDAR frame spacing of 0.005-10 s"),  # 1 kHz in s: no unit
    ([20000000000000 + 100 * k for k in range(4)], r"contradict"),  # spacing says ms, then 2e10 s: year 2603
])
def test_implausible_timestamps_are_refused(tmp_path: Path, values: list, why: str) -> None:
    path = tmp_path / "times.txt"
    path.write_text("".join(f"{v}\n" for v in values))
    with pytest.raises(DatasetError, match=re.escape(str(path)) + ": .*" + why):
        read_timestamps_file(path, len(values))


# ----------------------------------------------------------------------------- 3. file order


def test_float_stamp_names_are_ordered_by_value(tmp_path: Path) -> None:
    t = 1600000000.0 + 0.1 * np.arange(8) + np.array([0, 0.0003, -0.0002, 0, 0.0001, 0.0, -0.0001, 0.0002])
    names = [f"{x}.npy" for x in t]  # str(float): '1600000000.1003', '1600000000.3', ...
    assert "1600000000.3.npy" in names and any(len(n) > len("1600000000.1003.npy") for n in names)
    folder = npy_folder(tmp_path / "stamps", names[::-1])
    assert [p.name for p in point_files(folder)] == names
    assert [p.name for p in FolderSequence(folder).files] == names


def test_sec_unpadded_nsec_names_keep_their_order(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    stamps = [(100 + k // 10, (k % 10) * 100_000_000 + 5_000_000) for k in range(25)]  # 10 Hz, 5 ms past
    names = [f"{sec}.{nsec}.npy" for sec, nsec in stamps]  # f"{sec}.{nsec}": 100.5000000, 100.105000000, ...
    folder = npy_folder(tmp_path / "secnsec", names[::-1])
    with caplog.at_level(logging.WARNING, logger="gr_graph.datasets.folder"):
        assert [p.name for p in point_files(folder)] == names
    assert "seconds.nanoseconds" in caplog.text


@pytest.mark.parametrize("names", [
    [f"{n}.pcd" for n in (1, 2, 3, 10, 11)],                                       # unpadded
    [f"{n:06d}.bin" for n in range(5)],                                             # KITTI
    ["scan_1.pcd", "Scan_2.pcd", "scan_10.pcd"],                                    # prefixed
    [f"1600000000_{ns}.pcd" for ns in (50000000, 150000000, 950000000)] + ["1600000001_50000000.pcd"],  # sec_nsec
    ["frame2.pcd", "frame10.pcd", "frame11.pcd"],
])
def test_other_names_keep_the_natural_order(names: list[str]) -> None:
    files = [Path("/x") / n for n in names]
    assert [p.name for p in sort_point_files(files[::-1])] == names


# ----------------------------------------------------------------------------- 4. hidden files


def test_hidden_and_appledouble_files_are_skipped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = npy_folder(tmp_path / "stray", [f"{k:06d}.npy" for k in range(3)])
    (folder / "._000001.npy").write_bytes(b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X        " + bytes(400))
    (folder / ".hidden.npy").write_bytes(b"junk")
    (folder / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1" + bytes(100))
    with caplog.at_level(logging.WARNING, logger="gr_graph.datasets.folder"):
        seq = FolderSequence(folder)
    assert [p.name for p in seq.files] == ["000000.npy", "000001.npy", "000002.npy"]
    assert "skipped 2 hidden files named like scans (._000001.npy, .hidden.npy" in caplog.text

    only_hidden = tmp_path / "only_hidden"
    only_hidden.mkdir()
    (only_hidden / "._0.pcd").write_bytes(b"junk")
    with pytest.raises(DatasetError, match="only_hidden: not a recognised dataset"):
        guess_dataset(only_hidden)
    with pytest.raises(DatasetError, match=r"only_hidden: no point files .*; 1 hidden files skipped"):
        FolderSequence(only_hidden)


# ----------------------------------------------------------------------------- 5. empty clouds


def _empty_file(kind: str, path: Path) -> Path:
    if kind == "pcd_points0":
        return write_pcd(path.with_suffix(".pcd"), structured(np.zeros((0, 4))))
    if kind == "pcd_points0_ascii":
        return write_pcd(path.with_suffix(".pcd"), structured(np.zeros((0, 4))), ascii=True)
    if kind == "ply_vertex0":
        path = path.with_suffix(".ply")
        path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
                         b"property float y\nproperty float z\nproperty float intensity\nend_header\n")
        return path
    if kind == "npy_empty":
        np.save(path.with_suffix(".npy"), np.zeros((0, 4), np.float32))
        return path.with_suffix(".npy")
    if kind == "npy_struct_empty":
        np.save(path.with_suffix(".npy"), np.zeros(0, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")]))
        return path.with_suffix(".npy")
    path = path.with_suffix("." + kind.removeprefix("zero_"))  # a 0-byte .pcd / .ply / .npy
    path.write_bytes(b"")
    return path


@pytest.mark.parametrize("kind", ["pcd_points0", "pcd_points0_ascii", "ply_vertex0", "npy_empty", "npy_struct_empty",
                                  "zero_pcd", "zero_ply", "zero_npy"])
def test_empty_files_read_as_empty_clouds(tmp_path: Path, kind: str) -> None:
    cloud = read_point_file(_empty_file(kind, tmp_path / "0"))
    assert cloud.points.shape == (0, 3)


def _pcd_sequence_folder(folder: Path, empty: int, with_time: bool = False) -> Path:
    folder.mkdir()
    names = "x y z intensity t" if with_time else "x y z intensity"
    for k in range(4):
        path = folder / f"{k:06d}.pcd"
        if k == empty:
            path.write_bytes(b"")
        else:
            write_pcd(path, structured(scan(8, 200, with_time), names))
    return folder


def test_empty_pcd_in_a_sequence_is_an_empty_frame(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    folder = _pcd_sequence_folder(tmp_path / "zero_byte", empty=2)
    write_pcd(folder / "000001.pcd", structured(np.zeros((0, 4))))  # and a POINTS 0 one
    seq, _ = open_sequence(path=folder)
    with caplog.at_level(logging.WARNING, logger="gr_graph.datasets.folder"):
        frames = [seq[i] for i in range(len(seq))]
    assert [len(f.points) for f in frames] == [1600, 0, 0, 1600]
    assert frames[2].intensity.shape == (0,) and frames[2].index == 2
    assert f"{folder / '000001.pcd'}: empty scan (no points): frame 1 is empty (1 empty frame so far)" in caplog.text
    assert f"{folder / '000002.pcd'}: empty scan (a 0-byte file): frame 2 is empty (2 empty frames so far)" \
        in caplog.text
    assert seq.parent.empty_frames == {1, 2}


def test_empty_first_scan_probes_the_next_one(tmp_path: Path) -> None:
    folder = _pcd_sequence_folder(tmp_path / "first_empty", empty=0, with_time=True)
    seq = FolderSequence(folder)
    assert seq.motion_compensated is False and seq.conventions.has_time  # probed on 000001.pcd
    assert seq[0].points.shape == (0, 3) and seq[0].time.shape == (0,)
    assert seq[1].time is not None and 0.0 <= seq[1].time.min() and seq[1].time.max() <= 1.0


def test_truncated_and_corrupt_files_are_still_errors(tmp_path: Path) -> None:
    cut = write_pcd(tmp_path / "cut.pcd", structured(scan(4, 100)))
    cut.write_bytes(cut.read_bytes()[:-100])
    with pytest.raises(DatasetError, match=re.escape(f"{cut}: ") + ".*truncated"):
        read_pcd(cut)
    header_only = tmp_path / "header.pcd"
    header_only.write_bytes(b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\n")
    with pytest.raises(DatasetError, match=re.escape(f"{header_only}: no end of header")):
        read_pcd(header_only)
    no_z = write_pcd(tmp_path / "no_z.pcd", structured(np.zeros((0, 2)), "x y"))  # empty, but no z field
    with pytest.raises(DatasetError, match=re.escape(f"{no_z}: no field z")):
        read_pcd(no_z)
    ply = tmp_path / "cut.ply"
    ply.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nproperty float y\n"
                    b"property float z\nend_header\n" + bytes(12 * 5))
    with pytest.raises(DatasetError, match=re.escape(f"{ply}: ") + ".*truncated"):
        read_ply(ply)
    npy = tmp_path / "bad.npy"
    npy.write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(DatasetError, match=re.escape(f"{npy}: ")):
        read_npy(npy)
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.zeros((0, 7)))
    with pytest.raises(DatasetError, match=re.escape(f"{wrong}: array of shape (0, 7)")):
        read_npy(wrong)


def test_malformed_headers_name_the_file_and_comments_may_hold_any_text(tmp_path: Path) -> None:
    from gr_graph.datasets.point_files import read_point_file

    good = write_pcd(tmp_path / "good.pcd", structured(scan(4, 100)))
    text = good.read_bytes()
    for what in (b"POINTS\n", b"POINTS 1.0\n"):
        bad = tmp_path / "bad.pcd"
        bad.write_bytes(re.sub(rb"POINTS \d+\n", what, text, count=1))
        with pytest.raises(DatasetError, match=re.escape(f"{bad}: malformed PCD header or data")):
            read_point_file(bad)
    ply = tmp_path / "bad.ply"
    ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex two\nproperty float x\nproperty float y\n"
                    b"property float z\nend_header\n1 2 3\n")
    with pytest.raises(DatasetError, match=re.escape(f"{ply}: malformed PLY header or data")):
        read_point_file(ply)
    commented = tmp_path / "commented.pcd"
    commented.write_bytes(text.replace(b"VERSION", "# recorded at the caf\u00e9\nVERSION".encode("utf-8"), 1))
    np.testing.assert_array_equal(read_point_file(commented).points, read_point_file(good).points)


# ----------------------------------------------------------------------------- 6. non-finite intensity


def test_nonfinite_intensity_is_replaced_by_zero(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    pts = scan(8, 200)
    pts[1::20, 3] = np.nan   # 80 NaN intensities at finite points
    pts[2::40, 3] = np.inf   # 40 infinite ones
    pts[::50, 0] = np.nan    # 32 points with a NaN coordinate (dropped and counted, as before)
    pts[1, 0] = np.nan       # one of them also has a NaN intensity: not counted as an intensity fix
    keep = np.isfinite(pts[:, 0])
    n_fixed = int(np.sum(keep & ~np.isfinite(pts[:, 3])))
    path = write_pcd(tmp_path / "nan.pcd", structured(pts))
    with caplog.at_level(logging.WARNING, logger="gr_graph.datasets.pointcloud2"):
        cloud = read_point_file(path)
    assert n_fixed == 119
    assert f"{path}: 119 non-finite intensity values at finite points replaced by 0" in caplog.text
    assert cloud.dropped_nonfinite == int(np.sum(~keep))
    expected = pts[keep, 3].astype(np.float32)
    expected[~np.isfinite(expected)] = 0.0
    np.testing.assert_array_equal(cloud.intensity, expected)
    np.testing.assert_array_equal(cloud.points, pts[keep, :3].astype(np.float32).astype(np.float64))

    npy = tmp_path / "nan.npy"  # the same for the other readers (here an (N, 4) array)
    np.save(npy, pts)
    assert np.all(np.isfinite(read_point_file(npy).intensity))

    bad_time = scan(8, 200, with_time=True)
    bad_time[5, 4] = np.nan  # a non-finite per-point time is still an error
    path = write_pcd(tmp_path / "nan_t.pcd", structured(bad_time, "x y z intensity t"))
    with pytest.raises(DatasetError, match=re.escape(f"{path}: non-finite per-point times")):
        read_point_file(path)


def test_bag_messages_replace_nonfinite_intensity_too(caplog: pytest.LogCaptureFixture) -> None:
    from gr_graph.datasets.pointcloud2 import decode_structured

    pts = scan(8, 100)
    pts[3::10, 3] = np.nan  # 80 NaN intensities, as a PointCloud2 message would carry them
    with caplog.at_level(logging.WARNING, logger="gr_graph.datasets.pointcloud2"):
        cloud = decode_structured(structured(pts), "bag.mcap, message 3")
    assert "bag.mcap, message 3: 80 non-finite intensity values at finite points replaced by 0" in caplog.text
    assert len(cloud.points) == len(pts) and np.all(np.isfinite(cloud.intensity))
    assert np.count_nonzero(cloud.intensity == 0) >= 80
