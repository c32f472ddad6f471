"""Densified scans S+_k for the learning rounds (Algorithm 2 of the paper, lines 3-9).

:func:`densified_sequence` wraps a :class:`~gr_graph.datasets.base.LidarSequence` in a lazy
view (:class:`DensifiedSequence`): frame ``k`` is computed when it is read and nothing is
cached. Same ``len``, ``timestamps``, ``gt_poses`` and ``T_cam_velo`` as the input. Frame
``k`` of the view is built as follows:

1. the raw frame is preprocessed exactly as SLAM preprocesses a scan
   (:func:`gr_graph.preprocess.preprocess_scan`: non-finite points dropped, range crop,
   voxel downsampling with ``preprocess.voxel_size``). Those downsampled points are what the
   memory stores and what the network was trained on, so the network sees in-distribution
   input;
2. the network predicts a covariance ``C_i`` per point (``training.predict.
   predict_covariances``, seeded);
3. anisotropy filter: a point is kept if ``a_i = 1 - l_min / l_max > tau_ani``;
4. ``M = samples_per_point`` samples ``~ N(s_i, C_i)`` are drawn per kept point
   (``training.densify.densify``), with the generator seeded by ``(seed, frame index)``,
   so a frame is the same whenever, and in whatever order, it is read.

**By default the scan keeps every point and gains the samples** (``training.keep_original`` and
``training.keep_dropped`` true: densification that adds, never removes, structure; the default since
2026-12-05, measured in the README's Results). The paper's Algorithm 2 (both false) does not include
the kept points themselves (its S+ holds only their samples) and drops the points the filter drops.
Intensity and per-point time: every output point inherits those of its source point (the raw point
nearest to the downsampled point), so learning rounds deskew with the sensor's times as round 0 does;
``ring`` is None.

Fallbacks (each logged with a warning and recorded in :attr:`DensifiedSequence.fallbacks`,
``{frame index: reason}``; :meth:`DensifiedSequence.stats` counts them):

* ``"nonfinite_covariance"`` / ``"non_pd_covariance"``: the network produced non-finite
  covariances for the frame, or covariances that are not positive definite
  (:func:`covariance_problem`): the **raw frame** is returned unchanged;
* ``"few_kept"``: fewer than ``min_kept_points`` points passed the anisotropy filter and the
  filter's dropped points are not kept (``keep_dropped`` false, the paper's densification: the
  output would be too few points for registration): the **unfiltered preprocessed points** (the
  scan as the network saw it, no sampling) are returned. With ``keep_dropped`` (the default)
  every point stays in the output however few pass the filter, so there is no fallback: the
  frame is its points plus the few samples;
* ``"unusable_scan"``: preprocessing left fewer than ``preprocess.min_points`` points (SLAM
  would flag the scan anyway): the raw frame is returned.

Predicted covariances: the points the network saw and its covariances are kept for the
``keep_predictions`` most recently computed frames (default 16; the pipeline keeps more than
the SLAM prefetch depth) and returned by :meth:`DensifiedSequence.predicted`, so that the learning rounds can
build each odometry edge's information H(C) without running the network again.

One cloud outside a sequence: :func:`densify_cloud` (and the ``gr-densify`` command,
:mod:`gr_graph.densify_cli`) runs the same steps 1-4 through :func:`densify_points`, the
function the view uses for every frame.

``checkpoint`` may be a ``model.pt`` / ``checkpoint.pt`` path, a
``training.network.CovarianceNet``, or any callable ``points (N, 3) -> C (N, 3, 3)`` (tests,
hand-made covariance models).
"""

from __future__ import annotations

import logging
import os
import threading
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from gr_graph.config import PreprocessConfig, TrainingConfig
from gr_graph.datasets.base import LidarFrame, LidarSequence, inherit_sweep_attributes
from gr_graph.preprocess import preprocess_scan

log = logging.getLogger(__name__)

__all__ = ["DensifiedSequence", "densified_sequence", "FALLBACK_REASONS", "DensifiedPoints", "densify_points",
           "horizontal_surfaces",
           "densify_cloud", "covariance_problem", "covariances_valid", "COVARIANCE_FALLBACKS"]

