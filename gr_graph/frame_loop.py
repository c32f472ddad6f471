"""F_SLAM over one sequence: the frame loop (one round of :mod:`gr_graph.pipeline`).

:func:`run_slam` reads (renders) the frames ahead in a worker thread, two for the densified
scans of the learning rounds (``data.read_threads``; :func:`prefetch_frames`), and for each frame

0. deskews it when ``odometry.deskew`` says so (:class:`FrameDeskewer`): every raw point
   is moved to the sensor frame at mid-sweep, assuming the sensor keeps the velocity of the
   last frame-to-frame motion (the odometry's constant-velocity increment, as KISS-ICP
   does); per-point times come from the frame (``LidarFrame.time``) or else the azimuth
   (densified frames of the learning rounds carry their source points' times);
1. preprocesses it (:func:`gr_graph.preprocess.preprocess_scan`); only the downsampled
   scan is kept;
2. registers it onto the past (:class:`gr_graph.odometry.VgicpOdometry`, its constant-velocity
   guess scaled to the time since the previous frame: dropped frames) and adds the pose
   and its odometry edge to the pose graph; in learning rounds the edge's information may
   first be replaced by the learned H(C) (:class:`gr_graph.edge_noise.LearnedEdgeNoise`);
3. when the :class:`gr_graph.loop_closure.LoopClosureSchedule` says so, looks for a loop
   (candidates on the loop-corrected estimate and by Scan Context, each verified by GICP),
   adds accepted loops to the graph (in learning rounds with their learned H(C) as well)
   and re-optimises it now and then.

After the last frame, a sequence with fewer than two usable scans (no trajectory, only guesses)
stops the run (:func:`check_usable_scans`: :class:`UnusableScansError`, naming the likely causes);
more than half of the scans unusable is a logged warning with the counts.
At the end the whole graph is optimised; in learning rounds every learned edge's information H(C) is
then scaled by one factor from the graph's residuals (:func:`scale_learned_information`; edges that kept
their registration information are calibrated already) (:meth:`_FrameLoop.calibrate_noise`,
:mod:`gr_graph.noise_calibration`) and the graph solved again. Then its marginal covariances
are computed (:class:`SlamResult`). Wall time is accumulated per stage (``read`` is time spent waiting
for frames).
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict, deque
from collections.abc import Collection, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import closing, contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from gr_graph.config import GraphConfig, SlamConfig, loop_max_rmse
from gr_graph.sensors import SensorConfig, check_sequence_sensor
from gr_graph.datasets.base import DatasetError, LidarFrame, LidarSequence, is_motion_compensated
from gr_graph.datasets.registry import counted_rings
from gr_graph.datasets.stamp_gaps import motion_times
from gr_graph.deskew import deskew, deskew_covariances, sweep_motion_from_velocity, times_from_azimuth
from gr_graph.edge_noise import LearnedEdgeNoise
from gr_graph.ground_tilt import GroundTiltOffsets
from gr_graph.loop_closure import LoopClosureSchedule, RowBuffer, ScanContextDatabase, loop_candidates, verify_loop
from gr_graph.odometry import RegistrationEdge, VgicpOdometry
from gr_graph.noise_calibration import (
    LoopAxisVarianceFactors,
    LoopVarianceFactor,
    loop_axis_variance_factors,
    loop_variance_factor,
    outlying_loop,
    variance_factor,
)
from gr_graph.pose_graph import GraphResult, PoseGraph, build_pose_graph
from gr_graph.preprocess import Scan, preprocess_scan, rebuild_scan

log = logging.getLogger(__name__)

# BLAS threads (numpy's and scipy's OpenBLAS) while several threads read a round's frames (the
# learning rounds' network pass, data.read_threads): the products there are thin (N x 3, N x 6) and
# OpenBLAS's team only spun on the cores the readers and the SLAM thread need. A learning round
# 0.84x the time, bit-identical; round 0 (one reader) keeps the team (benchmarks/results/blas_threads.md).
SLAM_BLAS_THREADS = 1
MAX_STARTUP_FRAMES = 5  # raw frames kept to be deskewed once the first motion is known (normally 2)

__all__ = ["FrameDeskewer", "SlamResult", "StageTimer", "UnusableScansError", "check_usable_scans", "deskew_enabled",
           "frame_readers", "frames_read_ahead", "prefetch_frames", "run_slam"]


class UnusableScansError(DatasetError):
    """Too few of a sequence's scans were usable for a trajectory (:func:`check_usable_scans`).

    Attributes
    ----------
    n_usable, n_frames : int
    """

    def __init__(self, message: str, n_usable: int, n_frames: int) -> None:
        super().__init__(message, n_usable, n_frames)  # all three in args: the error pickles
        self.n_usable = n_usable
        self.n_frames = n_frames

    def __str__(self) -> str:
        return str(self.args[0])


def scale_learned_information(edges: list[RegistrationEdge], scale: float) -> int:
    """Multiply the information of every edge that has the learned H(C) (``info["edge_noise"] ==
    "learned"``), and of every failed registration, by ``scale``; return how many edges were left as
    they are.

    Those left are registrations that kept their registration information, already divided by their own
    residuals' variance factor (:func:`gr_graph.odometry.scaled_information`): scaled by the variance
    factor of the raw H(C) (0.002-0.4 in the published runs) they would count hundreds of times less
    than their precision. A failed registration's fallback (a guess, ``graph.fallback_sigmas``) is
    scaled with the learned edges, so that it stays weak beside them.
    """
    kept = 0
    for e in edges:
        if e.info.get("edge_noise") == "learned" or not e.ok:
            e.information = scale * np.asarray(e.information, np.float64)
        else:
            kept += 1
    return kept


def deskew_scan_period(cfg: SlamConfig, sequence: Any) -> float | None:
    """The sweep duration deskewing assumes [s]: ``odometry.deskew_scan_period``, else ``sensor.scan_period``
    (said for the sensor: also for KITTI-layout folders, whose loader has no sweep duration of its own),
    else the sequence's ``scan_period``, else None (one frame spacing)."""
    for value in (cfg.odometry.deskew_scan_period, cfg.sensor.scan_period, getattr(sequence, "scan_period", None)):
        if value is not None:
            return float(value)
    return None


