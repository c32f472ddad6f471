"""Ring recovery and 64 -> 32 -> 16 channel subsampling on the real KITTI 00 frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError, LidarFrame
from gr_graph.datasets.channels import RingRecoveryError, elevation_deg, recover_rings, subsample_channels
from gr_graph.datasets.kitti import KittiSequence


@pytest.fixture(scope="module")
def frames(kitti_root: Path) -> list[LidarFrame]:
    seq = KittiSequence(kitti_root, "00")
    return [seq[i] for i in range(len(seq))]


def _naive_wrap_breaks(points: np.ndarray) -> int:
    az = np.arctan2(points[:, 1], points[:, 0])
    return int(np.sum(np.abs(np.diff(az)) > np.pi))


def test_naive_wrap_detection_overcounts(frames: list[LidarFrame]) -> None:
    # The reason recovery needs more than wrap detection (../shared/data/README.md).
    assert _naive_wrap_breaks(frames[0].points) > 64


@pytest.mark.parametrize("k", range(6))
def test_64_rings_ordered_by_elevation(frames: list[LidarFrame], k: int) -> None:
    frame = frames[k]
    ring = frame.ring
    assert ring is not None and ring.dtype == np.int16
    assert set(np.unique(ring)) == set(range(64))
    # Rings are contiguous runs in storage order (one scan line each).
    assert np.count_nonzero(np.diff(ring)) == 63
    elev = elevation_deg(frame.points)
    med = np.array([np.median(elev[ring == r]) for r in range(64)])
    assert np.all(np.diff(med) < 0), "ring 0 must be the highest beam, then strictly descending"
    # HDL-64E: about +2 deg down to about -24.9 deg.
    assert 1.5 < med[0] < 3.0 and -25.5 < med[-1] < -23.0
    # Each line sweeps at most one turn of azimuth.
    for r in range(64):
        az = np.unwrap(np.arctan2(frame.points[ring == r, 1], frame.points[ring == r, 0]))
        assert np.ptp(az) < 2 * np.pi + 1e-9


def test_line_boundaries_where_elevation_steps(frames: list[LidarFrame]) -> None:
    # Independent check of every boundary: a few points before it look higher than a few after.
    frame = frames[0]
    elev = elevation_deg(frame.points)
    starts = np.flatnonzero(np.diff(frame.ring)) + 1
    for s in starts:
        assert np.median(elev[s - 5 : s]) > np.median(elev[s : s + 5]), f"boundary at {s}"


@pytest.mark.parametrize("channels, stride", [(32, 2), (16, 4)])
def test_subsampling_keeps_whole_rings(frames: list[LidarFrame], channels: int, stride: int) -> None:
    for frame in frames:
        sub = subsample_channels(frame, channels)
        assert sub.n_rings == channels
        assert set(np.unique(sub.ring)) == set(range(channels))
        counts = np.bincount(frame.ring, minlength=64)
        kept_original = np.arange(0, 64, stride)
        # Every kept ring is whole: its point count equals the original ring's.
        np.testing.assert_array_equal(np.bincount(sub.ring, minlength=channels), counts[kept_original])
        frac = len(sub) / len(frame)
        assert abs(frac - 1 / stride) < 0.05, f"kept {frac:.3f} of the points"
        # The kept points are exactly those of the kept rings, in order.
        mask = np.isin(frame.ring, kept_original)
        np.testing.assert_array_equal(sub.points, frame.points[mask])


def test_subsampling_64_is_identity(frames: list[LidarFrame]) -> None:
    assert subsample_channels(frames[0], 64) is frames[0]


def test_subsampling_needs_rings(frames: list[LidarFrame]) -> None:
    f = frames[0]
    no_ring = LidarFrame(f.index, f.timestamp, f.points, f.intensity, ring=None)
    with pytest.raises(DatasetError, match="no ring"):
        subsample_channels(no_ring, 16)
    with pytest.raises(DatasetError, match="24 channels"):
        subsample_channels(f, 24)


def test_shuffled_points_are_refused(frames: list[LidarFrame]) -> None:
    pts = frames[0].points[np.random.default_rng(0).permutation(len(frames[0]))]
    with pytest.raises(RingRecoveryError, match="sensor order"):
        recover_rings(pts)


def test_cropped_scan_is_refused(frames: list[LidarFrame]) -> None:
    f = frames[0]
    with pytest.raises(RingRecoveryError):
        recover_rings(f.points[f.ring < 40])


def test_top_beam_without_returns_ahead(frames: list[LidarFrame]) -> None:
    # Sky straight ahead: the scan's first point lies well past azimuth 0. Every other
    # line must still start at azimuth 0 and keep all of its points.
    f = frames[0]
    az = np.degrees(np.arctan2(f.points[:, 1], f.points[:, 0]))
    keep = ~((f.ring == 0) & (az >= 0) & (az < 30))
    assert keep.sum() < len(f) - 50
    np.testing.assert_array_equal(recover_rings(f.points[keep]), f.ring[keep])


def test_first_point_just_short_of_zero(frames: list[LidarFrame]) -> None:
    # Azimuth jitter can put a line's first point a hair below 0 deg; it stays in line 0.
    f = frames[0]
    pts = f.points.copy()
    r = np.hypot(pts[0, 0], pts[0, 1])
    pts[0, :2] = r * np.cos(np.radians(-0.01)), r * np.sin(np.radians(-0.01))
    np.testing.assert_array_equal(recover_rings(pts), f.ring)