FALLBACK_REASONS = {
    "nonfinite_covariance": "covariances (network or PCA) non-finite: raw frame used",
    "non_pd_covariance": "covariances (network or PCA) not positive definite: raw frame used",
    "few_kept": "too few points passed the anisotropy filter: unfiltered preprocessed points used",
    "unusable_scan": "too few points after preprocessing: raw frame used",
}

Predictor = Callable[[np.ndarray], np.ndarray]
COVARIANCE_FALLBACKS = ("nonfinite_covariance", "non_pd_covariance")  # the raw frame is used


def covariance_problem(C: np.ndarray) -> str | None:
    """Why ``(N, 3, 3)`` covariances cannot be used: ``"nonfinite_covariance"``,
    ``"non_pd_covariance"`` (smallest eigenvalue of the symmetric part <= 0), or None."""
    return _problem_and_eigenvalues(C)[0]


def _problem_and_eigenvalues(C: np.ndarray) -> tuple[str | None, np.ndarray | None]:
    """:func:`covariance_problem` and, for finite ``C``, the ascending eigenvalues of its
    symmetric parts (``training.densify.symmetric_eigenvalues``, reused by the anisotropy filter)."""
    from training.densify import symmetric_eigenvalues

    C = np.asarray(C, np.float64)
    if not np.isfinite(C).all():
        return "nonfinite_covariance", None
    w = symmetric_eigenvalues(C)
    if len(C) and w[:, 0].min() <= 0.0:
        return "non_pd_covariance", w
    return None, w


# codes of surface_orientation
NO_NORMAL, HORIZONTAL, VERTICAL, OBLIQUE = 0, 1, 2, 3


def surface_orientation(C: np.ndarray, max_tilt_deg: float = 30.0) -> np.ndarray:
    """``(N,)`` int8 code per covariance, from its minor axis (the surface normal) in the sensor frame.

    :data:`HORIZONTAL`: the normal within ``max_tilt_deg`` of the z axis (the ground, for a
    level-mounted sensor); :data:`VERTICAL`: within ``max_tilt_deg`` of the x-y plane (walls,
    fronts, poles' sides); :data:`OBLIQUE`: between; :data:`NO_NORMAL`: no defined normal (the
    smallest eigenvalue not under half the middle one: edges, corners, clutter).
    """
    C = np.asarray(C, np.float64)
    out = np.full(len(C), NO_NORMAL, np.int8)
    if len(C) == 0:
        return out
    w, V = np.linalg.eigh(0.5 * (C + C.transpose(0, 2, 1)))
    nz = np.abs(V[:, 2, 0])
    has_normal = w[:, 0] < 0.5 * w[:, 1]
    out[has_normal] = OBLIQUE
    out[has_normal & (nz > np.cos(np.radians(max_tilt_deg)))] = HORIZONTAL
    out[has_normal & (nz < np.sin(np.radians(max_tilt_deg)))] = VERTICAL
    return out


def horizontal_surfaces(C: np.ndarray, max_tilt_deg: float = 30.0) -> np.ndarray:
    """``(N,)`` bool: covariances whose minor axis (the surface normal) is within ``max_tilt_deg``
    of the sensor's z axis, i.e. horizontal surfaces (the ground, for a level-mounted sensor).
    Only covariances with a defined normal count (:func:`surface_orientation`).

    A diagnostic of what the anisotropy filter keeps (:meth:`DensifiedSequence.stats`):
    ground points move with the sensor's ring pattern and constrain neither forward motion nor
    heading, so a densified scan made mostly of them registers poorly along the direction of travel.
    """
    return surface_orientation(C, max_tilt_deg) == HORIZONTAL


def covariances_valid(C: np.ndarray) -> bool:
    """Whether every covariance of ``C`` is finite and positive definite."""
    return covariance_problem(C) is None


