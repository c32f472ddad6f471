"""Deskewing in the frame loop, per-point times on frames, and the motion-distorted sequence.

References are independent of gr_graph.deskew: distorted points are built with one
``factors.se3.exp_se3`` product per point, along constant-velocity trajectories where the
undistorted points are known exactly.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from factors.se3 import exp_se3, inverse_se3
from gr_graph.config import load_config
from gr_graph.datasets.base import DatasetError, LidarFrame
from gr_graph.datasets.channels import subsample_channels
from gr_graph.datasets.distortion import MotionDistortedSequence
from gr_graph.datasets.registry import SequenceView
from gr_graph.deskew import times_from_azimuth
from gr_graph.frame_loop import _FrameLoop, deskew_enabled

XI_FRAME = np.array([0.004, -0.002, 0.06, 1.3, 0.04, 0.01])  # per frame: 13 m/s, 34 deg/s yaw at 10 Hz
DT = 0.1


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def _frame(index: int, points: np.ndarray, time: np.ndarray | None = None, ring: np.ndarray | None = None
           ) -> LidarFrame:
    return LidarFrame(index=index, timestamp=index * DT, points=points,
                      intensity=np.zeros(len(points), np.float32), ring=ring, time=time)


class ListSequence:
    """Frames held in a list, with constant-velocity ground truth (mid-sweep poses)."""

    def __init__(self, frames: list[LidarFrame], poses: np.ndarray, motion_compensated: bool = True,
                 scan_period: float | None = None) -> None:
        self.frames = frames
        self.name = "list"
        self.timestamps = np.array([f.timestamp for f in frames])
        self.gt_poses = poses
        self.T_cam_velo = np.eye(4)
        self.motion_compensated = motion_compensated
        if scan_period is not None:
            self.scan_period = scan_period

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> LidarFrame:
        return self.frames[i]

    def __iter__(self) -> Iterator[LidarFrame]:
        return iter(self.frames)


def _constant_velocity_poses(n: int) -> np.ndarray:
    return np.stack([exp_se3(k * XI_FRAME) for k in range(n)])


def _measured_by_reference(undistorted: np.ndarray, t: np.ndarray, sweep_xi: np.ndarray) -> np.ndarray:
    """What a sensor moving by Exp(s sweep_xi) over the sweep measures (one product per point)."""
    out = np.empty_like(undistorted)
    for i, (p, ti) in enumerate(zip(undistorted, t)):
        T = inverse_se3(exp_se3((ti - 0.5) * sweep_xi))  # sensor at ti in the mid-sweep frame, inverted
        out[i] = T[:3, :3] @ p + T[:3, 3]
    return out


def _loop(seq, mode: str = "on", scan_period: float | None = None) -> _FrameLoop:
    cfg = load_config(overrides={"odometry": {"deskew": mode, "deskew_scan_period": scan_period},
                                 "loops": {"enabled": False}, "graph": {"marginals": False},
                                 "output": {"progress": False}})
    return _FrameLoop(seq, cfg, None)


# ------------------------------------------------------------------------------------ frames


def test_frame_time_is_checked_and_carried() -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform(-10, 10, (64, 3))
    t = rng.uniform(0, 1, 64)
    f = _frame(0, p, t, ring=(np.arange(64) % 4).astype(np.int16))
    sub = f.select(np.arange(64) % 2 == 0)
    np.testing.assert_array_equal(sub.time, t[::2])
    f.__class__.__post_init__(f)
    ch = subsample_channels(LidarFrame(0, 0.0, p, np.zeros(64, np.float32), f.ring, n_rings=4, time=t), 2)
    np.testing.assert_array_equal(ch.time, t[f.ring % 2 == 0])
    with pytest.raises(DatasetError, match="time shape"):
        _frame(0, p, t[:10])
    with pytest.raises(DatasetError, match=r"\[0, 1\]"):
        _frame(0, p, t * 2.0)
    with pytest.raises(DatasetError, match=r"\[0, 1\]"):
        _frame(0, p, np.where(t > 0.5, np.nan, t))


def test_auto_follows_motion_compensated() -> None:
    comp = ListSequence([], np.zeros((0, 4, 4)), motion_compensated=True)
    raw = ListSequence([], np.zeros((0, 4, 4)), motion_compensated=False)
    assert deskew_enabled("auto", comp)[0] is False
    assert deskew_enabled("auto", raw)[0] is True
    assert deskew_enabled("on", comp)[0] is True
    assert deskew_enabled("off", raw)[0] is False

    class Bare:  # no attribute: counted as compensated (results unchanged)
        pass

    assert deskew_enabled("auto", Bare())[0] is False


# ------------------------------------------------------------------------------------ the frame loop


@pytest.mark.parametrize("time_source", ["data", "azimuth"])
@pytest.mark.parametrize("scan_period", [None, 0.05])
def test_frame_loop_deskews_to_the_undistorted_points(time_source: str, scan_period: float | None) -> None:
    """With the odometry's increment equal to the true one, deskewed == undistorted to 1e-9."""
    rng = np.random.default_rng(1)
    n = 3000
    sweep_xi = XI_FRAME * ((scan_period or DT) / DT)
    # the measured points are drawn first, so that their azimuth gives the true times
    measured = rng.uniform([-40, -40, -2], [40, 40, 5], (n, 3))
    t = times_from_azimuth(measured) if time_source == "azimuth" else rng.uniform(0, 1, n)
    undistorted = np.array([_apply(exp_se3((ti - 0.5) * sweep_xi), p[None])[0] for p, ti in zip(measured, t)])
    # the reference distortion reproduces the measured points (independent construction, round trip)
    np.testing.assert_allclose(_measured_by_reference(undistorted, t, sweep_xi), measured, atol=1e-9)
    frames = [_frame(k, measured, t if time_source == "data" else None) for k in range(3)]
    seq = ListSequence(frames, _constant_velocity_poses(3), motion_compensated=False)
    loop = _loop(seq, "auto", scan_period)
    assert loop.deskew_on
    loop.odometry._delta = exp_se3(XI_FRAME)  # the velocity is known
    out = loop.deskew(2, frames[2])
    np.testing.assert_allclose(out.points, undistorted, atol=1e-9)
    assert np.abs(out.points - measured).max() > 0.3  # there was something to undo
    assert loop.deskewer.time_sources[time_source] == 1


