"""Conventions fixed from a sequence's first frame: time units, ring counts and ring order."""

from __future__ import annotations

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError
from gr_graph.datasets.frame_fields import FieldConventions, guess_time_unit, ring_count, rings_rise_with_elevation
from gr_graph.datasets.pointcloud2 import DecodedCloud


@pytest.mark.parametrize("unit,span", [(1.0, 0.0999), (1e-3, 99.9), (1e-6, 99_900.0), (1e-9, 99_900_000.0),
                                       (1.0, 0.05), (1e-9, 4.9e7)])
def test_time_unit_from_the_sweep_span(unit: float, span: float) -> None:
    times = np.linspace(-span, 0.0, 100)  # Velodyne-style: relative to the end of the sweep
    assert guess_time_unit(times, 0.1) == unit
    assert guess_time_unit(times + 1.7e9 / unit, 0.1) == unit  # absolute stamps: only the span matters


def test_ring_counts() -> None:
    assert [ring_count(m) for m in (15, 13, 31, 63, 127, 39)] == [16, 16, 32, 64, 128, 40]


def _cloud(n_rings: int, lowest_first: bool, times: np.ndarray | None = None) -> DecodedCloud:
    elevation = np.radians(np.linspace(15.0, -15.0, n_rings))  # ring 0 highest
    az = np.linspace(-np.pi, np.pi, 50, endpoint=False)
    ring = np.repeat(np.arange(n_rings), len(az))
    e, a = elevation[ring], np.tile(az, n_rings)
    pts = 10.0 * np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    stored = n_rings - 1 - ring if lowest_first else ring
    return DecodedCloud(pts, None, times, None if times is None else "t", stored, 0)


def test_ring_order_and_frames() -> None:
    up = _cloud(16, lowest_first=True)
    assert rings_rise_with_elevation(up.points, up.ring)
    conv = FieldConventions.probe(up, 0.1, "src")
    assert conv.n_rings == 16 and conv.flip_rings and not conv.has_time
    frame = conv.frame(up, 3, 0.3, "src")
    np.testing.assert_array_equal(frame.ring, np.repeat(np.arange(16), 50))
    assert frame.n_rings == 16 and not frame.intensity.any() and frame.time is None
    down = _cloud(16, lowest_first=False)
    assert not FieldConventions.probe(down, 0.1, "src").flip_rings
    too_many = _cloud(20, lowest_first=False)
    with pytest.raises(DatasetError, match="later.bag: ring 19 >= 16 rings counted in the probe frames"):
        conv.frame(too_many, 4, 0.4, "later.bag")