def _make_predictor(checkpoint: Any, device: str, seed: int, full_passes: bool = False) -> Predictor:
    """A function ``points -> C`` from a path (or ``"pretrained"``), a CovarianceNet or a callable
    (``full_passes``: :func:`training.predict.predict_covariances`' option, ``training.prediction_passes``)."""
    if isinstance(checkpoint, (str, os.PathLike)):
        from gr_graph.pretrained import resolve_weights
        from training.trainer import load_model

        checkpoint = load_model(resolve_weights(checkpoint), device)  # load once, not per frame
    from training.network import CovarianceNet

    if isinstance(checkpoint, CovarianceNet):
        from training.predict import predict_covariances

        model = checkpoint.eval()  # once: predict_covariances then never switches modes (reader threads share it)

        def predict(points: np.ndarray) -> np.ndarray:
            return predict_covariances(model, points, device=device, seed=seed, full_passes=full_passes)

        return predict
    if callable(checkpoint):
        return checkpoint
    raise TypeError(f"densified_sequence: checkpoint must be a path, a CovarianceNet or a callable, got {type(checkpoint)}")


@dataclass(frozen=True)
class DensifiedPoints:
    """The densification of one scan (:func:`densify_points`).

    Attributes
    ----------
    points : (M, 3) float64
        The output: the samples (grouped by source point, ``samples_per_point`` consecutive
        rows each, after the kept points themselves with ``keep_original``; then, with
        ``keep_dropped``, the points the filter dropped, unchanged); with the
        ``"few_kept"`` fallback the network's input unchanged; with a covariance fallback
        empty.
    source : (M,) int64
        Row of ``network_input`` each output point comes from.
    network_input : (N, 3) float64
        The (preprocessed) points the network saw.
    input_covariances : (N, 3, 3) float64 or None
        The network's covariance of each input point (None with a covariance fallback).
    kept : (N,) bool
        Which input points passed the anisotropy filter.
    fallback : str or None
        A key of :data:`FALLBACK_REASONS` (``"nonfinite_covariance"``, ``"non_pd_covariance"`` or
        ``"few_kept"``), or None.
    intensity : (M,) float32 or None
        Intensity of each output point (its source point's), when the input had intensity
        (:func:`densify_cloud`).
    """

    points: np.ndarray
    source: np.ndarray
    network_input: np.ndarray
    input_covariances: np.ndarray | None
    kept: np.ndarray
    fallback: str | None
    intensity: np.ndarray | None = None

    @property
    def n_kept(self) -> int:
        return int(self.kept.sum())

    @property
    def covariances(self) -> np.ndarray:
        """``(M, 3, 3)``: the covariance of each output point's source point."""
        if self.input_covariances is None:
            return np.zeros((0, 3, 3))
        return self.input_covariances[self.source]