@pytest.mark.parametrize("time_source", ["data", "azimuth"])
def test_learned_noise_predictions_are_moved_as_their_frames_were(time_source: str) -> None:
    """H(C) pairs the network's points (taken from the scan as read) under T̂ between deskewed frames:
    the frame loop moves them, and turns their covariances, as it moved the frame."""
    from gr_graph.edge_noise import LearnedEdgeNoise

    rng = np.random.default_rng(2)
    n = 500
    measured = rng.uniform([-40, -40, -2], [40, 40, 5], (n, 3))
    t = times_from_azimuth(measured) if time_source == "azimuth" else rng.uniform(0, 1, n)
    undistorted = np.array([_apply(exp_se3((ti - 0.5) * XI_FRAME), p[None])[0] for p, ti in zip(measured, t)])
    A = rng.normal(0, 0.1, (n, 3, 3))
    C = A @ A.transpose(0, 2, 1) + 1e-3 * np.eye(3)
    frames = [_frame(k, measured, t if time_source == "data" else None) for k in range(3)]

    class WithPredictions(ListSequence):  # the densified view's per-point times of its predictions
        def prediction_times(self, index: int) -> np.ndarray | None:
            return t if time_source == "data" else None

    seq = WithPredictions(frames, _constant_velocity_poses(3), motion_compensated=False)
    cfg = load_config(overrides={"odometry": {"deskew": "auto"}, "loops": {"enabled": False},
                                 "graph": {"marginals": False}, "output": {"progress": False}})
    en = LearnedEdgeNoise({2: (measured, C), 1: (measured, C)}.get, cfg)
    loop = _FrameLoop(seq, cfg, en)
    assert en.motion_correction is not None
    loop.odometry._delta = exp_se3(XI_FRAME)
    loop.deskew(2, frames[2])
    points, moved_C = en._prediction(2)
    np.testing.assert_allclose(points, undistorted, atol=1e-9)
    R = np.stack([exp_se3(np.r_[(ti - 0.5) * XI_FRAME[:3], 0, 0, 0])[:3, :3] for ti in t])
    np.testing.assert_allclose(moved_C, R @ C @ R.transpose(0, 2, 1), atol=1e-12)
    assert np.abs(moved_C - C).max() > 1e-5  # the rotation turned them
    same_points, same_C = en._prediction(1)  # a frame that was not deskewed: as predicted
    assert same_points is measured and same_C is C
    off = load_config(overrides={"odometry": {"deskew": "off"}, "output": {"progress": False}})
    en_off = LearnedEdgeNoise({}.get, off)
    _FrameLoop(seq, off, en_off)
    assert en_off.motion_correction is None


def test_frame_loop_off_leaves_frames_and_records_the_summary() -> None:
    """deskew off: frames untouched; on: every frame counted, startup frames redone."""
    rng = np.random.default_rng(2)
    scene = rng.uniform([-30, -30, -2], [30, 30, 6], (20000, 3))
    scene[:, 2] = np.where(rng.random(len(scene)) < 0.5, -1.7, scene[:, 2])  # a ground plane
    poses = _constant_velocity_poses(6)
    frames = [_frame(k, _apply(inverse_se3(poses[k]), scene)) for k in range(6)]
    res_off = _loop(ListSequence(frames, poses), "auto").run("")
    assert res_off.info["deskew"]["enabled"] is False and res_off.info["deskew"]["frames_deskewed"] == 0
    res_on = _loop(ListSequence(frames, poses), "on").run("")
    d = res_on.info["deskew"]
    assert d["enabled"] and d["frames_deskewed"] == 6 and d["frames_without_motion"] == 0
    assert d["time_source"] == {"data": 0, "azimuth": 6}


