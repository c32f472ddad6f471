"""Per-point times of partial sweeps, the ``sensor`` section's time and ring settings, half-azimuth
KITTI frames and ring counts that grow after the first frame (input-robustness audit)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.channels import subsample_channels
from gr_graph.datasets.folder import FolderSequence
from gr_graph.datasets.frame_fields import FieldConventions, guess_time_unit
from gr_graph.datasets.kitti import KittiSequence
from gr_graph.datasets.pointcloud2 import DecodedCloud
from gr_graph.datasets.rosbag import RosbagSequence
from gr_graph.deskew import normalise_times
from gr_graph.sensors import SensorConfig, SensorError, hdl64_elevations_deg
from loader_support import write_bag

PERIOD = 0.1


def _sweep(n_rings: int = 16, n_az: int = 360, lowest_first: bool = False, seed: int = 0) -> dict[str, np.ndarray]:
    """A clockwise sweep starting and ending facing backward: points, sweep fraction, ring (0 = highest)."""
    rng = np.random.default_rng(seed)
    frac = (np.arange(n_az) + 0.5) / n_az
    az = np.pi * (1.0 - 2.0 * frac)  # times_from_azimuth's convention: 0.5 straight ahead
    elevation = np.radians(np.linspace(10.0, -20.0, n_rings))
    ring = np.repeat(np.arange(n_rings), n_az)
    e, a, f = elevation[ring], np.tile(az, n_rings), np.tile(frac, n_rings)
    r = 10.0 + rng.uniform(0.0, 5.0, len(ring))
    pts = np.column_stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e)])
    stored = (n_rings - 1 - ring) if lowest_first else ring
    return {"points": pts, "frac": f, "ring": stored, "az": a}


def _cloud(s: dict[str, np.ndarray], keep: np.ndarray | None = None, times: np.ndarray | None = None,
           with_ring: bool = True) -> DecodedCloud:
    keep = np.ones(len(s["points"]), bool) if keep is None else keep
    t = None if times is None else times[keep]
    return DecodedCloud(s["points"][keep], None, t, None if t is None else "t",
                        s["ring"][keep] if with_ring else None, 0)


# ---------------------------------------------------------------- 1. partial sweeps
def test_partial_sweep_times_count_from_the_sweep_start() -> None:
    t = np.linspace(0.05, 0.1, 50)  # the second half of a 0.1 s sweep, seconds from its start
    np.testing.assert_allclose(normalise_times(t, PERIOD), t / PERIOD)
    assert normalise_times(t, PERIOD)[0] == pytest.approx(0.5)
    back = t - PERIOD  # the same, counted back from the sweep's end
    np.testing.assert_allclose(normalise_times(back, PERIOD), t / PERIOD, atol=1e-12)
    np.testing.assert_allclose(normalise_times(back, PERIOD, reference="sweep_end"), t / PERIOD, atol=1e-12)
    # absolute stamps: from the frame's stamp when the times fall in the sweep starting there
    stamp = 1.7e9
    np.testing.assert_allclose(normalise_times(stamp + t, PERIOD, sweep_start=stamp), t / PERIOD, atol=1e-5)
    # ... else (no stamp, or a stamp on another clock) from the earliest point, as before
    np.testing.assert_allclose(normalise_times(stamp + t, PERIOD), (t - t[0]) / PERIOD, atol=1e-5)
    np.testing.assert_allclose(normalise_times(stamp + t, PERIOD, sweep_start=5.0), (t - t[0]) / PERIOD, atol=1e-5)


def test_full_sweep_fractions_are_unchanged() -> None:
    """Full sweeps (earliest time within 1 % of a period of the reference) map exactly as before."""
    rng = np.random.default_rng(3)
    for t in (np.sort(rng.uniform(0.0, PERIOD, 1000)), np.linspace(8e-6, 0.0999, 1000),
              np.linspace(-0.0999, 0.0, 1000), 1.7e9 + np.linspace(0.0, 0.0999, 1000)):
        np.testing.assert_array_equal(normalise_times(t, PERIOD), np.clip((t - t.min()) / PERIOD, 0.0, 1.0))
    t = np.linspace(8e-6, 0.0999, 1000)
    np.testing.assert_array_equal(normalise_times(1.7e9 + t, PERIOD, sweep_start=1.7e9),
                                  normalise_times(1.7e9 + t, PERIOD))


def test_folder_partial_sweep_keeps_its_place(tmp_path: Path) -> None:
    s = _sweep()
    front = np.abs(s["az"]) < np.pi / 2
    for k in range(3):
        keep = front if k == 1 else np.ones(len(front), bool)
        arr = np.zeros(int(keep.sum()), [("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"), ("time", "f4")])
        for i, c in enumerate("xyz"):
            arr[c] = s["points"][keep, i]
        arr["time"] = (s["frac"][keep] * PERIOD).astype(np.float32)
        np.save(tmp_path / f"{k:06d}.npy", arr)
    seq = FolderSequence(tmp_path)
    full, half = seq[0], seq[1]
    np.testing.assert_allclose(full.time, s["frac"] - s["frac"].min(), atol=1e-6)  # a full sweep: as before
    # the front half lies in the middle of the sweep (0.25..0.75), not stretched from 0
    np.testing.assert_allclose(half.time, s["frac"][front], atol=1e-6)
    assert 0.24 < half.time.min() < 0.26 and 0.74 < half.time.max() < 0.76


# ---------------------------------------------------------------- 2. sensor time settings
def test_explicit_time_unit_overrides_the_guess() -> None:
    s = _sweep()
    ns = np.round(s["frac"] * PERIOD * 1e9)  # Ouster-style nanoseconds
    guessed = FieldConventions.probe(_cloud(s, times=ns), PERIOD, "a.pcd", SensorConfig())  # nothing given
    assert guessed.time_unit_s == 1e-9 and guessed.time_tolerance is None
    full = s["frac"] - s["frac"].min()  # a full sweep: counted from its first point, as before
    np.testing.assert_allclose(guessed.frame(_cloud(s, times=ns), 0, 0.0, "a.pcd").time, full, atol=1e-8)
    said_ns = FieldConventions.probe(_cloud(s, times=ns), PERIOD, "a.pcd", SensorConfig(time_unit="ns"))
    np.testing.assert_allclose(said_ns.frame(_cloud(s, times=ns), 0, 0.0, "a.pcd").time, full, atol=1e-8)
    # nanoseconds declared as seconds: refused at once, naming the file and the setting
    with pytest.raises(DatasetError, match=r"a\.pcd: .*check sensor\.time_unit"):
        FieldConventions.probe(_cloud(s, times=ns), PERIOD, "a.pcd", SensorConfig(time_unit="s"))
    # seconds declared as milliseconds: a span of 0.1 ms does not fill a sweep but fits it; a later frame
    # whose times leave the sweep is refused
    conv = FieldConventions.probe(_cloud(s, times=s["frac"] * 100.0), PERIOD, "a.pcd", SensorConfig(time_unit="ms"))
    assert conv.time_unit_s == 1e-3
    with pytest.raises(DatasetError, match=r"b\.pcd: .*sweep fractions"):
        conv.frame(_cloud(s, times=s["frac"] * 1000.0), 1, 0.1, "b.pcd")


def test_time_reference_and_scan_period_are_honoured() -> None:
    s = _sweep()
    back_half = s["frac"] >= 0.5
    t = s["frac"] * 0.05  # a 20 Hz sweep (0.05 s) in frames 0.1 s apart
    sensor = SensorConfig(time_unit="s", time_reference="sweep_start", scan_period=0.05)
    conv = FieldConventions.probe(_cloud(s, times=t), PERIOD, "a.pcd", sensor)
    assert conv.scan_period == 0.05 and conv.time_reference == "sweep_start"
    np.testing.assert_allclose(conv.frame(_cloud(s, back_half, times=t), 1, 0.1, "b.pcd").time,
                               s["frac"][back_half], atol=1e-9)
    end = FieldConventions.probe(_cloud(s, times=t - 0.05), PERIOD, "a.pcd",
                                 SensorConfig(time_reference="sweep_end", scan_period=0.05))
    np.testing.assert_allclose(end.frame(_cloud(s, back_half, times=t - 0.05), 1, 0.1, "b.pcd").time,
                               s["frac"][back_half], atol=1e-9)
    # times counted from the start declared as counted back from the end do not fit the sweep
    with pytest.raises(DatasetError, match="check sensor.time_unit, sensor.time_reference"):
        FieldConventions.probe(_cloud(s, times=t), PERIOD, "a.pcd",
                               SensorConfig(time_reference="sweep_end", scan_period=0.05))


def test_has_time_false_drops_the_time_field(caplog: pytest.LogCaptureFixture) -> None:
    s = _sweep()
    cloud = _cloud(s, times=s["frac"] * PERIOD)
    with caplog.at_level(logging.WARNING):
        conv = FieldConventions.probe(cloud, PERIOD, "a.pcd", SensorConfig(has_time=False))
    assert "sensor.has_time: false" in caplog.text
    frame = conv.frame(cloud, 0, 0.0, "a.pcd")
    assert frame.time is None  # the odometry takes times from the azimuth
    assert conv.has_time and not conv.motion_compensated  # the scans are still raw sweeps
    with pytest.raises(DatasetError, match="sensor.has_time is true"):
        FieldConventions.probe(_cloud(s), PERIOD, "a.pcd", SensorConfig(has_time=True))


def test_times_to_fractions_keeps_partial_sweeps_and_refuses_a_wrong_unit() -> None:
    sensor = SensorConfig(time_unit="s", scan_period=PERIOD)
    np.testing.assert_allclose(sensor.times_to_fractions(np.array([0.05, 0.07, 0.1])), [0.5, 0.7, 1.0])
    with pytest.raises(SensorError, match="check sensor.time_unit"):
        sensor.times_to_fractions(np.array([0.0, 5e7, 1e8]))


def test_bag_loader_takes_the_sensor_section(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    s = _sweep()
    arr = np.zeros(len(s["points"]), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                                      ("ring", "<u2"), ("t", "<u4")])
    for i, c in enumerate("xyz"):
        arr[c] = s["points"][:, i]
    arr["ring"] = s["ring"]
    arr["t"] = np.round(s["frac"] * PERIOD * 1e9)
    bag = write_bag(tmp_path / "b", {"/points": [arr, arr]})
    assert RosbagSequence(bag)[1].time is not None
    with caplog.at_level(logging.WARNING):
        seq = RosbagSequence(bag, sensor=SensorConfig(has_time=False, has_ring=False))
    assert seq[1].time is None and seq[1].ring is None and not seq.motion_compensated
    assert "sensor.has_time: false" in caplog.text and "sensor.has_ring: false" in caplog.text
    with pytest.raises(DatasetError, match="check sensor.time_unit"):
        RosbagSequence(bag, sensor=SensorConfig(time_unit="us"))


# ---------------------------------------------------------------- 2b. sweep duration from the times
def test_a_full_revolution_sets_the_sweep_duration_when_the_spacing_disagrees(
        caplog: pytest.LogCaptureFixture) -> None:
    s = _sweep()
    ns20 = np.round(s["frac"] * 0.05 * 1e9)  # a 20 Hz sweep (0.05 s) in ns, frames taken 0.1 s apart
    with caplog.at_level(logging.WARNING):
        conv = FieldConventions.probe(_cloud(s, times=ns20), PERIOD, "a.pcd")
    assert conv.scan_period == pytest.approx(0.05, rel=0.01) and conv.scan_period_source == "per-point times"
    assert "a.pcd" in caplog.text and "sensor.scan_period" in caplog.text
    frac = conv.frame(_cloud(s, times=ns20), 0, 0.0, "a.pcd").time
    assert frac.min() == 0.0 and frac.max() == pytest.approx(1.0)  # not 0..0.5
    # the front half of the same sweep is not a revolution: the spacing stays
    front = np.abs(s["az"]) < np.pi / 2
    half = FieldConventions.probe(_cloud(s, front, times=ns20), PERIOD, "a.pcd")
    assert half.scan_period == PERIOD and half.scan_period_source == "frame spacing"
    # within 10 % of the spacing: the spacing, exactly (results of data that agree do not move)
    close = FieldConventions.probe(_cloud(s, times=s["frac"] * 0.093), PERIOD, "a.pcd")
    assert close.scan_period == PERIOD
    # a given scan period wins over both
    said = FieldConventions.probe(_cloud(s, times=ns20), PERIOD, "a.pcd", SensorConfig(scan_period=0.08))
    assert said.scan_period == 0.08 and said.scan_period_source == "sensor.scan_period"


def test_a_start_up_fragment_first_does_not_set_the_sweep_duration(tmp_path: Path) -> None:
    """A driver's first message after start-up is often a fragment of a revolution: the sweep duration
    comes from the first probe frame that covers a full revolution (before, the fragment kept the
    frame spacing, 0.1 s, and a 20 Hz sensor's full sweeps got time fractions 0..0.5: half the
    deskewing)."""
    s = _sweep()
    ns20 = np.round(s["frac"] * 0.05 * 1e9)
    fragment = s["frac"] >= 0.75  # the last quarter of a revolution
    conv = FieldConventions.probe(_cloud(s, fragment, times=ns20), PERIOD, "0.pcd",
                                  more=[(_cloud(s, times=ns20), "1.pcd"), (_cloud(s, times=ns20), "2.pcd")])
    assert conv.scan_period == pytest.approx(0.05, rel=0.01) and conv.scan_period_source == "per-point times"
    frac = conv.frame(_cloud(s, times=ns20), 1, 0.0, "1.pcd").time
    assert frac.min() == 0.0 and frac.max() == pytest.approx(1.0)
    # fragments only: the frame spacing stays
    only = FieldConventions.probe(_cloud(s, fragment, times=ns20), PERIOD, "0.pcd",
                                  more=[(_cloud(s, fragment, times=ns20), "1.pcd")])
    assert only.scan_period == PERIOD and only.scan_period_source == "frame spacing"
    # a folder of 20 Hz scans without a timestamps file whose first scan is the fragment
    folder = _sweep_folder(tmp_path / "hz20", 0.05, None)
    arr = np.load(folder / "000000.npy")
    np.save(folder / "000000.npy", arr[fragment])
    seq = FolderSequence(folder)
    assert seq.scan_period == pytest.approx(0.05, rel=0.01)
    assert seq[1].time.max() == pytest.approx(1.0)


def _sweep_folder(folder: Path, sweep_s: float, times_txt: np.ndarray | None) -> Path:
    s = _sweep()
    folder.mkdir()
    arr = np.zeros(len(s["points"]), [("x", "f4"), ("y", "f4"), ("z", "f4"), ("t", "u4")])
    for i, c in enumerate("xyz"):
        arr[c] = s["points"][:, i]
    arr["t"] = np.round(s["frac"] * sweep_s * 1e9)
    for k in range(3):
        np.save(folder / f"{k:06d}.npy", arr)
    if times_txt is not None:
        np.savetxt(folder / "times.txt", times_txt, fmt="%.3f")
    return folder


def test_folder_and_bag_take_the_sweep_duration(tmp_path: Path) -> None:
    # 20 Hz, no timestamps file: frames one sweep apart, not 0.1 s
    hz20 = FolderSequence(_sweep_folder(tmp_path / "hz20", 0.05, None))
    assert hz20.scan_period == pytest.approx(0.05, rel=0.01)
    np.testing.assert_allclose(np.diff(hz20.timestamps), hz20.scan_period)
    # every other frame of a 10 Hz sensor kept: the stamps stay, the sweep is 0.1 s
    sub = FolderSequence(_sweep_folder(tmp_path / "sub", 0.1, 0.2 * np.arange(3)))
    assert sub.scan_period == pytest.approx(0.1, rel=0.01)
    np.testing.assert_allclose(np.diff(sub.timestamps), 0.2)
    # frames 0.1 s apart, 0.1 s sweeps: the spacing, as before
    usual = FolderSequence(_sweep_folder(tmp_path / "usual", 0.1, None))
    # (the stamps then move to the sweeps' middles: times counted from the sweep's start, +0.05 s)
    assert usual.stamps_moved_by_s == pytest.approx(0.05, abs=1e-3)
    assert usual.scan_period == 0.1 and np.array_equal(usual.timestamps, np.arange(3) * 0.1 + usual.stamps_moved_by_s)
    # ... also where the median spacing of k x 0.1 rounds off 0.1 (100 frames): the times, and so the
    # data fingerprint a resume compares, are exactly those of before
    for k in range(3, 100):
        np.save(tmp_path / "usual" / f"{k:06d}.npy", np.load(tmp_path / "usual" / "000000.npy"))
    many = FolderSequence(tmp_path / "usual")
    assert many.scan_period != 0.1
    assert np.array_equal(many.timestamps, np.arange(100) * 0.1 + many.stamps_moved_by_s)
    # a bag: the sensor section's scan period reaches the sequence (and so the deskewer)
    s = _sweep()
    arr = np.zeros(len(s["points"]), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<u4")])
    for i, c in enumerate("xyz"):
        arr[c] = s["points"][:, i]
    arr["t"] = np.round(s["frac"] * 0.1 * 1e9)
    bag = write_bag(tmp_path / "b", {"/points": [arr, arr]})
    assert RosbagSequence(bag).scan_period == 0.1
    assert RosbagSequence(bag, sensor=SensorConfig(scan_period=0.12)).scan_period == 0.12


# ---------------------------------------------------------------- 3. half-azimuth KITTI frames
def _kitti_scan(rng: np.random.Generator, n_az: int = 700) -> np.ndarray:
    """An HDL-64E-like scan stored line by line, each line one clockwise turn from azimuth 0."""
    elevation = np.radians(hdl64_elevations_deg())
    az = -np.linspace(0.0, 2.0 * np.pi, n_az, endpoint=False)
    lines = []
    for e in elevation:
        a = az + rng.normal(0.0, 1e-4, n_az)
        r = 15.0 + 5.0 * np.sin(3.0 * a) + rng.normal(0.0, 0.02, n_az)
        r = np.minimum(r, 1.6 / np.tan(-e)) if e < -0.01 else r  # a ground plane 1.6 m below
        lines.append(np.column_stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e),
                                      rng.uniform(0.0, 1.0, n_az)]))
    return np.concatenate(lines).astype(np.float32)


def test_half_azimuth_kitti_frame_gets_elevation_rings(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    seq_dir = tmp_path / "sequences" / "00"
    (seq_dir / "velodyne").mkdir(parents=True)
    (seq_dir / "calib.txt").write_text("Tr: " + " ".join(str(v) for v in np.eye(4)[:3].ravel()) + "\n")
    (seq_dir / "times.txt").write_text("".join(f"{0.1 * k:.6f}\n" for k in range(6)))
    rng = np.random.default_rng(0)
    for k in range(6):
        scan = _kitti_scan(rng)
        if k == 2:
            scan = scan[np.abs(np.arctan2(scan[:, 1], scan[:, 0])) < np.pi / 2]
        scan.tofile(seq_dir / "velodyne" / f"{k:06d}.bin")
    seq = KittiSequence(tmp_path, "00")
    assert len(np.unique(seq[0].ring)) == 64 and seq.ring_recovery_counts["storage_order"] == 1
    with caplog.at_level(logging.WARNING):
        half = seq[2]
    assert seq.ring_recovery_counts["elevation"] == 1 and seq.ring_recovery_counts["reference"] == 0
    assert "rings by elevation" in caplog.text and "too few lines" in caplog.text
    counts = np.bincount(half.ring, minlength=64)
    assert np.count_nonzero(counts) >= 60 and counts.max() < 0.05 * len(half)  # not one ring
    sub = subsample_channels(half, 16)
    assert 0.2 * len(half) < len(sub) < 0.3 * len(half)


# ---------------------------------------------------------------- 4. ring counts
def test_more_rings_than_the_first_frame_is_an_error_naming_the_fix() -> None:
    s = _sweep(n_rings=64, n_az=60, lowest_first=True)  # Velodyne numbering: ring 0 is the lowest beam
    sky = s["ring"] < 48  # the first frame has no returns on its top 16 beams
    conv = FieldConventions.probe(_cloud(s, sky), PERIOD, "000000.pcd")
    assert conv.n_rings == 48 and conv.flip_rings
    with pytest.raises(DatasetError, match=r"000001.pcd: ring 63 >= 48 rings counted in the probe frames.*--sensor"):
        conv.frame(_cloud(s), 1, 0.1, "000001.pcd")  # not renumbered on the fly (stride, flips, threads)


def test_named_sensor_fixes_the_ring_count() -> None:
    s = _sweep(n_rings=64, n_az=60, lowest_first=True)
    sky = s["ring"] < 48
    for sensor in (SensorConfig(model="os1-64"), SensorConfig(model="custom", n_beams=64,
                                                              vertical_fov_deg=(10.0, -20.0))):
        conv = FieldConventions.probe(_cloud(s, sky), PERIOD, "000000.pcd", sensor)
        first = conv.frame(_cloud(s, sky), 0, 0.0, "000000.pcd")
        assert first.n_rings == 64
        np.testing.assert_array_equal(first.ring, 63 - s["ring"][sky])  # the same numbering as later frames
        np.testing.assert_array_equal(conv.frame(_cloud(s), 1, 0.1, "000001.pcd").ring, 63 - s["ring"])
    # the default sensor (nothing said) does not fix the count: a 16-ring recording keeps 16
    assert FieldConventions.probe(_cloud(_sweep()), PERIOD, "a.pcd", SensorConfig()).n_rings == 16
    with pytest.raises(DatasetError, match="ring 63 >= 16 rings of the sensor"):
        FieldConventions.probe(_cloud(s), PERIOD, "a.pcd", SensorConfig(model="vlp16"))


def test_has_ring_false_drops_the_ring_field(caplog: pytest.LogCaptureFixture) -> None:
    s = _sweep(n_rings=64, n_az=60, lowest_first=True)
    sensor = SensorConfig(model="custom", n_beams=64, vertical_fov_deg=(10.0, -20.0), has_ring=False)
    with caplog.at_level(logging.WARNING):
        conv = FieldConventions.probe(_cloud(s, s["ring"] < 48), PERIOD, "000000.pcd", sensor)
    assert "sensor.has_ring: false" in caplog.text
    frame = conv.frame(_cloud(s), 1, 0.1, "000001.pcd")  # ring 63 is no error: rings are not read
    assert frame.ring is None and frame.n_rings == 64
    with pytest.raises(DatasetError, match="sensor.has_ring is true"):
        FieldConventions.probe(_cloud(s, with_ring=False), PERIOD, "a.pcd", SensorConfig(has_ring=True))


def test_full_sweep_stamped_a_little_before_its_first_point_maps_as_before() -> None:
    """A driver's latency (first firing 3 ms after the stamp) does not shift a full sweep."""
    stamp = 1000.0
    t = stamp + np.linspace(0.003, 0.1029, 200)
    frac = normalise_times(t, 0.1, "auto", stamp)
    np.testing.assert_allclose(frac, (t - t.min()) / 0.1)