def densify_points(points: np.ndarray, predictor: Predictor, cfg: TrainingConfig, seed: Any,
                   index: int = -1) -> DensifiedPoints:
    """Algorithm 2, lines 3-9, on one preprocessed scan: covariances, anisotropy filter, samples.

    Parameters
    ----------
    points : (N, 3) array
        The scan as the network sees it (preprocessed like the memory it was trained on).
    predictor : callable
        ``points (N, 3) -> C (N, 3, 3)`` (see :func:`_make_predictor`).
    cfg : TrainingConfig
        ``tau_ani``, ``samples_per_point``, ``keep_original``, ``keep_dropped``, ``min_kept_points``.
    seed : int or sequence of int
        Seed of the sampling (the pipeline: ``[training.seed, frame index]``).
    index : int
        Frame index, for messages.

    Returns
    -------
    DensifiedPoints
        With ``fallback`` set as in the module docstring: non-finite or not positive
        definite covariances give ``"nonfinite_covariance"`` / ``"non_pd_covariance"`` (no output points), fewer than
        ``min_kept_points`` kept points give ``"few_kept"`` (the input points, unfiltered) unless
        ``keep_dropped`` keeps every input point anyway.
    """
    from training.densify import densify

    s = np.asarray(points, np.float64)
    no_kept = np.zeros(len(s), bool)
    try:
        C = np.asarray(predictor(s), np.float64)
    except FloatingPointError as exc:
        log.debug("densify frame %d: %s", index, exc)
        return DensifiedPoints(np.zeros((0, 3)), np.zeros(0, np.int64), s, None, no_kept, "nonfinite_covariance")
    if C.shape != (len(s), 3, 3):
        raise ValueError(f"densify frame {index}: covariances must be ({len(s)}, 3, 3), got {C.shape}")
    problem, eigenvalues = _problem_and_eigenvalues(C)
    if problem is not None:
        log.debug("densify frame %d: %s", index, FALLBACK_REASONS[problem])
        return DensifiedPoints(np.zeros((0, 3)), np.zeros(0, np.int64), s, None, no_kept, problem)
    try:
        dense, kept = densify(s, C, cfg.tau_ani, cfg.samples_per_point, seed=seed,  # type: ignore[arg-type]
                              include_original=cfg.keep_original, eigenvalues=eigenvalues)
    except np.linalg.LinAlgError as exc:  # positive definite to eigvalsh, not to the Cholesky factorisation
        log.debug("densify frame %d: %s", index, exc)
        return DensifiedPoints(np.zeros((0, 3)), np.zeros(0, np.int64), s, None, no_kept, "non_pd_covariance")
    if int(kept.sum()) < cfg.min_kept_points and not cfg.keep_dropped:  # the output would be too few points
        return DensifiedPoints(s, np.arange(len(s), dtype=np.int64), s, C, kept, "few_kept")
    kept_rows = np.flatnonzero(kept)
    source = np.repeat(kept_rows, cfg.samples_per_point)
    if cfg.keep_original:
        source = np.concatenate([kept_rows, source])
    if cfg.keep_dropped:
        dropped_rows = np.flatnonzero(~kept)
        dense = np.concatenate([dense, s[dropped_rows]])
        source = np.concatenate([source, dropped_rows])
    return DensifiedPoints(dense, source.astype(np.int64), s, C, kept, None)


def _source_times(raw: LidarFrame, points: np.ndarray) -> np.ndarray | None:
    """The per-point time of the raw point nearest to each of ``points`` (None without times)."""
    if raw.time is None or not len(raw.points):
        return None
    rows = nearest_raw_rows(raw.points, points)
    return None if rows is None else np.asarray(raw.time, np.float64)[rows]


def nearest_raw_rows(raw_points: np.ndarray, points: np.ndarray) -> np.ndarray | None:
    """Row of the raw point nearest to each of ``points`` (None when no raw point is finite).

    A voxel centroid of two raw points is as near to one as to the other; such ties go to either
    (small_gicp's k-d tree, ~1.5x faster here than scipy's, breaks them differently from it).
    """
    if not np.isfinite(points).all():
        raise ValueError("nearest_raw_rows: points must be finite (the preprocessed scan's)")
    finite = np.flatnonzero(np.isfinite(raw_points).all(axis=1))
    if len(finite) == 0 or len(points) == 0:
        return None if len(finite) == 0 else np.zeros(0, np.int64)
    import small_gicp

    raw = np.ascontiguousarray(raw_points[finite], np.float64)
    j, _ = small_gicp.KdTree(raw, num_threads=1).batch_nearest_neighbor_search(
        np.ascontiguousarray(points, np.float64), num_threads=1)
    return finite[np.asarray(j, np.int64)]


def source_intensity(raw_points: np.ndarray, raw_intensity: np.ndarray | None, points: np.ndarray,
                     rows: np.ndarray | None = None) -> np.ndarray:
    """Intensity of the raw point nearest to each of ``points`` (zeros without intensity);
    ``rows``: :func:`nearest_raw_rows` of them when already known."""
    if raw_intensity is None or len(raw_points) == 0 or len(points) == 0:
        return np.zeros(len(points), np.float32)
    if rows is None:
        rows = nearest_raw_rows(raw_points, points)
    if rows is None:
        return np.zeros(len(points), np.float32)
    return np.asarray(raw_intensity, np.float32)[rows]


