"""Constant-velocity deskewing against independent per-point SE(3) products."""

from __future__ import annotations

import numpy as np
import pytest

from factors.se3 import exp_se3, inverse_se3
from gr_graph.deskew import deskew, distort, normalise_times, sweep_motion_from_velocity, times_from_azimuth


def _scene(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([-40, -40, -2], [40, 40, 5], size=(n, 3))


@pytest.mark.parametrize("xi", [np.array([0.0, 0.0, 0.05, 1.2, 0.05, 0.0]),     # driving, turning
                                np.array([0.01, -0.02, 0.3, 0.5, -0.2, 0.1]),    # fast turn
                                np.array([0.0, 0.0, 1e-9, 0.0, 0.0, 1e-9])])    # nearly still
def test_deskew_undoes_a_constant_velocity_sweep(xi: np.ndarray) -> None:
    """Points measured from the pose Exp(t xi) at their own time come back in the mid-sweep frame."""
    world = _scene(2000, 0)  # world = sensor frame at the sweep's start
    t = np.random.default_rng(1).uniform(0, 1, len(world))
    measured = np.empty_like(world)
    for i in range(len(world)):  # independent reference: one 4x4 product per point
        T_inv = inverse_se3(exp_se3(t[i] * xi))
        measured[i] = T_inv[:3, :3] @ world[i] + T_inv[:3, 3]
    mid = inverse_se3(exp_se3(0.5 * xi))
    expected = world @ mid[:3, :3].T + mid[:3, 3]
    out = deskew(measured, t, exp_se3(xi))
    np.testing.assert_allclose(out, expected, atol=1e-9)
    # to the start of the sweep instead: the world points themselves
    np.testing.assert_allclose(deskew(measured, t, exp_se3(xi), reference_time=0.0), world, atol=1e-9)


def test_no_motion_and_empty_input() -> None:
    p = _scene(10, 2)
    np.testing.assert_array_equal(deskew(p, np.linspace(0, 1, 10), np.eye(4)), p)
    assert deskew(np.zeros((0, 3)), np.zeros(0), exp_se3(np.ones(6) * 0.1)).shape == (0, 3)
    with pytest.raises(ValueError, match="times"):
        deskew(p, np.zeros(3), np.eye(4))


def test_times_from_azimuth_clockwise_sweep() -> None:
    # behind-left (az just below +180 deg) starts, ahead is mid-sweep, behind-right ends
    pts = np.array([[-1.0, 1e-6, 0], [0, 1, 0], [1, 0, 0], [0, -1, 0], [-1, -1e-6, 0]])
    np.testing.assert_allclose(times_from_azimuth(pts), [0.0, 0.25, 0.5, 0.75, 1.0], atol=1e-6)
    np.testing.assert_allclose(times_from_azimuth(pts, clockwise=False), [1.0, 0.75, 0.5, 0.25, 0.0], atol=1e-6)


def test_times_from_azimuth_follow_the_sensors_spin_and_start() -> None:
    """sensor.rotation and sensor.sweep_start_azimuth_deg: a counter-clockwise sensor, or one whose sweep
    starts straight ahead, gets its own times; the default (clockwise from behind) is the formula of before."""
    deg = np.array([0.0, -90.0, 90.0, 179.0, -179.0, 45.0])
    pts = np.column_stack([np.cos(np.radians(deg)), np.sin(np.radians(deg)), np.zeros(len(deg))])
    np.testing.assert_allclose(times_from_azimuth(pts, True, 0.0), [0.0, 0.25, 0.75, 181 / 360, 179 / 360, 315 / 360],
                               atol=1e-12)
    np.testing.assert_allclose(times_from_azimuth(pts, False, 0.0), [0.0, 0.75, 0.25, 179 / 360, 181 / 360, 45 / 360],
                               atol=1e-12)
    np.testing.assert_allclose(times_from_azimuth(pts, False, 90.0)[[2, 0, 1]], [0.0, 0.75, 0.5], atol=1e-12)
    az = np.arctan2(pts[:, 1], pts[:, 0])
    np.testing.assert_array_equal(times_from_azimuth(pts), np.clip(0.5 * (1.0 - az / np.pi), 0, 1))
    np.testing.assert_allclose(times_from_azimuth(pts, True, -180.0), times_from_azimuth(pts), atol=1e-12)
    # deskewing a counter-clockwise sweep with its own times undoes it; with the clockwise default it does not
    rng = np.random.default_rng(2)
    world = rng.uniform(-20, 20, (2000, 3))
    motion = exp_se3(np.array([0.0, 0.0, 0.05, 1.0, 0.1, 0.0]))
    ccw = times_from_azimuth(world, False, 0.0)
    measured = distort(world, ccw, motion)
    again = times_from_azimuth(measured, False, 0.0)
    err_own = np.linalg.norm(deskew(measured, again, motion) - world, axis=1)
    err_default = np.linalg.norm(deskew(measured, times_from_azimuth(measured), motion) - world, axis=1)
    assert np.median(err_own) < 0.2 * np.median(err_default)


def test_normalise_times_units_and_errors() -> None:
    ns = np.array([1_000_000_000, 1_050_000_000, 1_100_000_000], np.float64)
    np.testing.assert_allclose(normalise_times(ns), [0, 0.5, 1])
    np.testing.assert_allclose(normalise_times(ns, scan_period=2e8), [0, 0.25, 0.5])
    np.testing.assert_allclose(normalise_times(np.zeros(3)), [0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match="non-finite"):
        normalise_times(np.array([0.0, np.nan]))


def test_sweep_motion_scales_the_frame_motion() -> None:
    xi = np.array([0.0, 0.0, 0.1, 1.0, 0.0, 0.0])
    np.testing.assert_allclose(sweep_motion_from_velocity(exp_se3(xi), 0.1, 0.05), exp_se3(0.5 * xi), atol=1e-12)


@pytest.mark.parametrize("xi", [np.array([0.3, -0.2, 1.5, 4.0, -1.0, 0.5]),   # > 0.05 rad per half sweep
                                np.array([0.0, 0.0, 0.08, 1.3, 0.0, 0.0])])   # Taylor branch
def test_closed_form_matches_per_point_matrices_and_distort_inverts(xi: np.ndarray) -> None:
    """Both coefficient branches against one exp_se3 product per point; distort is the inverse."""
    p = _scene(500, 3)
    t = np.random.default_rng(4).uniform(0, 1, len(p))
    expected = np.array([exp_se3((ti - 0.5) * xi)[:3, :3] @ pi + exp_se3((ti - 0.5) * xi)[:3, 3]
                         for pi, ti in zip(p, t)])
    np.testing.assert_allclose(deskew(p, t, exp_se3(xi)), expected, atol=1e-9)
    np.testing.assert_allclose(deskew(distort(p, t, exp_se3(xi)), t, exp_se3(xi)), p, atol=1e-9)
    assert np.abs(distort(p, t, exp_se3(xi)) - p).max() > 0.1


def test_the_frame_deskewer_takes_the_sensors_spin_for_frames_without_times() -> None:
    from gr_graph.config import load_config
    from gr_graph.datasets.base import LidarFrame
    from gr_graph.frame_loop import FrameDeskewer

    cfg = load_config(None, {"sensor": {"rotation": "counterclockwise", "sweep_start_azimuth_deg": 0.0}})
    rng = np.random.default_rng(4)
    pts = rng.uniform(-20, 20, (500, 3))
    frame = LidarFrame(0, 0.0, pts, np.zeros(500, np.float32))
    step = exp_se3(np.array([0.0, 0.0, 0.02, 0.8, 0.0, 0.0]))
    sensor = cfg.sensor
    out = FrameDeskewer(None, sensor.rotation == "clockwise", sensor.sweep_start_azimuth_deg)(frame, step, 0.1)
    np.testing.assert_allclose(out.points, deskew(pts, times_from_azimuth(pts, False, 0.0), step))
    assert not np.allclose(out.points, FrameDeskewer(None)(frame, step, 0.1).points)


def test_the_deskewing_sweep_duration_follows_what_was_said() -> None:
    """odometry.deskew_scan_period, else sensor.scan_period (also for loaders without a sweep duration, e.g.
    KITTI-layout folders), else the sequence's, else None (one frame spacing)."""
    from types import SimpleNamespace

    from gr_graph.config import load_config
    from gr_graph.frame_loop import deskew_scan_period

    kitti_like, timed = SimpleNamespace(), SimpleNamespace(scan_period=0.1)
    assert deskew_scan_period(load_config(None, {}), kitti_like) is None
    assert deskew_scan_period(load_config(None, {}), timed) == 0.1
    said = load_config(None, {"sensor": {"scan_period": 0.05}})
    assert deskew_scan_period(said, kitti_like) == 0.05 and deskew_scan_period(said, timed) == 0.05
    both = load_config(None, {"sensor": {"scan_period": 0.05}, "odometry": {"deskew_scan_period": 0.08}})
    assert deskew_scan_period(both, timed) == 0.08


def test_the_tail_of_a_sweep_end_sweep_stays_at_the_end() -> None:
    """Times of a sweep's last 4 ms counted back from its end ([-0.004, 0] s) also fit the sweep start's
    slack; they are the end of the sweep (fractions 0.96-1), not its start."""
    from gr_graph.deskew import resolve_time_reference

    tail = np.linspace(-0.004, 0.0, 50)
    assert resolve_time_reference(tail, 0.1) == "sweep_end"
    np.testing.assert_allclose(normalise_times(tail, 0.1), 1.0 + tail / 0.1)
    # as before: start-relative times with a little jitter below 0, a whole sweep back from its end, stamps
    assert resolve_time_reference(np.array([-0.001, 0.05, 0.099]), 0.1) == "sweep_start"
    assert resolve_time_reference(np.linspace(-0.1, 0.0, 20), 0.1) == "sweep_end"
    assert resolve_time_reference(np.zeros(5), 0.1) == "sweep_start"
    assert resolve_time_reference(1.7e9 + np.linspace(0, 0.1, 20), 0.1) == "absolute"