# ------------------------------------------------------------------------------------ distorted sequence


def _undistorted_sequence(n_frames: int = 5) -> ListSequence:
    rng = np.random.default_rng(3)
    poses = _constant_velocity_poses(n_frames)
    scene = rng.uniform([-40, -40, -2], [60, 40, 6], (4000, 3))
    frames = [_frame(k, _apply(inverse_se3(poses[k]), scene)) for k in range(n_frames)]
    return ListSequence(frames, poses)


@pytest.mark.parametrize("k", [0, 2, 4])  # extrapolated at both ends
def test_distorted_sequence_on_a_constant_velocity_trajectory(k: int) -> None:
    base = _undistorted_sequence()
    raw = MotionDistortedSequence(base, scan_period=0.1)
    assert raw.motion_compensated is False
    f = raw[k]
    sweep_xi = XI_FRAME * (0.1 / DT)
    np.testing.assert_allclose(f.points, _measured_by_reference(base[k].points, f.time, sweep_xi), atol=1e-9)
    # the times are those of the measured azimuths (fixed point), away from the backward seam
    az = times_from_azimuth(f.points)
    inner = (f.time > 0.02) & (f.time < 0.98)
    assert np.abs(az - f.time)[inner].max() < 1e-4
    comp = MotionDistortedSequence(base, scan_period=0.1, compensation_velocity_noise=0.0)
    assert comp.motion_compensated is True and comp[k].time is None
    np.testing.assert_allclose(comp[k].points, base[k].points, atol=1e-9)
    noisy = MotionDistortedSequence(base, 0.1, compensation_velocity_noise=0.5, compensation_rate_noise_deg=1.0)
    resid = np.linalg.norm(noisy[k].points - base[k].points, axis=1)
    assert 1e-3 < resid.max() < 0.2
    np.testing.assert_array_equal(noisy[k].points, noisy[k].points)  # seeded per frame


def test_views_keep_motion_compensated_and_scan_period() -> None:
    raw = MotionDistortedSequence(_undistorted_sequence(), scan_period=0.08)
    view = SequenceView(raw, 1, 4)
    assert view.motion_compensated is False and view.scan_period == 0.08
    assert SequenceView(_undistorted_sequence(), 0, 2).motion_compensated is True


def test_distorted_sequence_needs_ground_truth() -> None:
    seq = _undistorted_sequence()
    seq.gt_poses = None
    with pytest.raises(DatasetError, match="ground-truth"):
        MotionDistortedSequence(seq)


# ------------------------------------------------------------------------------------ synthetic drive


class _Cached(ListSequence):
    def __init__(self, seq) -> None:
        super().__init__([seq[i] for i in range(len(seq))], np.asarray(seq.gt_poses),
                         bool(getattr(seq, "motion_compensated", True)), getattr(seq, "scan_period", None))
        self.timestamps = np.asarray(seq.timestamps)
        self.name = seq.name


@pytest.mark.slow
def test_deskewing_recovers_most_of_the_distortion_on_a_fast_synthetic_stretch() -> None:
    """50 synthetic frames at ~12.7 m/s: raw distortion hurts, deskewing recovers most of it."""
    from gr_graph.datasets.registry import open_sequence
    from gr_graph.frame_loop import run_slam
    from gr_graph.metrics import ate, rpe_translation

    seq, _ = open_sequence("00", frames=(4200, 4250), synthetic_preset="clean")
    clean = _Cached(seq)
    raw = _Cached(MotionDistortedSequence(clean, scan_period=0.1))
    assert raw.motion_compensated is False and all(f.time is not None for f in raw.frames)
    cfg = load_config(overrides={"loops": {"enabled": False}, "graph": {"marginals": False},
                                 "output": {"progress": False}})
    gt = np.linalg.inv(clean.gt_poses[0]) @ clean.gt_poses
    figures = {}
    for label, s, mode in (("clean", clean, "auto"), ("raw_off", raw, "off"), ("raw_auto", raw, "auto")):
        res = run_slam(s, cfg.model_copy(update={"odometry": cfg.odometry.model_copy(update={"deskew": mode})}))
        figures[label] = (rpe_translation(res.odometry_poses, gt, delta=10).mean,
                          ate(res.odometry_poses, gt).rmse, res.info["deskew"])
    assert figures["clean"][2]["enabled"] is False and figures["raw_off"][2]["enabled"] is False
    d = figures["raw_auto"][2]
    assert d["enabled"] and d["frames_deskewed"] == 50 and d["time_source"]["data"] == 50
    (rpe_c, ate_c), (rpe_off, ate_off), (rpe_on, ate_on) = (figures[k][:2] for k in ("clean", "raw_off", "raw_auto"))
    # measured: clean 0.002 / 0.002, off 0.051 / 0.071, on 0.011 / 0.006 (RPE-10 mean / ATE RMSE, m)
    assert rpe_on < 0.4 * rpe_off and ate_on < 0.25 * ate_off
    assert rpe_on - rpe_c < 0.25 * (rpe_off - rpe_c)