class DensifiedSequence:
    """Lazy view of ``parent`` whose frames are the densified scans S+_k (module docstring).

    Frames may be read from several threads at once (``concurrent_reads``; the SLAM reader's
    ``data.read_threads``): the parent is read under a lock, the network's input split is seeded
    by ``training.seed`` and each frame's sampling by ``(training.seed, frame index)``, and the
    counters are locked, so a frame is the same whatever thread reads it and in whatever order.
    """

    concurrent_reads = True

    def __init__(self, parent: LidarSequence, predictor: Predictor, training_cfg: TrainingConfig,
                 preprocess: PreprocessConfig | None = None, keep_predictions: int = 16) -> None:
        self.parent = parent
        self.predictor = predictor
        self.cfg = training_cfg
        self.preprocess = preprocess or PreprocessConfig()
        self.name = f"{parent.name}-densified"
        self.timestamps = parent.timestamps
        self.gt_poses = parent.gt_poses
        self.T_cam_velo = parent.T_cam_velo
        inherit_sweep_attributes(self, parent)
        self.fallbacks: dict[int, str] = {}
        # index -> (preprocessed, kept, output, with covariances, horizontal among them, horizontal among kept)
        self._n_points: dict[int, tuple[int, int, int, int, int, int]] = {}
        self._lock = threading.Lock()
        self._parent_lock = threading.Lock()
        self._position: dict[int, int] = {}  # frame.index -> position in the parent, of every frame read
        self.n_recomputed = 0  # predictions recomputed for frames no longer kept (loop edges)
        self.recomputed_failures = 0
        self.keep_predictions = keep_predictions
        # index -> (preprocessed points, their covariances, their sweep fractions or None)
        self._predicted: OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = OrderedDict()
        self._recomputed_times: tuple[int, np.ndarray | None] | None = None  # the last recomputed frame's

    def __len__(self) -> int:
        return len(self.parent)

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]

    def _record(self, index: int, n_pre: int, n_kept: int, n_out: int, reason: str | None,
                n_horizontal: tuple[int, int, int] = (0, 0, 0)) -> None:
        with self._lock:
            self._n_points[index] = (n_pre, n_kept, n_out, *n_horizontal)
            if reason is not None:
                if index not in self.fallbacks:
                    log.warning("densify frame %d: %s", index, FALLBACK_REASONS[reason])
                self.fallbacks[index] = reason

    def stats(self) -> dict[str, Any]:
        """Counts over the frames read so far: fallbacks per reason, mean points per stage, and the
        share of horizontal surfaces (:func:`horizontal_surfaces`) among the points with
        covariances and among the points the anisotropy filter kept."""
        with self._lock:
            n = np.array(list(self._n_points.values()), dtype=np.float64).reshape(-1, 6)
            return {
                "frames": len(n),
                "fallbacks": dict(sorted(Counter(self.fallbacks.values()).items())),  # not in reading order
                "fallback_frames": sorted(self.fallbacks),
                "mean_preprocessed_points": float(n[:, 0].mean()) if len(n) else 0.0,
                "mean_kept_points": float(n[:, 1].mean()) if len(n) else 0.0,
                "mean_output_points": float(n[:, 2].mean()) if len(n) else 0.0,
                "kept_fraction": float(n[:, 1].sum() / max(n[:, 0].sum(), 1.0)),
                "horizontal_fraction_input": float(n[:, 4].sum() / max(n[:, 3].sum(), 1.0)),
                "horizontal_fraction_kept": float(n[:, 5].sum() / max(n[:, 1].sum(), 1.0)),
            }

    def predicted(self, index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """``(points (N, 3), C (N, 3, 3))`` the network gave for frame ``index`` (the preprocessed
        scan), if it is among the ``keep_predictions`` frames computed last and its covariances
        were finite; else None."""
        with self._lock:
            kept = self._predicted.get(int(index))
        return None if kept is None else (kept[0], kept[1])

    def prediction_times(self, index: int) -> np.ndarray | None:
        """Sweep fractions of the points of :meth:`prediction` for frame ``index``: the per-point time
        of the raw point nearest to each (as densified points get theirs); None when the frame has no
        per-point times or was never read through this view. The frame loop deskews the predictions
        with them as it deskewed the frame (:class:`gr_graph.frame_loop.FrameDeskewer`)."""
        with self._lock:
            kept = self._predicted.get(int(index))
            position = self._position.get(int(index))
            recomputed = self._recomputed_times
        if kept is not None:
            return kept[2]
        if recomputed is not None and recomputed[0] == int(index):  # made with :meth:`prediction` just before
            return recomputed[1]
        if position is None:
            return None
        with self._parent_lock:
            raw = self.parent[position]
        scan = preprocess_scan(raw.points, self.preprocess, index=int(raw.index))
        return _source_times(raw, scan.points) if scan.usable else None

    def prediction(self, index: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Like :meth:`predicted`, but a frame that is no longer kept is predicted again.

        The loop edges of the learning rounds need the covariances of a frame read hundreds of
        frames earlier. The prediction is deterministic (the predictor is seeded and the
        preprocessing is the one of :meth:`__getitem__`), so the recomputed covariances are the
        ones densification used. ``index`` is ``frame.index`` of a frame of this view (the key
        of :meth:`predicted`). Returns None for a frame never read through this view (logged),
        or when the scan is unusable or the covariances are not finite and positive definite
        (counted in :attr:`recomputed_failures`).
        """
        kept = self.predicted(index)
        if kept is not None:
            return kept
        with self._lock:
            position = self._position.get(int(index))
        if position is None:  # never read through this view: nothing to predict again
            log.warning("prediction: frame %d was never read from this view; no covariances", index)
            return None
        with self._parent_lock:
            raw = self.parent[position]
        scan = preprocess_scan(raw.points, self.preprocess, index=int(raw.index))
        C, problem = self._predict(scan.points) if scan.usable else (None, "unusable_scan")
        failed = problem is not None or C.shape != (len(scan.points), 3, 3)
        times = _source_times(raw, scan.points) if scan.usable and not failed else None
        with self._lock:
            self.n_recomputed += 1
            self.recomputed_failures += int(failed)
            self._recomputed_times = (int(index), times)  # :meth:`prediction_times` asks next (deskewed frames)
        if not scan.usable:
            return None
        if failed:
            log.warning("frame %d: recomputed covariances are not finite and positive definite", index)
            return None
        return scan.points, C

    def _predict(self, points: np.ndarray) -> tuple[np.ndarray, str | None]:
        """The predictor's covariances of ``points`` and :func:`covariance_problem` of them (a
        predictor raising ``FloatingPointError`` counts as non-finite output)."""
        try:
            C = np.asarray(self.predictor(points), np.float64)
        except FloatingPointError as exc:
            log.debug("predictor: %s", exc)
            return np.full((len(points), 3, 3), np.nan), "nonfinite_covariance"
        return C, covariance_problem(C) if C.shape == (len(points), 3, 3) else None

    def _keep(self, index: int, points: np.ndarray, C: np.ndarray, times: np.ndarray | None) -> None:
        with self._lock:
            self._predicted[index] = (points, C, times)
            self._predicted.move_to_end(index)
            while len(self._predicted) > max(int(self.keep_predictions), 0):
                self._predicted.popitem(last=False)

    def __getitem__(self, i: int) -> LidarFrame:
        with self._parent_lock:  # :meth:`prediction` may read the parent from another thread
            raw = self.parent[i]
        idx = int(raw.index)
        with self._lock:
            self._position[idx] = int(i)
        cfg = self.cfg
        scan = preprocess_scan(raw.points, self.preprocess, index=idx)
        if not scan.usable:
            self._record(idx, len(scan.points), 0, len(raw.points), "unusable_scan")
            return raw
        s = scan.points
        res = densify_points(s, self.predictor, cfg, seed=[cfg.seed, idx], index=idx)
        if res.fallback in COVARIANCE_FALLBACKS:
            self._record(idx, len(s), 0, len(raw.points), res.fallback)
            return raw
        # every output point takes the intensity and per-point time of the raw point nearest to its source
        # point: learning rounds deskew with the sensor's times like round 0, not with azimuth-guessed ones
        # (and the predictions with the same times, for the learned edge noise)
        rows = nearest_raw_rows(raw.points, s) if raw.time is not None and len(raw.points) else None
        source_time = None if rows is None else np.asarray(raw.time, np.float64)[rows]
        # only covariances densify accepted (finite, positive definite)
        self._keep(idx, s, res.input_covariances, source_time)
        horizontal = horizontal_surfaces(res.input_covariances)
        n_horizontal = (len(s), int(horizontal.sum()), int((horizontal & res.kept).sum()))
        if not cfg.densify:  # ablation (training.densify: false): raw scans, predictions kept for the edge noise
            self._record(idx, len(s), res.n_kept, len(raw.points), None, n_horizontal)
            return raw
        self._record(idx, len(s), res.n_kept, len(res.points), res.fallback, n_horizontal)
        if rows is None and raw.intensity is not None and len(raw.points):
            rows = nearest_raw_rows(raw.points, s)
        intensity = source_intensity(raw.points, raw.intensity, s, rows)[res.source]
        time = None if source_time is None else source_time[res.source]
        return LidarFrame(index=idx, timestamp=raw.timestamp, points=np.ascontiguousarray(res.points, np.float64),
                          intensity=intensity.astype(np.float32), ring=None, n_rings=raw.n_rings,
                          dropped_nonfinite=raw.dropped_nonfinite, time=time)


def densified_sequence(sequence: LidarSequence, checkpoint: Any, training_cfg: TrainingConfig | None = None,
                       device: str = "cpu", preprocess: PreprocessConfig | None = None,
                       keep_predictions: int = 16) -> DensifiedSequence:
    """The lazy densified view of ``sequence`` (see the module docstring).

    Parameters
    ----------
    sequence : LidarSequence
        The raw scans.
    checkpoint : path, CovarianceNet or callable
        The trained f_theta (``model.pt`` from ``training.train.train_from_memory``), or a
        callable ``points (N, 3) -> (N, 3, 3)``.
    training_cfg : TrainingConfig
        ``tau_ani``, ``samples_per_point``, ``seed``, ``keep_original``, ``keep_dropped``, ``min_kept_points``.
    device : str
        Device of the network.
    preprocess : PreprocessConfig
        Must be the preprocessing of the memory the network was trained on (default: defaults).
    keep_predictions : int
        How many of the most recently computed frames keep their points and covariances
        (:meth:`DensifiedSequence.predicted`).
    """
    cfg = training_cfg or TrainingConfig()
    predictor = _make_predictor(checkpoint, device, cfg.seed, full_passes=cfg.prediction_passes == "training_size")
    return DensifiedSequence(sequence, predictor, cfg, preprocess, keep_predictions)


def densify_cloud(points: np.ndarray, weights: Any = "pretrained", *, intensity: np.ndarray | None = None,
                  tau_ani: float | None = None, samples_per_point: int | None = None,
                  keep_original: bool | None = None, keep_dropped: bool | None = None, seed: int = 0,
                  device: str = "cpu",
                  preprocess: PreprocessConfig | None = None) -> DensifiedPoints:
    """Densify one point cloud with a trained network (Algorithm 2, as the learning rounds do).

    The cloud is preprocessed as SLAM preprocesses a scan (range crop around the origin,
    voxel downsampling: the network's training input), the network predicts a covariance per
    point, and each point with anisotropy above ``tau_ani`` gains ``samples_per_point`` samples of
    ``N(s_i, C_i)`` (with ``keep_original`` / ``keep_dropped`` false, the paper's Algorithm 2: the
    samples replace the point, and the points under the threshold are dropped). Frame 0 of
    :func:`densified_sequence` with the same settings (and ``training.prediction_passes: split``,
    the default) gives the same points.

    Example::

        from gr_graph.densify import densify_cloud
        dense = densify_cloud(points)   # the shipped weights; or weights="runs/slam/round_1/training/model.pt"
        dense.points, dense.covariances   # (M, 3) and (M, 3, 3)

    Parameters
    ----------
    points : (N, 3) or (N, >=4) array
        The cloud in its sensor frame (a 4th column is taken as intensity when ``intensity``
        is not given). Non-finite rows are dropped.
    weights : "pretrained", path, CovarianceNet or callable
        ``"pretrained"`` (default: the model shipped with gr_graph, :mod:`gr_graph.pretrained`),
        or a ``model.pt`` written by ``python -m training.train`` or by a ``gr_graph.slam
        --rounds`` run (``round_<r>/training/model.pt``); checked on load
        (:func:`training.trainer.load_model`).
    intensity : (N,) array, optional
        Per-point intensity; each output point gets its source point's (nearest raw point).
    tau_ani, samples_per_point, keep_original, keep_dropped : optional
        Override ``training.tau_ani``, ``training.samples_per_point`` (M),
        ``training.keep_original``, ``training.keep_dropped`` of :class:`gr_graph.config.TrainingConfig`.
    seed : int
        Seeds the network's input split and the sampling (same seed, same output).
    device : str
        Device of the network.
    preprocess : PreprocessConfig, optional
        Must match the preprocessing of the memory the network was trained on (default: the
        defaults of :class:`gr_graph.config.PreprocessConfig`).

    Returns
    -------
    DensifiedPoints
        ``points`` (M, 3), ``covariances`` (M, 3, 3), ``intensity`` (M,) when the input had
        intensity, and ``fallback``: None, or ``"few_kept"`` (too few points passed the
        filter: the output is the preprocessed cloud, logged as a warning).

    Raises
    ------
    ValueError
        If ``points`` is not (N, >=3), or fewer than ``preprocess.min_points`` points remain
        after preprocessing.
    FloatingPointError
        If the network's covariances are non-finite or not positive definite.
    """
    if weights is None:
        raise ValueError("densify_cloud: weights is required ('pretrained', or a model.pt from `python -m "
                         "training.train` or from a gr_graph.slam --rounds run: round_<r>/training/model.pt)")
    x = np.asarray(points)
    if x.ndim != 2 or x.shape[1] < 3:
        raise ValueError(f"densify_cloud: points must be (N, 3) or (N, >=4), got {x.shape}")
    if intensity is None and x.shape[1] >= 4:
        intensity = x[:, 3]
    if intensity is not None:
        intensity = np.asarray(intensity, np.float32).reshape(-1)
        if len(intensity) != len(x):
            raise ValueError(f"densify_cloud: {len(intensity)} intensities for {len(x)} points")
        bad = ~np.isfinite(intensity)
        if bad.any():  # as the file readers do: 0, counted
            log.warning("densify_cloud: %d non-finite intensities set to 0", int(bad.sum()))
            intensity = np.where(bad, np.float32(0.0), intensity)
    xyz = np.asarray(x[:, :3], np.float64)
    pre = preprocess or PreprocessConfig()
    updates = {k: v for k, v in (("tau_ani", tau_ani), ("samples_per_point", samples_per_point),
                                 ("keep_original", keep_original), ("keep_dropped", keep_dropped))
               if v is not None}
    cfg = TrainingConfig(seed=seed, **updates)  # pydantic checks the ranges (ValueError)
    scan = preprocess_scan(xyz, pre, index=0)
    if not scan.usable:
        raise ValueError(f"densify_cloud: only {len(scan.points)} points left after preprocessing "
                         f"(range {pre.min_range}-{pre.max_range} m, voxel {pre.voxel_size} m; at least "
                         f"{pre.min_points} needed)")
    res = densify_points(scan.points, _make_predictor(weights, device, seed), cfg, seed=[seed, 0], index=0)
    if res.fallback in COVARIANCE_FALLBACKS:
        raise FloatingPointError("densify_cloud: the network's covariances are non-finite or not positive definite")
    if res.fallback is not None:
        log.warning("densify_cloud: %s (%d of %d points passed tau_ani=%g)", FALLBACK_REASONS[res.fallback],
                    res.n_kept, len(res.network_input), cfg.tau_ani)
    inten = None if intensity is None else source_intensity(xyz, np.asarray(intensity), res.network_input)[res.source]
    return DensifiedPoints(res.points, res.source, res.network_input, res.input_covariances, res.kept, res.fallback,
                           inten)
