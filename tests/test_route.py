"""The project's generated route (gr_graph.datasets.synthetic.route): KITTI 00's character.

Every property is measured here from the poses and timestamps alone (finite differences,
nearest neighbours, heading changes), independently of what the generator reports; what it
reports (revisits, stops, turns) is then checked against those measurements.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gr_graph.datasets.synthetic import rig
from gr_graph.datasets.synthetic.route import RouteConfig, generate_route


@pytest.fixture(scope="module")
def route():
    return generate_route(0)


def _yaw(T: np.ndarray) -> np.ndarray:
    return np.unwrap(np.arctan2(T[:, 1, 0], T[:, 0, 0]))


def _speed(route) -> np.ndarray:
    """Speed on each frame interval: secant |Δp| / Δt with the real timestamps."""
    P = route.T_w_velo[:, :3, 3]
    return np.linalg.norm(np.diff(P, axis=0), axis=1) / np.diff(route.times)


def test_frames_timestamps_and_poses(route):
    T, t = route.T_w_velo, route.times
    assert T.shape == (4541, 4, 4) and t.shape == (4541,)
    np.testing.assert_array_equal(T[0], np.eye(4))  # world = LiDAR frame of frame 0
    np.testing.assert_array_equal(T[:, 3], np.tile([0, 0, 0, 1.0], (4541, 1)))
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.tile(np.eye(3), (4541, 1, 1)), atol=1e-12)
    assert np.all(np.linalg.det(R) > 0)
    assert t[0] == 0.0
    dt = np.diff(t)
    assert np.all(np.abs(dt - 0.1) <= 0.0011)  # 10 Hz with a sub-millisecond jitter
    assert np.all(np.abs(t - 0.1 * np.arange(4541)) <= 0.0005 + 1e-12)


def test_length_and_speeds(route):
    v = _speed(route)
    length = float(np.sum(v * np.diff(route.times)))
    assert 3650.0 < length < 3750.0
    assert length == pytest.approx(route.length_m, rel=1e-3)
    assert v.max() <= 13.0 + 1e-6 and v.max() > 12.0
    assert v.min() < 0.01  # it stops
    # smooth acceleration and braking: |dv/dt| within what a car does in town
    a = np.diff(v) / (0.5 * (route.times[2:] - route.times[:-2]))
    assert np.abs(a).max() < 2.0
    assert np.mean(v) == pytest.approx(3700.0 / 454.0, rel=0.02)


def test_yaw_rates_and_attitude_are_plausible(route):
    T = route.T_w_velo
    yaw_rate = np.abs(np.diff(_yaw(T))) / np.diff(route.times)
    assert np.degrees(yaw_rate.max()) < 35.0
    v = _speed(route)
    assert (v * yaw_rate).max() < 2.5  # lateral acceleration (m/s²)
    # roll and pitch: grade, cross slope and body motion, a few degrees at most
    tilt = np.degrees(np.arccos(np.clip(T[:, 2, 2], -1, 1)))
    assert tilt.max() < 4.0 and tilt.max() > 0.2
    # gentle height changes: metres over the route, grades below 6 %
    z = T[:, 2, 3]
    assert 1.0 < np.ptp(z) < 12.0
    step = np.linalg.norm(np.diff(T[:, :2, 3], axis=0), axis=1)
    moving = step > 0.3
    assert (np.abs(np.diff(z))[moving] / step[moving]).max() < 0.06


def test_stops(route):
    v = _speed(route)
    still = np.r_[False, v < 0.001, False]  # standing still (< 0.1 mm a frame)
    edges = np.flatnonzero(np.diff(still.astype(int)))
    durations = [route.times[b] - route.times[a] for a, b in zip(edges[::2], edges[1::2])]
    long_stops = [d for d in durations if d >= 10.0]
    assert len(long_stops) >= 2
    assert len(route.stops) == len(long_stops)
    for s, d in zip(route.stops, long_stops):
        a, b = s.frames
        assert s.duration_s == pytest.approx(d, abs=0.21)
        np.testing.assert_allclose(route.T_w_velo[a:b, :3, 3], np.broadcast_to(route.T_w_velo[a, :3, 3], (b - a, 3)), atol=1e-9)


def test_revisits_same_and_opposite_direction(route):
    P = route.T_w_velo[:, :2, 3]
    yaw = _yaw(route.T_w_velo)
    travelled = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
    assert len(route.revisits) >= 4
    assert {r.direction for r in route.revisits} == {"same", "opposite"}
    assert route.revisits[0].frames[0] >= 1000  # drift builds up before the first revisit
    tree = cKDTree(P)
    for r in route.revisits:
        a, b = r.frames
        e0, e1 = r.earlier
        assert e1 <= a and travelled[b - 1] - travelled[a] >= 40.0
        gap = []
        for i, nb in enumerate(tree.query_ball_point(P[a:b], 6.0)):
            jj = np.asarray(nb, dtype=int)
            dd = np.linalg.norm(P[jj] - P[a + i], axis=1)
            c = np.cos(yaw[a + i] - yaw[jj])
            ok = (jj >= e0) & (jj < e1) & ((c > 0.9) if r.direction == "same" else (c < -0.9))
            assert ok.any(), (r, a + i)
            jn = jj[ok][np.argmin(dd[ok])]
            left = np.array([-np.sin(yaw[a + i]), np.cos(yaw[a + i])])
            gap.append(abs((P[jn] - P[a + i]) @ left))  # lateral offset between the passes
        if r.direction == "same":
            assert np.median(gap) < 0.2  # the same lane
        else:
            assert 3.2 < np.median(gap) < 3.8  # the other lane, 2 x 1.75 m away


def test_turns_are_90_degrees_on_a_street_grid(route):
    yaw = _yaw(route.T_w_velo)
    assert len(route.turns) >= 10
    for turn in route.turns:
        k = turn.frame
        lo, hi = max(0, k - 60), min(len(yaw) - 1, k + 60)
        change = np.degrees(yaw[hi] - yaw[lo])
        assert abs(abs(change) - 90.0) < 3.0, turn
        assert turn.angle_deg == pytest.approx(change, abs=3.0)
    # between turns the streets run along two perpendicular axes: headings on moving,
    # straight frames are multiples of 90° off the first street (within the lane smoothing)
    v = _speed(route)
    rate = np.abs(np.gradient(yaw))
    straight = (np.r_[v, v[-1]] > 3.0) & (rate < 1e-4)
    off = np.degrees(yaw[straight] - yaw[0]) % 90.0
    assert np.all(np.minimum(off, 90.0 - off) < 0.5)


def test_rig_calibration_is_the_projects_own():
    T = rig.T_cam_velo()
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    axis = R.T @ [0.0, 0.0, 1.0]  # the camera's optical axis in the LiDAR frame
    assert axis[0] > 0.999 and -0.02 < axis[2] < 0  # forward, slightly down
    cam_in_velo = -R.T @ T[:3, 3]
    assert cam_in_velo[2] == pytest.approx(-0.33, abs=0.01)  # LiDAR 33 cm above the camera
    assert cam_in_velo[0] == pytest.approx(0.22, abs=0.01)  # camera 22 cm ahead of it
    P0 = rig.P0()
    assert P0[0, 0] == P0[1, 1] == 700.0 and P0[:, 3].tolist() == [0, 0, 0]


@pytest.mark.slow
def test_deterministic_per_seed_and_different_for_another_seed(route):
    again = generate_route.__wrapped__(0)  # bypass the cache: build it anew
    np.testing.assert_array_equal(again.T_w_velo, route.T_w_velo)
    np.testing.assert_array_equal(again.times, route.times)
    assert again.revisits == route.revisits and again.stops == route.stops
    other = generate_route.__wrapped__(1)
    assert other.T_w_velo.shape == route.T_w_velo.shape
    d = np.linalg.norm(other.T_w_velo[:, :3, 3] - route.T_w_velo[:, :3, 3], axis=1)
    assert np.median(d) > 50.0
    assert len(other.revisits) >= 4 and len(other.stops) >= 2
    assert 3650.0 < other.length_m < 3750.0


def test_bad_seed_and_impossible_config():
    with pytest.raises(ValueError, match="route seed"):
        generate_route(-1)
    from gr_graph.datasets.synthetic.route import RouteGenerationError

    with pytest.raises(RouteGenerationError, match="route seed 0"):
        generate_route(0, RouteConfig(min_revisits=40, max_attempts=3))