def test_interleaved_ring_numbers_are_renumbered_by_elevation(caplog: pytest.LogCaptureFixture) -> None:
    """Laser ids in firing order (VLP-16-style: even ids the lower half, odd ids the upper, each rising):
    the frames' rings count from the highest beam by elevation, so --channels keeps beams spread over
    the whole field of view, not the upper half only."""
    import logging

    from gr_graph.datasets.base import LidarFrame
    from gr_graph.datasets.channels import subsample_channels

    n = 64
    elevation_deg = np.linspace(2.0, -24.8, n)  # by beam, highest first
    beam_of_id = np.array([n - 1 - k // 2 if k % 2 == 0 else n // 2 - 1 - k // 2 for k in range(n)])
    assert sorted(beam_of_id) == list(range(n))  # even ids: lowest beams rising, odd ids: upper half rising
    az = np.linspace(-np.pi, np.pi, 40, endpoint=False)
    ids = np.repeat(np.arange(n), len(az))
    e, a = np.radians(elevation_deg[beam_of_id[ids]]), np.tile(az, n)
    pts = 15.0 * np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    cloud = DecodedCloud(pts, None, None, None, ids, 0)
    with caplog.at_level(logging.WARNING):
        conv = FieldConventions.probe(cloud, 0.1, "firing_order.pcd")
    assert "not in elevation order" in caplog.text and conv.ring_table is not None and not conv.flip_rings
    frame = conv.frame(cloud, 0, 0.0, "firing_order.pcd")
    np.testing.assert_array_equal(frame.ring, beam_of_id[ids])  # numbered by elevation, highest first
    kept = subsample_channels(LidarFrame(0, 0.0, frame.points, frame.intensity, frame.ring, n), 16)
    kept_elevation = np.degrees(np.arctan2(kept.points[:, 2], np.hypot(kept.points[:, 0], kept.points[:, 1])))
    assert kept_elevation.max() == pytest.approx(2.0) and kept_elevation.min() < -23.0  # every 4th beam
    # rings in order (or reversed) need no table: the frames are as before
    assert FieldConventions.probe(_cloud(16, lowest_first=True), 0.1, "src").ring_table is None
    assert FieldConventions.probe(_cloud(16, lowest_first=False), 0.1, "src").ring_table is None
    # neighbours out of order by less than the tolerance (interleaved HDL-64E lasers): left in storage order
    elev = np.radians(np.linspace(15.0, -15.0, 16))
    elev[6] = elev[5] + np.radians(0.05)  # ring 6 0.05 deg above ring 5
    r = np.repeat(np.arange(16), 50)
    az16 = np.tile(np.linspace(-np.pi, np.pi, 50, endpoint=False), 16)
    pts16 = 10.0 * np.column_stack([np.cos(elev[r]) * np.cos(az16), np.cos(elev[r]) * np.sin(az16), np.sin(elev[r])])
    assert FieldConventions.probe(DecodedCloud(pts16, None, None, None, r, 0), 0.1, "src").ring_table is None


def test_a_first_frame_with_constant_times_does_not_hide_the_sequences_times() -> None:
    """A first message whose time field is all zeros, then real sweeps: the sequence has per-point times
    (raw sweeps, deskewed with them), not 'motion-compensated' because of its first frame."""
    ns = np.linspace(0.0, 99_000_000.0, 800)
    zero = _cloud(16, lowest_first=False, times=np.zeros(800))
    later = [(_cloud(16, lowest_first=False, times=ns), f"{k}.pcd") for k in range(1, 5)]
    conv = FieldConventions.probe(zero, 0.1, "0.pcd", more=later)
    assert conv.has_time and conv.motion_compensated is False and conv.time_unit_s == 1e-9
    np.testing.assert_allclose(conv.frame(later[0][0], 1, 0.1, "1.pcd").time, ns * 1e-9 / 0.1)
    # every probe constant: no times (as before), logged
    assert not FieldConventions.probe(zero, 0.1, "0.pcd", more=[(zero, "1.pcd")]).has_time


def test_times_become_sweep_fractions() -> None:
    ns = np.linspace(0.0, 99_000_000.0, 800)  # Ouster: uint32 nanoseconds from the sweep start
    cloud = _cloud(16, lowest_first=False, times=ns)
    conv = FieldConventions.probe(cloud, 0.1, "src")
    assert conv.has_time and conv.time_unit_s == 1e-9
    np.testing.assert_allclose(conv.frame(cloud, 0, 0.0, "src").time, ns * 1e-9 / 0.1)
    no_time = _cloud(16, lowest_first=False)
    with pytest.raises(DatasetError, match="b.pcd: no per-point time field"):
        conv.frame(no_time, 1, 0.1, "b.pcd")


def test_points_without_a_return_at_the_origin_are_dropped_before_rings_are_probed(
        caplog: pytest.LogCaptureFixture) -> None:
    """An organized cloud (Ouster-style) marks a beam without a return as x = y = z = 0: kept, such
    points pulled the sky rings' median elevation to 0 and the rings (in order) were renumbered."""
    import logging

    from gr_graph.datasets.pointcloud2 import decode_structured

    ordered = _cloud(16, lowest_first=False)
    rng = np.random.default_rng(0)
    pts = ordered.points.copy()
    no_return = (ordered.ring < 5) & (rng.random(len(pts)) < 0.7)  # the upper beams see the sky
    pts[no_return] = 0.0
    arr = np.zeros(len(pts), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("ring", "u2")])
    arr["x"], arr["y"], arr["z"], arr["ring"] = pts[:, 0], pts[:, 1], pts[:, 2], ordered.ring
    cloud = decode_structured(arr.reshape(16, -1), "organized.pcd")
    assert cloud.dropped_nonfinite == int(no_return.sum()) and len(cloud.points) == len(pts) - no_return.sum()
    assert np.all(np.any(cloud.points != 0, axis=1))
    with caplog.at_level(logging.WARNING):
        conv = FieldConventions.probe(cloud, 0.1, "organized.pcd")
    assert conv.ring_table is None and "not in elevation order" not in caplog.text
    kept = DecodedCloud(np.where(no_return[:, None], 0.0, pts), None, None, None, ordered.ring, 0)
    assert FieldConventions.probe(kept, 0.1, "src").ring_table is not None  # what the zeros did before


@pytest.mark.parametrize("time_name, ring_name", [("t", "ring"), ("scalar_t", "scalar_ring"), ("Time", "Ring"),
                                                  ("TIMESTAMP", "RING"), ("offset_time", "ring")])
def test_time_and_ring_fields_are_found_whatever_their_case_or_exporter_prefix(time_name: str, ring_name: str) -> None:
    """As the intensity field already was: CloudCompare's scalar_ prefix, other cases, Livox
    converters' offset_time (before, such a time field was not read and raw sweeps counted as
    motion-compensated)."""
    from gr_graph.datasets.pointcloud2 import decode_structured, field_named

    arr = np.zeros(5, [("x", "f4"), ("y", "f4"), ("z", "f4"), ("scalar_Intensity", "f4"), (time_name, "f8"),
                       (ring_name, "u2")])
    arr["x"] = 1.0 + np.arange(5)
    arr[time_name] = np.linspace(0.0, 0.1, 5)
    arr[ring_name] = [3, 2, 1, 0, 4]
    arr["scalar_Intensity"] = 7.0
    cloud = decode_structured(arr, "a.pcd")
    assert cloud.time_field == time_name
    np.testing.assert_array_equal(cloud.time, arr[time_name])
    np.testing.assert_array_equal(cloud.ring, [3, 2, 1, 0, 4])
    np.testing.assert_array_equal(cloud.intensity, 7.0)
    # an exact name wins over a loose one, and a preferred name over a later one
    assert field_named(("Time", "t"), ("t", "time")) == "t"
    assert field_named(("scalar_time", "T"), ("t", "time")) == "T"
    assert field_named(("tag", "line"), ("t", "time")) is None


def test_a_folder_of_files_without_a_time_field_says_what_it_assumes(tmp_path, caplog: pytest.LogCaptureFixture
                                                                     ) -> None:
    """A PCD / PLY / NPY folder whose scans hold no per-point time is taken as motion-compensated, logged
    with the option that deskews raw sweeps (as a bag's topic is); .bin scans, which cannot hold one, are not
    warned about."""
    import logging

    from gr_graph.datasets.folder import FolderSequence

    rng = np.random.default_rng(0)
    for name, write in (("npy", lambda p, a: np.save(p.with_suffix(".npy"), a)),
                        ("bin", lambda p, a: np.c_[a, np.zeros(len(a))].astype(np.float32).tofile(p.with_suffix(".bin")))):
        folder = tmp_path / name
        folder.mkdir()
        for k in range(3):
            write(folder / f"{k}", rng.uniform(-20, 20, (500, 3)))
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            assert FolderSequence(folder).motion_compensated is True
        assert ("no per-point time field" in caplog.text) == (name == "npy"), name
        assert ("odometry.deskew: on" in caplog.text) == (name == "npy"), name