def check_usable_scans(n_usable: int, n_frames: int, name: str, cfg: SlamConfig) -> None:
    """Stop a run whose scans give no trajectory; warn when most of them are unusable.

    A scan is usable when at least ``preprocess.min_points`` points are left after cropping to
    ``[preprocess.min_range, preprocess.max_range]`` and downsampling. With no usable scan, or
    fewer than two of a sequence of two or more, every odometry edge is a fallback guess and the
    trajectory says nothing: :class:`UnusableScansError`, whose message names the likely causes.
    More than half of the scans unusable: a logged warning with the counts.
    """
    pc = cfg.preprocess
    causes = (f"points in millimetres (or another unit) instead of metres; preprocess.min_range "
              f"{pc.min_range:g} m / preprocess.max_range {pc.max_range:g} m cropping every point away; "
              f"scans with fewer than preprocess.min_points {pc.min_points} points (empty or nearly empty files or "
              f"messages, a wrong point_format or topic)")
    if n_usable == 0 or (n_usable < 2 <= n_frames):
        raise UnusableScansError(
            f"{name}: {n_usable} of {n_frames} scans usable, too few for a trajectory (every odometry edge would be "
            f"a guess). Likely causes: {causes}", n_usable, n_frames)
    if n_frames - n_usable > n_frames / 2:
        log.warning("%s: only %d of %d scans usable (%d unusable): their odometry edges are constant-velocity "
                    "guesses. Likely causes: %s", name, n_usable, n_frames, n_frames - n_usable, causes)


