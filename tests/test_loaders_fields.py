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


def test_times_become_sweep_fractions() -> None:
    ns = np.linspace(0.0, 99_000_000.0, 800)  # Ouster: uint32 nanoseconds from the sweep start
    cloud = _cloud(16, lowest_first=False, times=ns)
    conv = FieldConventions.probe(cloud, 0.1, "src")
    assert conv.has_time and conv.time_unit_s == 1e-9
    np.testing.assert_allclose(conv.frame(cloud, 0, 0.0, "src").time, ns * 1e-9 / 0.1)
    no_time = _cloud(16, lowest_first=False)
    with pytest.raises(DatasetError, match="b.pcd: no per-point time field"):
        conv.frame(no_time, 1, 0.1, "b.pcd")