def test_absolute_stamps_of_a_driver_that_stamps_the_sweep_end() -> None:
    stamp = 1000.0
    t = stamp + np.linspace(-0.0999, 0.0, 200)  # the stamp marks the last point (e.g. Robosense, Hesai)
    frac = normalise_times(t, 0.1, "absolute", stamp, 0.05)
    assert frac.min() == pytest.approx(0.0) and frac.max() == pytest.approx(0.999)
    half = stamp + np.linspace(-0.05, 0.0, 100)  # a half sweep stamped at its end: the second half
    np.testing.assert_allclose(normalise_times(half, 0.1, "absolute", stamp, 0.05), (half - stamp + 0.1) / 0.1)
    with pytest.raises(ValueError, match="sweep fractions"):  # another clock, said to be the stamps' clock
        normalise_times(stamp + 5.0 + np.linspace(0, 0.05, 10), 0.1, "absolute", stamp, 0.05)


def test_a_128_ring_recording_opens_without_naming_the_sensor(tmp_path: Path) -> None:
    from gr_graph.datasets.registry import open_sequence

    s = _sweep(n_rings=128, n_az=90)
    folder = tmp_path / "os128"
    folder.mkdir()
    for k in range(3):
        cloud = _cloud(s)
        arr = np.zeros(len(cloud.points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", "<u2")])
        arr["x"], arr["y"], arr["z"] = cloud.points.T
        arr["ring"] = cloud.ring
        np.save(folder / f"{k:06d}.npy", arr)
    seq, _ = open_sequence(path=folder)  # the default sensor (nothing said): the rings come from the data
    assert seq[2].n_rings == 128 and int(seq[2].ring.max()) == 127
    with pytest.raises(DatasetError, match="ring 127 >= 64 rings of the sensor"):  # a named 64-beam sensor
        open_sequence(path=folder, sensor="os1-64")


# ---------------------------------------------------------------- 5. probe frames spread over the sequence
def _timed_folder(folder: Path, n: int, spans_ns: dict[int, float], rings_of: dict[int, int] | None = None) -> Path:
    """``n`` .npy sweeps (uint32 ns times ``t``, Velodyne ring numbering); frame k's times span
    ``spans_ns.get(k, 0.1 s)`` (a 2 ms first message: its points cover 2 % of the azimuth), its rings
    are those below ``rings_of.get(k, 16)``."""
    folder.mkdir()
    s = _sweep(n_rings=16, n_az=200, lowest_first=True)
    for k in range(n):
        span = spans_ns.get(k, 0.1e9)
        keep = s["ring"] < (rings_of or {}).get(k, 16)
        if span < 0.1e9:
            keep &= s["frac"] <= span / 0.1e9
        arr = np.zeros(int(keep.sum()), [("x", "f4"), ("y", "f4"), ("z", "f4"), ("ring", "u2"), ("t", "u4")])
        for i, c in enumerate("xyz"):
            arr[c] = s["points"][keep, i]
        arr["ring"] = s["ring"][keep]
        arr["t"] = np.round(s["frac"][keep] * span / max(float(s["frac"][keep].max()), 1e-9) if span > 0.1e9
                            else s["frac"][keep] * 0.1e9)
        np.save(folder / f"{k:06d}.npy", arr)
    return folder


def test_a_short_first_message_does_not_set_the_time_unit(tmp_path: Path) -> None:
    """A first message of 2 ms (ns times): alone it reads as microseconds (before, every later full
    sweep was then clipped to fraction 1 without a word); the probe frames spread over the folder set ns."""
    from gr_graph.datasets.point_files import read_point_file

    folder = _timed_folder(tmp_path / "f", 6, {0: 2e6})
    first = folder / "000000.npy"
    assert guess_time_unit(read_point_file(first).time, PERIOD) == 1e-6  # what the first frame alone says
    with pytest.raises(DatasetError, match="000000.npy: .*guessed"):  # alone, the wrong guess is now refused
        FieldConventions.probe(read_point_file(first), PERIOD, str(first))
    seq = FolderSequence(folder)
    assert seq.conventions.time_unit_s == 1e-9
    full = seq[3].time
    assert full.min() < 0.01 and full.max() > 0.99 and 0.4 < np.median(full) < 0.6  # a whole sweep, spread
    assert seq[0].time.max() < 0.03  # the 2 ms message keeps its place at the sweep's start
    assert seq.conventions.n_overlong_frames == 0
    # two frames, the short one first: the full sweep sets the unit (the upper median)
    two = tmp_path / "two"
    two.mkdir()
    for name in ("000000.npy", "000001.npy"):
        (two / name).write_bytes((folder / name).read_bytes())
    assert FolderSequence(two).conventions.time_unit_s == 1e-9


def test_an_overlong_frame_is_clipped_and_counted_a_wrong_guess_refused(tmp_path: Path,
                                                                         caplog: pytest.LogCaptureFixture) -> None:
    # frame 5 of 10 (not a probe: 0, 2, 4, 7, 9) spans five sweeps: clipped, logged, counted
    seq = FolderSequence(_timed_folder(tmp_path / "a", 10, {5: 0.5e9}))
    assert seq.conventions.time_unit_s == 1e-9
    with caplog.at_level(logging.WARNING):
        long = seq[5].time
    assert long.max() == 1.0 and np.mean(long == 1.0) > 0.7
    assert seq.conventions.n_overlong_frames == 1 and "000005.npy" in caplog.text and "clipped" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        np.testing.assert_array_equal(seq[5].time, long)  # read again (a later round): counted and logged once
    assert seq.conventions.n_overlong_frames == 1 and "clipped" not in caplog.text
    # the same at a probe frame: refused when the folder is opened, naming the file and the fix
    with pytest.raises(DatasetError, match=r"000004.npy: .*guessed.*sensor.time_unit"):
        FolderSequence(_timed_folder(tmp_path / "b", 10, {4: 0.5e9}))
    # with the unit given, an overlong frame is an error as before
    given = FolderSequence(_timed_folder(tmp_path / "c", 10, {5: 0.5e9}), sensor=SensorConfig(time_unit="ns"))
    with pytest.raises(DatasetError, match="000005.npy"):
        given[5]


def test_the_ring_count_comes_from_frames_spread_over_the_sequence(tmp_path: Path) -> None:
    """Velodyne numbering (ring 0 lowest), the first frames see no sky returns on the top 5 beams:
    11 rings alone (not rounded to 16), a crash at the first frame with a building; the probes find 16."""
    rings_of = {k: 11 for k in range(4)}
    seq = FolderSequence(_timed_folder(tmp_path / "f", 8, {}, rings_of))
    assert seq.n_rings == 16 and seq.conventions.flip_rings
    full = _sweep(n_rings=16, n_az=200, lowest_first=True)["ring"]
    np.testing.assert_array_equal(np.unique(seq[0].ring), np.unique(15 - full[full < 11]))
    np.testing.assert_array_equal(np.unique(seq[5].ring), np.arange(16))  # numbered as frame 0's
    # a bag, the same: the probe messages are decoded while the bag is indexed
    arrs = [np.load(p) for p in sorted((tmp_path / "f").glob("*.npy"))]
    bag = RosbagSequence(write_bag(tmp_path / "b", {"/points": arrs}))
    assert bag.n_rings == 16 and bag.conventions.time_unit_s == 1e-9
    np.testing.assert_array_equal(bag[6].ring, seq[6].ring)


def test_an_empty_message_without_fields_is_an_empty_frame() -> None:
    """A warm-up message of a bag with per-point times and rings that declares no fields."""
    from gr_graph.datasets.pointcloud2 import empty_cloud

    s = _sweep()
    conv = FieldConventions.probe(_cloud(s, times=s["frac"] * PERIOD), PERIOD, "m0")
    assert conv.has_time and conv.has_ring
    frame = conv.frame(empty_cloud(), 3, 0.3, "m3")
    assert len(frame.points) == 0 and frame.time.shape == (0,) and frame.ring.shape == (0,)
    with pytest.raises(DatasetError, match="m4: no per-point time field"):  # points without the field: an error
        conv.frame(_cloud(s), 4, 0.4, "m4")


def test_data_with_other_rings_than_the_unnamed_default_sensor_are_warned_about(tmp_path: Path) -> None:
    """A 16-ring folder without --sensor: the loop threshold stays the HDL-64E's, which is said."""
    from gr_graph.config import LoopConfig, loop_max_rmse
    from gr_graph.frame_loop import unnamed_sensor_note

    seq = FolderSequence(_timed_folder(tmp_path / "f", 3, {}))
    default = SensorConfig()
    threshold = loop_max_rmse(LoopConfig(), default, None)
    note = unnamed_sensor_note(seq, default, threshold)
    assert note is not None and "16 rings" in note and f"{threshold:.3f} m" in note and "--sensor" in note
    named = SensorConfig(model="vlp16")
    assert unnamed_sensor_note(FolderSequence(tmp_path / "f", sensor=named), named, 0.5) is None
    assert unnamed_sensor_note(object(), default, threshold) is None  # KITTI, synthetic: rings not from the data