class StageTimer:
    """Accumulates wall time per named stage: ``with timer("odometry"): ...``."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - t0


def frames_read_ahead(ahead: int, threads: int) -> int:
    """How many frames :func:`prefetch_frames` reads ahead at most: ``ahead``, at least one a worker."""
    return max(ahead, max(1, int(threads)))


def frame_readers(sequence: LidarSequence, ahead: int, threads: int) -> int:
    """How many worker threads :func:`prefetch_frames` reads ``sequence`` with: none when it does
    not read ahead (``ahead <= 0``: the calling thread reads), ``threads`` for a sequence whose
    ``concurrent_reads`` attribute is true, else one."""
    if ahead <= 0:
        return 0
    return max(1, int(threads)) if getattr(sequence, "concurrent_reads", False) else 1


def prefetch_frames(sequence: LidarSequence, ahead: int = 4, threads: int = 1) -> Iterator[LidarFrame]:
    """Yield ``sequence[0..K-1]`` in order while worker threads read (render) the next ones.

    Reading/rendering (file I/O, open3d ray casting, numpy, torch) releases the GIL, so it
    overlaps with registration. ``ahead=0`` reads in the calling thread. Errors surface in order.
    ``threads`` workers read at once only from a sequence whose ``concurrent_reads`` attribute
    is true (its ``__getitem__`` is thread-safe and a frame does not depend on the order frames
    are read in: :class:`gr_graph.densify.DensifiedSequence`); any other sequence is read by one.
    At least as many frames as workers are read ahead.
    """
    K = len(sequence)
    if ahead <= 0:
        for i in range(K):
            yield sequence[i]
        return
    workers = frame_readers(sequence, ahead, threads)
    ahead = frames_read_ahead(ahead, workers)
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="gr_graph-read") as pool:
        queue: deque = deque(pool.submit(sequence.__getitem__, i) for i in range(min(ahead, K)))
        nxt = len(queue)
        while queue:
            fut = queue.popleft()
            if nxt < K:
                queue.append(pool.submit(sequence.__getitem__, nxt))
                nxt += 1
            yield fut.result()


def unnamed_sensor_note(sequence: Any, sensor: SensorConfig, max_rmse: float) -> str | None:
    """A warning when the data count another number of rings than the configured sensor's beams
    and no sensor was named: the loop threshold (and the catalogue's other figures) are then the
    default sensor's. Only for loaders that count rings from the data (folders, bags); None
    otherwise."""
    rings = counted_rings(sequence)
    if sensor.named_beams is not None or rings in (None, sensor.beams):
        return None
    return (f"the data hold {rings} rings but no sensor is named: the loop-verification RMSE threshold is "
            f"the {sensor.model}'s ({max_rmse:.3f} m for {sensor.beams} beams); name the sensor (--sensor MODEL, "
            "or sensor: {model: custom, n_beams: N, vertical_fov_deg: [...]}) for thresholds of its ring spacing")


def deskew_enabled(mode: str, sequence: LidarSequence) -> tuple[bool, str]:
    """Whether ``odometry.deskew = mode`` deskews ``sequence``, and why (for the run summary).

    ``auto`` deskews sequences that say ``motion_compensated = False``; a sequence without
    the attribute counts as compensated (no change to its results).
    """
    if mode == "on":
        return True, "odometry.deskew: on"
    if mode == "off":
        return False, "odometry.deskew: off"
    compensated = is_motion_compensated(sequence)
    if compensated:
        return False, "auto: the sequence's scans are motion-compensated"
    return True, "auto: the sequence's scans are not motion-compensated"


class FrameDeskewer:
    """Constant-velocity motion compensation of raw frames to mid-sweep (before preprocessing).

    The sweep motion is the last frame-to-frame increment scaled to the sweep duration:
    ``Exp(Log(increment) * scan_period / frame_period)``, where ``frame_period`` is the time
    between the two frames of the increment. Without a ``scan_period`` the sweep is taken to
    last exactly one frame period (a spinning LiDAR sweeping continuously; KISS-ICP's model).

    Parameters
    ----------
    scan_period : float, optional
        Sweep duration [s].
    clockwise, start_azimuth_deg : bool, float
        Frames without per-point times: the spin and the sweep's start azimuth their times are
        taken from (:func:`gr_graph.deskew.times_from_azimuth`; ``sensor.rotation``,
        ``sensor.sweep_start_azimuth_deg``).

    Attributes
    ----------
    n_deskewed : int
        Frames moved (with a non-identity sweep motion).
    n_without_motion : int
        Frames left as they are because no motion was known yet (the first two frames).
    time_sources : dict
        Frames deskewed with times from the data (``"data"``) or the azimuth (``"azimuth"``).
    """

    def __init__(self, scan_period: float | None = None, clockwise: bool = True,
                 start_azimuth_deg: float = 180.0) -> None:
        self.scan_period = scan_period
        self.clockwise, self.start_azimuth_deg = clockwise, start_azimuth_deg  # times from the azimuth
        self.n_deskewed = 0
        self.n_without_motion = 0
        self.time_sources: dict[str, int] = {"data": 0, "azimuth": 0}
        self.applied: dict[int, tuple[np.ndarray, str]] = {}  # frame.index -> (sweep motion, time source)

    def sweep_motion(self, increment: np.ndarray, frame_period: float | None) -> np.ndarray:
        """The sensor's motion over one sweep predicted from the last frame-to-frame increment."""
        if self.scan_period is None or frame_period is None or not frame_period > 0.0:
            return np.asarray(increment, np.float64)
        return sweep_motion_from_velocity(increment, frame_period, self.scan_period)

    def __call__(self, frame: LidarFrame, increment: np.ndarray, frame_period: float | None) -> LidarFrame:
        """``frame`` with its points moved to mid-sweep (the same frame when there is no motion)."""
        motion = self.sweep_motion(increment, frame_period)
        if np.allclose(motion, np.eye(4), rtol=0.0, atol=1e-12) or len(frame) == 0:
            self.n_without_motion += 1
            return frame
        if frame.time is not None:
            times, source = frame.time, "data"
        else:
            times, source = times_from_azimuth(frame.points, self.clockwise, self.start_azimuth_deg), "azimuth"
        self.n_deskewed += 1
        self.time_sources[source] += 1
        self.applied[int(frame.index)] = (motion, source)
        return replace(frame, points=deskew(frame.points, times, motion))

    def move_prediction(self, frame_index: int, points: np.ndarray, covariances: np.ndarray,
                        times: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Points of frame ``frame_index`` taken before deskewing (the network's input, with their
        covariances) moved as the frame was: to mid-sweep, each covariance turned with its point.
        ``times``: the points' sweep fractions (None: from the azimuth, as for a frame without
        times). A frame left as it is gives them back unchanged."""
        applied = self.applied.get(int(frame_index))
        if applied is None:
            return points, covariances
        motion, source = applied
        if source == "azimuth" or times is None or len(times) != len(points):
            times = times_from_azimuth(points, self.clockwise, self.start_azimuth_deg)
        return deskew(points, times, motion), deskew_covariances(covariances, times, motion)

    def redo(self, frame: LidarFrame, increment: np.ndarray, frame_period: float | None) -> LidarFrame:
        """Deskew a frame that was first left as it is (no motion known then); moves it from
        the ``frames_without_motion`` count to the deskewed ones."""
        out = self(frame, increment, frame_period)
        if out is not frame:
            self.n_without_motion -= 1
        return out

    def summary(self, enabled: bool, mode: str, reason: str, stamps_moved_by_s: float = 0.0) -> dict[str, Any]:
        """What the run summary records about deskewing (``stamps_moved_by_s``: the loader moved the
        frame stamps to the sweeps' middles by this much, :mod:`gr_graph.datasets.stamp_shift`)."""
        return {"mode": mode, "enabled": enabled, "reason": reason, "scan_period": self.scan_period,
                "frames_deskewed": self.n_deskewed, "frames_without_motion": self.n_without_motion,
                "time_source": dict(self.time_sources), "stamps_moved_by_s": stamps_moved_by_s}


@dataclass
class SlamResult:
    """Everything one SLAM run (one round) produced.

    ``scans`` are the downsampled scans (float32, LiDAR frame); ``checked[i]`` says whether
    scan i was queried for loops; ``loop_attempts`` lists every verified candidate (accepted
    or not) with its figures; ``covariances`` are the marginals (None if disabled).
    """

    frame_index: np.ndarray
    timestamps: np.ndarray
    poses: np.ndarray
    odometry_poses: np.ndarray
    covariances: np.ndarray | None
    scans: list[np.ndarray]
    edges: list[RegistrationEdge]
    loop_attempts: list[dict]
    checked: np.ndarray
    runtime: dict[str, float]
    graph_error: tuple[float, float] = (float("nan"), float("nan"))
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def loops(self) -> list[RegistrationEdge]:
        return [e for e in self.edges if e.kind == "loop"]


def not_converged_counts(edges: Sequence[RegistrationEdge]) -> dict[str, int]:
    """Accepted edges of each kind (``odometry``, ``loop``) whose registration ended without passing
    small_gicp's convergence test (:attr:`RegistrationEdge.converged`)."""
    return {kind: sum(e.ok and e.kind == kind and not e.converged for e in edges) for kind in ("odometry", "loop")}


class LoopCorrectedEstimate:
    """The current trajectory estimate: the last optimised poses (a prefix of the run), then
    the odometry poses moved by the correction at the end of that prefix."""

    def __init__(self, odometry_poses: list[np.ndarray]) -> None:
        self.odometry_poses = odometry_poses  # grows with the run (VgicpOdometry.poses), append only
        self.optimised = np.zeros((0, 4, 4))
        self._odometry = RowBuffer((4, 4))  # the list's poses as an array, extended as it grows

    def poses(self, upto: int) -> np.ndarray:
        """Estimate of poses ``0..upto-1`` (a new array)."""
        if upto > self._odometry.n:
            self._odometry.extend(self.odometry_poses[self._odometry.n:upto])
        odom = self._odometry.rows(upto).copy()
        n = len(self.optimised)
        if n == 0:
            return odom
        if n >= upto:
            return self.optimised[:upto].copy()
        corr = self.optimised[n - 1] @ np.linalg.inv(odom[n - 1])
        return np.concatenate([self.optimised, corr[None] @ odom[n:]])

    def pose(self, i: int) -> np.ndarray:
        """Estimate of pose ``i``."""
        n = len(self.optimised)
        if n == 0:
            return self.odometry_poses[i]
        if i < n:
            return self.optimised[i]
        return self.optimised[n - 1] @ np.linalg.inv(self.odometry_poses[n - 1]) @ self.odometry_poses[i]


class _FrameLoop:
    """State of one :func:`run_slam` call (see the module docstring)."""

    def __init__(self, sequence: LidarSequence, cfg: SlamConfig, edge_noise: LearnedEdgeNoise | None) -> None:
        self.sequence = sequence
        self.cfg = cfg
        check_sequence_sensor(sequence, cfg.sensor)
        # thresholds that depend on how sparse the rings are follow the sensor (gr_graph.sensors)
        self.loop_cfg = cfg.loops.model_copy(update={"max_rmse": loop_max_rmse(cfg.loops, cfg.sensor,
                                                                               cfg.data.channels)})
        note = unnamed_sensor_note(sequence, cfg.sensor, self.loop_cfg.max_rmse)
        if note:
            log.warning(note)
        self.edge_noise = edge_noise
        self.timer = StageTimer()
        self.odometry = VgicpOdometry(cfg.odometry, cfg.graph)
        self.graph = PoseGraph(cfg.graph)
        self.estimate = LoopCorrectedEstimate(self.odometry.poses)
        self.schedule = LoopClosureSchedule(self.loop_cfg)
        self.scan_context = ScanContextDatabase(self.loop_cfg) if self.loop_cfg.use_scan_context else None
        self.scans: list[np.ndarray] = []
        self.frame_index: list[int] = []
        self.edges: list[RegistrationEdge] = []
        self.attempts: list[dict] = []
        self.checked = np.zeros(len(sequence), dtype=bool)
        self.n_flagged = 0
        self.loop_variance: dict[str, Any] | None = None  # graph.loop_variance: estimated (finish)
        self.ground_tilt = GroundTiltOffsets() if cfg.graph.ground_tilt_offset else None
        self.n_dropped = 0
        self.usable: list[bool] = []  # per run position: the scan was usable (preprocess.min_points)
        self.deskew_on, self.deskew_reason = deskew_enabled(cfg.odometry.deskew, sequence)
        scan_period = deskew_scan_period(cfg, sequence)
        self.deskewer = FrameDeskewer(scan_period, cfg.sensor.rotation == "clockwise", cfg.sensor.sweep_start_azimuth_deg)
        self.startup_frames: list[LidarFrame] = []  # raw frames seen before any motion was known
        self.startup_given_up = False  # more than MAX_STARTUP_FRAMES of them: they stay as they are
        self.stamps_moved_by_s = float(getattr(sequence, "stamps_moved_by_s", 0.0))  # by the loader (stamp_shift)
        stamps = getattr(sequence, "timestamps", None)
        # the motion model's times: stamps displaced off the sensor's beat moved back onto it (stamp_gaps)
        self.motion = None if stamps is None else motion_times(stamps, getattr(sequence, "name", "sequence"))
        if self.stamps_moved_by_s and not self.deskew_on:
            log.warning("the frame stamps were moved by %+.4g s to the sweeps' middles, but deskewing is off (%s): "
                        "the poses refer to the scans as the data hold them, not necessarily to the sweeps' middles",
                        self.stamps_moved_by_s, self.deskew_reason)
        if self.deskew_on:
            log.info("deskewing every frame to mid-sweep (%s)", self.deskew_reason)
            if edge_noise is not None:  # H(C) pairs the network's points under T̂ between deskewed frames
                edge_noise.motion_correction = self.deskewed_prediction

    def deskewed_prediction(self, frame_index: int, points: np.ndarray,
                            covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The network's points and covariances of a frame, deskewed as the frame was
        (:meth:`FrameDeskewer.move_prediction`, with the per-point times of the densified view)."""
        times_of = getattr(self.sequence, "prediction_times", None)
        times = None if times_of is None else times_of(frame_index)
        return self.deskewer.move_prediction(frame_index, points, covariances, times)

    @property
    def n_loops(self) -> int:
        return sum(e.kind == "loop" for e in self.edges)

    def run(self, desc: str) -> SlamResult:
        """SLAM over the sequence; numpy's BLAS on ``SLAM_BLAS_THREADS`` while several threads read."""
        several_readers = frame_readers(self.sequence, self.cfg.data.prefetch, self.cfg.data.read_threads) > 1
        with threadpool_limits(SLAM_BLAS_THREADS if several_readers else None, user_api="blas"):
            return self.run_frames(desc)

    def run_frames(self, desc: str) -> SlamResult:
        """Read, register and look for loops frame by frame, then :meth:`finish`."""
        K = len(self.sequence)
        bar = tqdm(range(K), desc=f"slam{desc}", unit="frame", disable=not self.cfg.output.progress,
                   mininterval=1.0)
        # closed on an error too: the readers stop before the caller's BLAS team is back
        with closing(prefetch_frames(self.sequence, self.cfg.data.prefetch, self.cfg.data.read_threads)) as frames:
            for i in bar:
                with self.timer("read"):  # time spent waiting for the reader thread
                    frame = next(frames)
                if self.deskew_on:
                    frame = self.deskew(i, frame)
                scan = self.preprocess(frame)
                self.add_odometry(i, scan)
                if self.loop_cfg.enabled:
                    with self.timer("loops"):
                        self.look_for_loop(i, scan)
                bar.set_postfix(loops=self.n_loops, flagged=self.n_flagged, refresh=False)
        bar.close()
        check_usable_scans(sum(self.usable), K, getattr(self.sequence, "name", "sequence"), self.cfg)
        return self.finish()

    def deskew(self, i: int, frame: LidarFrame) -> LidarFrame:
        """Frame ``i`` (position in the run) moved to mid-sweep with the odometry's last increment.

        The frames seen before any motion was known (the first two, which stay as they are)
        are deskewed with the first known motion when it comes, and the odometry's map is
        rebuilt from them, so that no distorted scan stays in the map (a car already driving
        at frame 0 would otherwise see its first deskewed scan jump against them).
        """
        frame_period = self.odometry.last_increment_period  # the time the increment spans (after a flagged step too)
        if frame_period is None and i >= 2:
            frame_period = self.frame_time_step(i - 1)
        increment = self.odometry.last_increment
        with self.timer("deskew"):
            out = self.deskewer(frame, increment, frame_period)
        if out is frame and self.deskewer.n_deskewed == 0:
            if len(self.startup_frames) < MAX_STARTUP_FRAMES:
                self.startup_frames.append(frame)
            elif not self.startup_given_up:
                log.warning("deskew: no motion known after %d frames; the first frames stay in the map as they are",
                            MAX_STARTUP_FRAMES)
                self.startup_given_up = True
        elif self.startup_frames:
            if not self.startup_given_up:
                self.redo_startup_frames(increment, frame_period)
            self.startup_frames = []
        return out

    def redo_startup_frames(self, increment: np.ndarray, frame_period: float | None) -> None:
        """Deskew the startup frames with ``increment``, re-preprocess them, rebuild the map."""
        with self.timer("deskew"):
            frames = [self.deskewer.redo(f, increment, frame_period) for f in self.startup_frames]
        scans = [self.preprocess(f) for f in frames]
        for j, scan in enumerate(scans):
            self.n_dropped -= scan.n_dropped  # counted when the frame was first preprocessed
            self.scans[j] = scan.points.astype(np.float32)
            self.usable[j] = bool(scan.usable)
            if self.ground_tilt is not None:
                self.ground_tilt.forget(j)
        with self.timer("odometry"):
            self.odometry.rebuild_map(scans)
        log.debug("deskewed the %d startup frames and rebuilt the odometry map", len(scans))

    def preprocess(self, frame: LidarFrame) -> Scan:
        with self.timer("preprocess"):
            scan = preprocess_scan(frame.points, self.cfg.preprocess, index=int(frame.index),
                                   num_threads=self.cfg.odometry.num_threads)
        self.n_dropped += scan.n_dropped
        return scan

    def frame_time_step(self, i: int) -> float | None:
        """Seconds between frames ``i - 1`` and ``i`` (run positions) from the sequence's
        timestamps, displaced stamps moved onto the sensor's beat (:func:`motion_times`); None for
        the first frame or when the timestamps do not say."""
        ts = None if self.motion is None else self.motion.times
        if i < 1 or ts is None or len(ts) <= i:
            return None
        dt = float(ts[i]) - float(ts[i - 1])
        return dt if np.isfinite(dt) else None

    def add_odometry(self, i: int, scan: Scan) -> None:
        """Register scan ``i`` (its constant-velocity guess scaled to the time since the previous
        frame: dropped frames); add its pose and odometry edge to the graph."""
        self.usable.append(bool(scan.usable))
        with self.timer("odometry"):
            edge = self.odometry.step(scan, self.frame_time_step(i))
        self.scans.append(scan.points.astype(np.float32))
        self.frame_index.append(int(scan.index))
        self.graph.add_pose(self.estimate.pose(i))
        if edge is None:
            return
        if self.edge_noise is not None:
            with self.timer("edge_noise"):
                self.edge_noise.apply(edge, self.frame_index[edge.source], self.frame_index[edge.target])
        if self.ground_tilt is not None:
            self.ground_tilt.widen(edge, self.scans)
        self.edges.append(edge)
        self.n_flagged += int(not edge.ok)
        self.graph.add_edge(edge.source, edge.target, edge.T, edge.information, loop=False)

    def look_for_loop(self, i: int, scan: Scan) -> None:
        """Loop closure at scan ``i`` when the schedule says so; re-optimise after new loops."""
        if self.scan_context is not None:
            self.scan_context.add(scan.points)
        if not self.schedule.should_check(i, scan.usable):
            return
        self.checked[i] = True
        est = self.estimate.poses(i + 1)
        pc, oc, lc = self.cfg.preprocess, self.cfg.odometry, self.loop_cfg
        for cand in loop_candidates(est, i, self.scan_context, lc):
            target = rebuild_scan(self.scans[cand.match], pc, index=self.frame_index[cand.match],
                                  num_threads=oc.num_threads)
            le = verify_loop(scan, target, cand, lc, self.cfg.graph, num_threads=oc.num_threads)
            self.attempts.append(
                {"query": i, "match": cand.match, "frame_query": self.frame_index[i],
                 "frame_match": self.frame_index[cand.match], "accepted": le.ok, "reason": le.reason,
                 "T": le.T, **le.info}
            )
            if le.ok:
                if self.edge_noise is not None:
                    with self.timer("edge_noise"):
                        self.edge_noise.apply(le, self.frame_index[le.source], self.frame_index[le.target])
                if self.ground_tilt is not None:
                    self.ground_tilt.widen(le, self.scans)
                self.edges.append(le)
                self.graph.add_edge(le.source, le.target, le.T, le.information, loop=True)
                self.schedule.loop_accepted()
                log.debug("loop (%d, %d) accepted via %s", i, cand.match, cand.source)
                break
        if self.schedule.should_reoptimize(i):
            with self.timer("graph"):
                self.graph.set_estimate(est)
                self.estimate.optimised = self.graph.optimize(marginals=False).poses
            self.schedule.reoptimized(i)

    def calibrate_noise(self, poses: np.ndarray) -> GraphResult:
        """Scale every learned edge's information by ``1 / sigma0^2`` of the graph and solve it again.

        ``sigma0^2`` (:func:`gr_graph.noise_calibration.variance_factor`) is taken at the
        optimum of the Gaussian graph (loops without their robust kernel, started from
        ``poses``): the variance factor is defined for the least-squares model, and a uniform
        scale does not move that optimum, so one estimate is exact for it. The robust graph
        with the scaled information is then solved from there. The scale is recorded in
        :attr:`LearnedEdgeNoise.calibration`; without loops there is no redundancy and nothing
        changes (scale 1, logged). Loops failing the deletion test of
        :func:`gr_graph.noise_calibration.outlying_loop` are left out of the estimate, worst
        first, the Gaussian graph solved again without each, at most a tenth of the loops (one
        with fewer than 20; recorded under ``loops_left_out``).
        """
        assert self.edge_noise is not None
        gaussian_cfg = self.cfg.graph.model_copy(update={"loop_kernel": "none"})
        gaussian = self._graph_of(poses, gaussian_cfg)
        optimum = gaussian.optimize(marginals=False).poses
        left_out: list[int] = []
        tests: list[dict[str, Any]] = []
        alpha = self.cfg.training.learned_noise_outlier_alpha
        n_loops = sum(e.kind == "loop" and e.ok for e in self.edges)
        # a few wrong loops, not a systematic disagreement of every loop with the odometry (e.g. a
        # miscalibrated sensor): that is the variance factor's to absorb, so at most a tenth are left out
        most = max(1, n_loops // 10)
        while len(left_out) < most and (found := self._outlying_loop(gaussian, left_out, alpha)) is not None:
            e = self.edges[found[0]]
            left_out.append(found[0])
            tests.append({"loop": [int(e.source), int(e.target)], "f_statistic": found[1], "threshold": found[2]})
            log.warning("edge noise calibration: loop (%d, %d) left out of the variance factor: F = %.3g against the "
                        "other edges (threshold %.3g at alpha %g); it stays in the robust graph",
                        e.source, e.target, found[1], found[2], alpha)
            gaussian = self._graph_of(optimum, gaussian_cfg, skip=left_out)
            optimum = gaussian.optimize(marginals=False).poses
        if len(left_out) == most and n_loops > 1 and self._outlying_loop(gaussian, left_out, alpha) is not None:
            log.warning("edge noise calibration: more loops fail the test than the %d left out (a tenth of %d); the "
                        "others count", most, n_loops)
        vf = variance_factor(optimum, [e for i, e in enumerate(self.edges) if i not in left_out])
        self.edge_noise.calibration = {**vf.summary(), "loops_left_out": tests, "loops_left_out_max": most}
        if vf.sigma0_sq is None:
            log.info("edge noise calibration: no redundancy (no loops), information left as it is")
        else:
            log.info("edge noise calibration: sigma0^2 = %.4g over redundancy %d (chi2 odometry %.4g, loops %.4g): "
                     "every edge's information x %.4g", vf.sigma0_sq, vf.redundancy, vf.chi2["odometry"],
                     vf.chi2["loop"], vf.scale)
        kept = scale_learned_information(self.edges, vf.scale)
        if kept:
            log.info("edge noise calibration: %d edges without H(C) keep their registration information", kept)
        self.edge_noise.calibration["n_edges_not_scaled"] = kept
        self.graph = self._graph_of(gaussian.current_poses(), self.cfg.graph)
        return self.graph.optimize(marginals=False)

    def _outlying_loop(self, gaussian: PoseGraph, left_out: list[int], alpha: float) -> tuple[int, float, float] | None:
        """:func:`~gr_graph.noise_calibration.outlying_loop` on the Gaussian graph of every edge but
        ``left_out`` (at its optimum); the loop's index into :attr:`edges`. None when the test
        cannot be made (e.g. a singular normal matrix; logged: nothing more is left out), so that a
        solved round is never lost to it."""
        kept = [i for i in range(len(self.edges)) if i not in left_out]
        try:
            found = outlying_loop(gaussian.graph, gaussian.values, [self.edges[i] for i in kept], alpha)
        except Exception as exc:  # e.g. splu on a pose no factor constrains, or no memory: the round is solved
            log.warning("edge noise calibration: no loop tested (%s: %s); every loop counts", type(exc).__name__, exc)
            return None
        return None if found is None else (kept[found[0]], found[1], found[2])

    def _scale_loops(self, factors: LoopVarianceFactor | LoopAxisVarianceFactors) -> None:
        """Apply ``factors`` to every loop edge's information."""
        for e in self.edges:
            if e.kind == "loop":
                e.information = factors.scaled_information(e.information)

    def _scale_loops_per_axis(self, solve: Any) -> None:
        """The per-axis stage of ``estimated_axes`` on the loops the common factor has scaled; a
        failure (memory, gtsam) is logged and recorded and keeps the common factor: it never loses
        the run."""
        try:
            axes = loop_axis_variance_factors(solve, self.edges)
        except Exception as exc:  # noqa: BLE001 - the run is finished: keep the common factor
            log.warning("loop variance per axis failed (%s: %s); the loops keep the common factor",
                        type(exc).__name__, exc)
            self.loop_variance["axes"] = {"method": "loop_axis_variance_components",
                                          "reason": f"failed: {type(exc).__name__}: {exc}"}
            return
        self.loop_variance["axes"] = axes.summary()
        if axes.reason is not None:
            log.info("loop variance per axis: not estimated (%s)", axes.reason)
            return
        log.info("loop variance per axis (roll, pitch, yaw, x, y, z): loop information x %s (%d iterations%s)",
                 ", ".join(f"{v:.4g}" for v in axes.axis_scale), axes.iterations,
                 "" if axes.converged else ", not converged: the last factors are applied")
        self._scale_loops(axes)

    def estimate_loop_variance(self, poses: np.ndarray) -> GraphResult | None:
        """Divide every loop edge's information by the loops' variance factor and solve again
        (``graph.loop_variance: estimated``, :func:`gr_graph.noise_calibration.loop_variance_factor`).
        ``estimated_axes``: then, on the scaled loops, one more factor per tangent axis that only
        weakens (:func:`~gr_graph.noise_calibration.loop_axis_variance_factors`), recorded under
        ``"axes"`` in :attr:`loop_variance`.

        The factor is estimated on the Gaussian graph (loops without their robust kernel, started
        from ``poses``), the odometry edges' information held fixed; the robust graph with the
        scaled loops is then solved from that solution. Recorded in :attr:`loop_variance`.
        Returns None when nothing was estimated (the graph and its solution stay as they are).
        """
        gaussian_cfg = self.cfg.graph.model_copy(update={"loop_kernel": "none"})
        latest = [np.asarray(poses)]

        def solve(informations: list[np.ndarray]) -> tuple[Any, Any]:
            graph = self._graph_of(latest[0], gaussian_cfg, informations)
            latest[0] = graph.optimize(marginals=False).poses
            return graph.graph, graph.values

        lv = loop_variance_factor(solve, self.edges)
        self.loop_variance = lv.summary()
        if lv.reason is not None:
            log.info("loop variance: not estimated (%s); loop information left as it is", lv.reason)
            return None
        log.info("loop variance: sigma_L^2 %s over loop redundancy %.1f (%d loops): loop information x %.4g",
                 ", ".join(f"{v:.4g}" for v in lv.sigma_sq), lv.redundancy, lv.n_loops, lv.scale)
        self._scale_loops(lv)
        if self.cfg.graph.loop_variance == "estimated_axes":  # then per axis, only where an axis needs more
            self._scale_loops_per_axis(solve)
        self.graph = self._graph_of(latest[0], self.cfg.graph)
        return self.graph.optimize(marginals=False)

    def _graph_of(self, poses: np.ndarray, graph_cfg: GraphConfig,
                  informations: list[np.ndarray] | None = None, skip: Collection[int] = ()) -> PoseGraph:
        """A new pose graph with ``poses`` as estimate and every edge of the run (with
        ``informations`` in edge order instead of the edges' own, if given), but the edges at
        the positions ``skip``."""
        infos = informations if informations is not None else [e.information for e in self.edges]
        return build_pose_graph(graph_cfg, poses, ((e.source, e.target, e.T, H, e.kind == "loop") for i, (e, H)
                                                   in enumerate(zip(self.edges, infos, strict=True)) if i not in skip))

    def finish(self) -> SlamResult:
        """Optimise the whole graph, compute the marginals; the run's result (the frame loop
        has checked that enough scans were usable: :func:`check_usable_scans`)."""
        K = len(self.sequence)
        if self.n_flagged:
            log.warning("%d of %d odometry edges failed and were replaced by the constant-velocity guess",
                        self.n_flagged, max(K - 1, 0))
        for kind, n in not_converged_counts(self.edges).items():
            if n:
                log.warning("%d accepted %s edges ended without passing small_gicp's convergence test (iteration "
                            "limit, or no step lowered the error); kept, as their other tests passed", n, kind)
        odom_poses = np.asarray(self.odometry.poses)
        with self.timer("graph"):
            self.graph.set_estimate(self.estimate.poses(K))
            res = self.graph.optimize(marginals=False)
            calibrating = ((self.edge_noise is not None and self.edge_noise.calibrate)
                           or self.cfg.graph.loop_variance != "fixed")
            if calibrating and self.ground_tilt is not None:  # estimated on the informations before the widening
                self.ground_tilt.restore()
            if self.edge_noise is not None and self.edge_noise.calibrate:
                res = replace(self.calibrate_noise(res.poses), initial_error=res.initial_error)
            if self.cfg.graph.loop_variance != "fixed":
                scaled = self.estimate_loop_variance(res.poses)
                if scaled is not None:
                    res = replace(scaled, initial_error=res.initial_error)
            if calibrating and self.ground_tilt is not None:  # then the calibrated informations widened
                self.ground_tilt.rewiden()
                self.graph = self._graph_of(res.poses, self.cfg.graph)
                res = replace(self.graph.optimize(marginals=False), initial_error=res.initial_error)
        covs, marginals = None, None
        if self.cfg.graph.marginals:
            with self.timer("marginals"):
                covs, report = self.graph.marginals_with_fallback()  # never raises on an indeterminate graph
            marginals = report.to_dict()
        log.info("pose graph: error %.4g -> %.4g in %d iterations; %d loops", res.initial_error, res.final_error,
                 res.iterations, self.n_loops)
        return SlamResult(
            frame_index=np.asarray(self.frame_index, dtype=np.int64),
            timestamps=np.asarray(self.sequence.timestamps, dtype=np.float64)[:K],
            poses=res.poses,
            odometry_poses=odom_poses,
            covariances=covs,
            scans=self.scans,
            edges=self.edges,
            loop_attempts=self.attempts,
            checked=self.checked,
            runtime=dict(self.timer.seconds),
            graph_error=(res.initial_error, res.final_error),
            info={"n_flagged_odometry": self.n_flagged, "n_dropped_nonfinite": self.n_dropped,
                  "n_unusable_scans": len(self.usable) - sum(self.usable),
                  "scans_left_out_of_map": self.odometry.scans_left_out_of_map,
                  "deskew": self.deskewer.summary(self.deskew_on, self.cfg.odometry.deskew, self.deskew_reason,
                                                  self.stamps_moved_by_s),
                  "stamp_gaps": None if self.motion is None else self.motion.summary(),
                  "sensor": {"model": self.cfg.sensor.model, "channels": self.cfg.channels,
                             "loop_max_rmse": self.loop_cfg.max_rmse,
                             # rings a folder or bag loader counted (None: not counted), beside the
                             # configured sensor's channels whose figures the run used
                             "data_rings": counted_rings(self.sequence)},
                  "marginals": marginals, "loop_variance": self.loop_variance,
                  "ground_tilt_offset": None if self.ground_tilt is None else self.ground_tilt.summary()},
        )


def run_slam(sequence: LidarSequence, cfg: SlamConfig, desc: str = "",
             edge_noise: LearnedEdgeNoise | None = None) -> SlamResult:
    """F_SLAM: odometry, loop closures, pose graph and marginals over ``sequence``.

    Frames are read (rendered) one at a time; only the downsampled scans are kept.
    ``edge_noise`` (learning rounds, ``training.edge_noise: learned``) replaces each odometry
    edge's information by the learned H(C) before it enters the graph. ``desc`` labels the
    progress bar.

    Raises
    ------
    UnusableScansError
        Fewer than two of the sequence's scans usable (:func:`check_usable_scans`).
    """
    return _FrameLoop(sequence, cfg, edge_noise).run(desc)
