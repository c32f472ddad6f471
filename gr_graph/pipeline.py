"""The SLAM pipeline F_SLAM and the reciprocal rounds around it (Algorithm 3 of the paper).

``SlamPipeline(cfg).run()``: round 0 is SLAM on the raw scans (odometry, loop closures,
pose graph, marginals, memory; :func:`gr_graph.frame_loop.run_slam`); each learning round
r ≥ 1 trains f_θ on the memory of round r−1 into ``round_<r>/training``
(:func:`training.train.train_from_memory`), densifies the scans with it
(:mod:`gr_graph.densify`) and runs SLAM again on the densified scans, with the odometry
edges' information from the network's covariances (:mod:`gr_graph.edge_noise`,
``training.edge_noise``). The rounds stop early when the trajectory moves less than
``training.convergence_delta`` (mean position change).

Acceptance: every learning round is tested against the last accepted round without ground
truth (:mod:`gr_graph.round_acceptance`, ``training.acceptance``); its summary carries
``accepted`` and ``acceptance`` (the test's figures). After a rejected round the rounds stop (the
next round would train on the rejected round's memory) unless ``training.stop_on_reject`` is
false (the harness's unguarded rounds: later rounds are then tested against the last accepted
one). The run's final trajectory, the last round of the unbroken run of accepted rounds (round 0
when round 1 is rejected), is copied to
``poses_kitti.txt`` / ``poses_tum.txt`` at the top of ``--out`` and named in ``metrics.json``
(``final_round``).

In rounds r ≥ 1 SLAM preprocesses with ``training.slam_voxel_size`` if set, and the memory
stores round 0's raw downsampled scans (not the densified ones: Algorithm 2 returns
M+ = (S_k, T̂+, C+), so the next training sees the input densification saw), with T̂ and
correspondences from round r's trajectory (:mod:`gr_graph.memory_builder`).

Outputs: :mod:`gr_graph.round_output`.

Resume: a rerun with the same ``--out`` skips every round whose ``round.json`` exists and
whose ``config_fingerprint`` (:func:`round_fingerprint`: a hash of the options the round
depends on) equals the current one; a round with a missing or different ``round.json`` is
recomputed, with everything after it. A finished round also records the identity of its input
(``data_fingerprint``, :func:`data_fingerprint`: the number of frames and, for data read from files
(or a synthetic world rendered along a given pose file: its timestamps and poses),
a hash of the files' names and sizes, the first and last 64 KiB of the first, middle and last
file, the timestamps, ground truth and
calibration): when the data at the same path changed (scans replaced, deleted or added), the rerun
refuses to resume (:class:`ResumeDataError`, before anything is written) and asks for a new ``--out``
or ``--no-resume``. The synthetic world has no files: its identity is its configuration (and its
number of frames). A ``round.json`` written before the data fingerprint existed is taken as it is. Finished rounds are re-judged (the test is cheap and
deterministic), so a rerun with a changed ``training.acceptance`` re-decides without recomputing. An unfinished round's training resumes from its
checkpoint unless an earlier round was recomputed (the memory changed).
``output.resume: false`` recomputes all rounds.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from gr_graph.atomic import atomic_write_bytes
from gr_graph.config import GraphConfig, SlamConfig, dump_config
from gr_graph.covariance_health import covariance_failures
from gr_graph.datasets.base import LidarSequence, find_in_chain, release_render_cache, velo_to_cam_poses
from gr_graph.datasets.frame_cache import CachedFrames, makes_frames, remove_stale_frame_cache
from gr_graph.datasets.stamp_gaps import motion_times
from gr_graph.folder_lock import FolderBusyError, folder_lock
from gr_graph.datasets.synthetic.render_process import RenderProcessSequence
from gr_graph.densify import DensifiedSequence, densified_sequence
from gr_graph.edge_noise import LearnedEdgeNoise, registration_edge_noise_summary
from gr_graph.frame_loop import SlamResult, StageTimer, UnusableScansError, frames_read_ahead, run_slam
from gr_graph.map_export import map_path
from gr_graph.memory import load_memory
from gr_graph.memory_builder import EDGE_H_DESCRIPTION, build_memory
from gr_graph.noise_consistency import round_noise_consistency
from gr_graph.round_output import (
    plot_metrics_rounds,
    plot_round,
    read_round_poses,
    read_round_summary,
    round_dir,
    round_summary,
    trajectory_summary,
    write_metrics,
    write_round_map,
    write_round_results,
    write_round_summary,
)
from gr_graph.trajectory import write_kitti_poses
from training.config import ADDED_TRAIN_OPTIONS

log = logging.getLogger(__name__)

#: what a run writes at the top of ``--out`` as its summary: removed when a run starts (written again by it)
RUN_SUMMARY_FILES = ("poses_kitti.txt", "poses_tum.txt", "metrics.json", "trajectory.png", "rounds.png")

__all__ = ["OUT_LOCK", "OutBusyError", "ResumeDataError", "SlamPipeline", "data_fingerprint", "round_fingerprint"]


class ResumeDataError(RuntimeError):
    """A finished round in ``--out`` was made from other data than the run's (resume refused)."""


class OutBusyError(FolderBusyError):
    """Another process runs into the same ``--out`` (it holds :data:`OUT_LOCK`)."""


#: the lock file a run holds in its ``--out`` (hidden; it stays, naming its last owner)
OUT_LOCK = ".gr_graph.lock"


#: ``data`` options that change how frames are read, never what is read: in no fingerprint or cache key.
READ_OPTIONS = {"prefetch", "frame_cache", "read_threads", "render_process"}
# path of an option (sections, then its key) -> the default it had in effect before it existed; at that
# value it is left out of the round fingerprint
_ADDED_OPTIONS: dict[tuple[str, ...], Any] = {("graph", "loop_variance"): "fixed", ("training", "keep_dropped"): False,
                                              ("graph", "ground_tilt_offset"): False,
                                              ("graph", "registration_covariance"): "scaled_hessian",
                                              **{("graph", k): GraphConfig.model_fields[k].default
                                                 for k in ("cluster_size", "min_clusters")},
                                              ("odometry", "map_keyframe_translation"): 0.0,
                                              ("odometry", "map_keyframe_rotation_deg"): 0.0,
                                              ("loops", "min_path_length"): 0.0, ("loops", "sc_height_offset"): 2.0,
                                              ("training", "prediction_passes"): "split",
                                              ("training", "learned_noise_outlier_alpha"): 0.0,
                                              ("training", "learned_noise_covariance"): "hessian",
                                              ("sensor", "rotation"): "clockwise",
                                              ("sensor", "sweep_start_azimuth_deg"): 180.0,
                                              ("sensor", "frame_stamp"): None,
                                              **{("training", "trainer", k): v for k, v in ADDED_TRAIN_OPTIONS.items()}}

# added options of the learned edge noise: left out of the fingerprint with ``edge_noise: registration``, where they
# do nothing (only these: the older ones stay, so that finished rounds of that ablation keep their fingerprint)
_LEARNED_NOISE_ADDED = ("learned_noise_outlier_alpha", "learned_noise_covariance")

# sensor options whose default became None (guessed from the data) after runs were published: None
# hashes as the value the default was, so that rounds finished before stay finished
_GUESSED_SENSOR_DEFAULTS: dict[str, str] = {"time_unit": "s", "time_reference": "sweep_start"}


def round_fingerprint(cfg: SlamConfig, r: int, guessed: Mapping[str, str] | None = None) -> str:
    """Hash of the options round ``r``'s result depends on.

    Round 0 does not depend on the ``training`` section or the device; no round depends on
    the number of rounds, the convergence threshold or the acceptance test (so ``--rounds 2``
    after ``--rounds 1`` reuses both finished rounds; a changed test re-judges finished rounds),
    nor on output options. Options added after runs were published (:data:`_ADDED_OPTIONS`:
    ``graph.loop_variance``, ``training.keep_dropped``, ``graph.registration_covariance`` and its two
    options, ``graph.ground_tilt_offset``, ``odometry.map_keyframe_*``, ``loops.min_path_length`` and ``sc_height_offset``,
    ``sensor.rotation``, ``sweep_start_azimuth_deg`` and ``frame_stamp``, ``training.prediction_passes`` and
    ``learned_noise_outlier_alpha`` and ``learned_noise_covariance``; the trainer's
    :data:`training.config.ADDED_TRAIN_OPTIONS`) count only when they are not at their default
    (``learned_noise_outlier_alpha`` and ``learned_noise_covariance`` not at all with ``training.edge_noise:
    registration``, where they do nothing),
    so that rounds finished before the option existed stay finished; ``sensor.time_unit``
    and ``time_reference``, whose default became None (guessed), hash None as what the data's
    conventions guessed (``guessed``, :func:`guessed_sensor_options`: a recording's time unit),
    else as their former defaults (``s``, ``sweep_start``). So a unit guessed as ``ns`` and one set
    to ``ns`` hash alike, and one set to ``s`` does not, while a guessed ``s`` hashes as before.
    ``time_reference`` is judged frame by frame when unset, so it has no one guessed value: unset
    still hashes as ``sweep_start`` (a given reference also turns times beyond the sweep into
    errors, so a wrong one rarely finishes a round).
    """
    if r == 0:
        d = cfg.model_dump(mode="json", exclude={"output": True, "data": READ_OPTIONS, "training": True,
                                                 "device": True})
    else:
        d = cfg.model_dump(mode="json", exclude={"output": True, "data": READ_OPTIONS,
                                                 "training": {"rounds", "convergence_delta", "acceptance",
                                                              "stop_on_reject", "weights", "fine_tune"}})
        tc = cfg.training
        if tc.weights is not None and tc.covariances == "network":  # the file's content, not its name
            from gr_graph.pretrained import weights_sha256

            d["weights_sha256"] = weights_sha256(tc.weights)
            d["fine_tune"] = tc.fine_tune
    if r > 0 and d["training"].get("edge_noise") != "learned":  # the learned edge noise's added options do nothing
        for key in _LEARNED_NOISE_ADDED:
            d["training"].pop(key, None)
    for (*sections, key), default in _ADDED_OPTIONS.items():
        node = d
        for section in sections:
            node = node.get(section, {})
        if key in node and node[key] == default:
            node.pop(key)
    for key, before in _GUESSED_SENSOR_DEFAULTS.items():  # None (guessed): what was guessed, or the former default
        if d.get("sensor", {}).get(key, before) is None:
            d["sensor"][key] = (guessed or {}).get(key, before)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def guessed_sensor_options(sequence: Any) -> dict[str, str]:
    """The ``sensor`` options the data's field conventions guessed where the section left them None,
    for :func:`round_fingerprint`: ``time_unit`` of a recording whose per-point times are used
    (:class:`~gr_graph.datasets.frame_fields.FieldConventions`); empty for data without them (KITTI,
    the synthetic world). ``time_reference`` is guessed frame by frame and is left out."""
    from gr_graph.datasets.frame_fields import FieldConventions
    from gr_graph.sensors import TIME_UNITS

    owner = find_in_chain(sequence, "conventions", accept=lambda v: isinstance(v, FieldConventions))
    if owner is None or not (owner.conventions.has_time and owner.conventions.use_time):
        return {}
    unit = next((name for name, s in TIME_UNITS.items() if s == owner.conventions.time_unit_s), None)
    return {} if unit is None else {"time_unit": unit}


#: files of a ROS2 bag folder that hold its data (storage and metadata)
ROS2_BAG_SUFFIXES = (".db3", ".mcap", ".yaml", ".zstd")


def _input_files(sequence: Any) -> list[Path] | None:
    """The files a sequence reads its frames from (of the sequence or the first of its ``parent``
    chain that has them): a loader's ``files`` (folders, KITTI), a bag's ``path`` (the file, or
    the files of a ROS2 bag folder); None for made frames (the synthetic world)."""
    seen: set[int] = set()
    while sequence is not None and id(sequence) not in seen:
        seen.add(id(sequence))
        files = getattr(sequence, "files", None)
        if isinstance(files, (list, tuple)) and all(isinstance(f, (str, Path)) for f in files):
            return [Path(f) for f in files]
        path = getattr(sequence, "path", None)
        if isinstance(path, (str, Path)):
            path = Path(path)
            if not path.is_dir():
                return [path]
            # a ROS2 bag folder: its storage files and metadata, not e.g. a Finder's .DS_Store
            return sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith(".")
                          and p.suffix.lower() in ROS2_BAG_SUFFIXES)
        sequence = getattr(sequence, "parent", None)
    return None


#: bytes read from each end of the sampled files of :func:`data_fingerprint`
FINGERPRINT_SAMPLE_BYTES = 65536


def _file_sample(path: Path, size: int) -> bytes:
    """The first and last :data:`FINGERPRINT_SAMPLE_BYTES` of a file (b"" when unreadable)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(FINGERPRINT_SAMPLE_BYTES)
            if size > 2 * FINGERPRINT_SAMPLE_BYTES:
                fh.seek(size - FINGERPRINT_SAMPLE_BYTES)
            return head + fh.read(FINGERPRINT_SAMPLE_BYTES)
    except OSError:
        return b""


def data_fingerprint(sequence: LidarSequence) -> dict[str, Any]:
    """The identity of a run's input, cheap to compute (no frame decoded).

    Returns
    -------
    dict
        ``n_frames``; ``files`` (how many files the frames come from, None for made frames: the
        synthetic world, whose identity is its configuration) and ``digest`` (None for made frames,
        but for a synthetic world rendered along a given pose file: a hash of its timestamps and poses),
        a hash of the files' names and sizes, the first and last 64 KiB of the first, middle and
        last file (data swapped for another drive with files of the same sizes, e.g. organized
        clouds, differ there), the sequence's timestamps, ground truth and ``T_cam_velo``, and the names
        and sizes of per-point time files read beside the scans (KITTI layout's ``times/``).
        Modification times are left out: data copied elsewhere (a cluster's scratch disk) is the
        same data. A file that cannot be read counts as size -1. Files whose stamps lie off the
        sensor's beat add ``stamps_off_beat``, how many the motion model moves
        (:func:`gr_graph.datasets.stamp_gaps.motion_times`), so that rounds made before it did are not
        resumed beside rounds made after.
    """
    files = _input_files(sequence)
    if files is None:
        # made frames are their configuration, but for a synthetic world rendered along a given pose file
        # (data.trajectory), whose content the configuration names only by its path
        if find_in_chain(sequence, "trajectory", accept=lambda v: isinstance(v, str)) is None:
            return {"n_frames": len(sequence), "files": None, "digest": None}
        h = hashlib.sha256()
        _hash_arrays(h, sequence, ("timestamps", "gt_poses"))
        return {"n_frames": len(sequence), "files": None, "digest": h.hexdigest()[:16]}
    h = hashlib.sha256()
    sizes = []
    for f in files:
        try:
            size = f.stat().st_size
        except OSError:
            size = -1
        sizes.append(size)
        h.update(f"{f.name}\0{size}\n".encode())
    for k in sorted({0, len(files) // 2, len(files) - 1} if files else set()):
        h.update(_file_sample(files[k], sizes[k]))
    _hash_arrays(h, sequence, ("timestamps", "gt_poses", "T_cam_velo"))
    time_files = find_in_chain(sequence, "time_files", accept=lambda v: isinstance(v, list))
    if time_files is not None:  # per-point times beside the scans (a KITTI-layout raw export): deskewed with them
        for f in time_files.time_files:
            h.update(f"time\0{f.name}\0{f.stat().st_size if f.is_file() else -1}\n".encode())
    out: dict[str, Any] = {"n_frames": len(sequence), "files": len(files), "digest": h.hexdigest()[:16]}
    stamps = getattr(sequence, "timestamps", None)
    off_beat = 0 if stamps is None else len(motion_times(stamps, log_moves=False).moved)
    if off_beat:  # the motion model moves them (since 2026-12-07): rounds made before used them as they were
        out["stamps_off_beat"] = off_beat
    return out


def _without(d: dict[str, Any], key: str) -> dict[str, Any]:
    return {k: v for k, v in d.items() if k != key}


def _hash_arrays(h: Any, sequence: Any, names: tuple[str, ...]) -> None:
    """Feed ``h`` each named array of ``sequence`` (its name, then its float64 bytes when it has one)."""
    for name in names:
        value = getattr(sequence, name, None)
        h.update(name.encode())
        if value is not None:
            h.update(np.ascontiguousarray(value, np.float64).tobytes())


def check_learning_config(cfg: SlamConfig) -> None:
    """Fail fast (before round 0) when a learning round could not run: ``--device cuda`` where
    torch has no CUDA device, no memory to train on, an invalid trainer configuration, or
    ``training.weights`` missing, broken or made for another network configuration.

    Raises
    ------
    ValueError, FileNotFoundError, training.trainer.TrainingError
        With a message naming the option or the weights file.
    """
    tc = cfg.training
    if cfg.device == "cuda":  # torch only then (the learning rounds import it anyway)
        from training.trainer import require_device

        require_device(cfg.device)
    if (tc.fine_tune or tc.acceptance.enabled) and not cfg.output.write_memory:
        raise ValueError("learning rounds train on the memory of the previous round, and the acceptance test reads "
                         "round 0's scans from it: output.write_memory must be true")
    # the trainer's run configuration is built (and validated) here, before round 0, not after it
    train_cfg = tc.trainer_config(cfg.device, False)
    if tc.weights is not None and tc.covariances == "network":
        from gr_graph.pretrained import resolve_weights
        from training.trainer import load_model  # imports torch: only when weights are given

        path = resolve_weights(tc.weights)
        net = load_model(path).config.to_dict()
        if tc.fine_tune and net != train_cfg.net.to_dict():
            raise ValueError(f"--weights {tc.weights} ({path}): its network configuration {net} differs from "
                             f"training.trainer.net {train_cfg.net.to_dict()}; fine-tuning needs the same network "
                             "(set training.trainer.net to the checkpoint's, or use --densify)")


class SlamPipeline:
    """``python -m gr_graph.slam`` as an object: ``SlamPipeline(cfg).run()``.

    Parameters
    ----------
    cfg : SlamConfig
    sequence : LidarSequence, optional
        Use this sequence instead of opening ``cfg.data`` (tests, notebooks). A sequence the
        pipeline opens itself has its render cache (the synthetic town, about 2 GB) freed once
        each round has read its frames; a given sequence is left as it is.
    source_description : str, optional
        One line saying where the data come from (logged and stored in metrics.json).

    See the module docstring for the rounds and the resume rule.
    """

    def __init__(self, cfg: SlamConfig, sequence: LidarSequence | None = None,
                 source_description: str | None = None) -> None:
        self.cfg = cfg
        self.out = Path(cfg.output.out_dir)
        self.owns_sequence = sequence is None  # opened here: its render cache is freed after each round
        if sequence is None:
            from gr_graph.datasets.registry import open_configured_sequence

            sequence, source_description = open_configured_sequence(cfg.data, synthetic_seed=cfg.seed,
                                                                    sensor=cfg.sensor)
        self.sequence: LidarSequence = sequence
        self.data_fingerprint = data_fingerprint(sequence)
        self.guessed_sensor = guessed_sensor_options(sequence)  # hashed for options left None
        self.frame_cache = self._open_frame_cache(sequence)
        if self.frame_cache is not None:
            self.sequence = self.frame_cache
        self.keep_frame_cache = False  # the harness reads the frames again after run() (KISS-ICP baseline)
        self.resumed_rounds: list[int] = []  # rounds the last run() took from --out instead of computing them
        self.source_description = source_description or sequence.name
        self.gt = self._anchored_gt()
        self._raw_scans: list[np.ndarray] | None = None  # round 0's scans (memory-mapped), for the acceptance test

    def round_fingerprint(self, r: int) -> str:
        """:func:`round_fingerprint` of round ``r`` under this run's configuration and data."""
        return round_fingerprint(self.cfg, r, self.guessed_sensor)

    def _open_frame_cache(self, sequence: LidarSequence) -> CachedFrames | None:
        """The on-disk frame cache ``<out>/frames`` (``data.frame_cache``,
        :mod:`gr_graph.datasets.frame_cache`), or None when it is off."""
        use = self.cfg.data.frame_cache
        if use is None:
            use = self.cfg.training.rounds > 0 and makes_frames(sequence)
        if not use:
            return None
        d = self.cfg.model_dump(mode="json", include={"data", "sensor", "seed"},
                                exclude={"data": READ_OPTIONS})
        from gr_graph import __version__
        from gr_graph.provenance import git_state

        code = [__version__, git_state()["commit"]]  # the renderer may change between commits
        identity = [d, sequence.name, len(sequence), code]
        if self.data_fingerprint["digest"] is not None:  # frames read from files: the files' identity too
            identity.append(self.data_fingerprint["digest"])
        key = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:16]
        return CachedFrames(sequence, self.out / "frames", key, open_now=False)  # opened by run(), after the checks

    def remove_frame_cache(self) -> None:
        """Delete ``<out>/frames`` (the end of :meth:`run`, unless ``keep_frame_cache``; the
        harness calls it after its baseline read the frames). A run without a cache of its own
        deletes one an earlier, interrupted run left there (gigabytes on the full route), when the
        folder holds nothing but cache files (logged)."""
        if self.frame_cache is not None:
            self.frame_cache.remove()
        elif remove_stale_frame_cache(self.out / "frames"):
            log.info("%s: removed the frame cache an earlier, interrupted run left", self.out / "frames")

    def provenance(self) -> dict[str, Any]:
        """Commit, packages, seeds, threads and device of this run (``metrics.json["provenance"]``)."""
        from gr_graph.provenance import provenance

        cfg = self.cfg
        return provenance(seeds={"world": cfg.seed, "training": cfg.training.seed}, device=cfg.device,
                          num_threads=cfg.odometry.num_threads)

    def run(self) -> dict[str, Any]:
        """Run round 0 and the learning rounds; write every output; return the metrics dict. One run
        at a time in an ``--out``: the run holds ``<out>/.gr_graph.lock`` (:data:`OUT_LOCK`,
        :func:`gr_graph.folder_lock.folder_lock`).

        Raises
        ------
        OutBusyError
            Another process runs into the same ``--out`` (nothing is written).
        ResumeDataError
            Resuming into an ``--out`` whose finished rounds were made from other data
            (:meth:`check_resume`; nothing is written).
        gr_graph.frame_loop.UnusableScansError
            Too few scans usable for a trajectory (:meth:`slam_round`; no round is finished and
            neither ``metrics.json`` nor the final poses are written).
        """
        with folder_lock(self.out / OUT_LOCK, f"--out {self.out}", OutBusyError):
            return self._run_locked()

    def _run_locked(self) -> dict[str, Any]:
        """:meth:`run` once its ``--out`` is held."""
        self.check_resume()
        if self.frame_cache is not None:
            self.frame_cache.open()
        self.prepare()
        metrics: dict[str, Any] = {"source": self.source_description, "n_frames": len(self.sequence),
                                   "data_fingerprint": self.data_fingerprint,
                                   "channels": self.cfg.channels, "sensor": self.cfg.sensor.model,
                                   "provenance": self.provenance(),
                                   "rounds": {}}
        previous_poses, recomputed, reference = None, False, 0
        self.resumed_rounds = []
        for r in range(self.cfg.training.rounds + 1):
            summary = None if recomputed else self.finished_round(r)
            if summary is None:
                summary = self.compute_round(r, resume_training=self.cfg.output.resume and not recomputed)
                recomputed = True
            else:
                self.resumed_rounds.append(r)
            metrics["rounds"][str(r)] = summary
            accepted = self.judge(r, reference, metrics["rounds"])
            poses = read_round_poses(self.round_dir(r))
            converged = previous_poses is not None and self.converged(r, summary, previous_poses, poses)
            write_metrics(self.out, metrics)  # after converged() added trajectory_change to the summary
            if not accepted:
                if self.cfg.training.stop_on_reject:
                    metrics["stopped"] = f"round {r} rejected by the acceptance test: no further rounds"
                    log.warning("round %d rejected: the learning rounds stop here (the final trajectory is an "
                                "accepted round's)", r)
                    break
                log.warning("round %d rejected; training.stop_on_reject is false: the rounds go on (later rounds are "
                            "tested against round %d)", r, reference)
            else:
                reference = r
            if converged:
                metrics["stopped"] = (f"round {r} converged: the trajectory moved {summary['trajectory_change']:.4g} m "
                                      f"< training.convergence_delta {self.cfg.training.convergence_delta:g} m")
                break
            previous_poses = poses
        if self.frame_cache is not None:
            metrics["frame_cache"] = self.frame_cache.stats()
        renderer = find_in_chain(self.sequence, "release_cache")
        if isinstance(renderer, RenderProcessSequence):  # frames served by it and its peak memory
            metrics["render_process"] = renderer.stats()
        self.write_final(metrics)
        if not self.keep_frame_cache:
            self.remove_frame_cache()
        self.write_figures(metrics)
        return metrics

    # -------------------------------------------------------------- steps of run()
    def prepare(self) -> None:
        """Check the learning rounds' configuration, write ``config.yaml`` and the ground truth."""
        if self.cfg.training.rounds > 0:
            self.check_learning_config()
        # an earlier run's final trajectory, metrics and figures, even when every round resumes: written again
        # (metrics.json after each round), and never left beside this run's config.yaml when this run stops;
        # only where an earlier run wrote (its config.yaml or round 0), not in a folder of the user's own
        if (self.out / "config.yaml").is_file() or (self.out / "round_0").is_dir():
            for name in RUN_SUMMARY_FILES:
                (self.out / name).unlink(missing_ok=True)
        self.out.mkdir(parents=True, exist_ok=True)
        dump_config(self.cfg, self.out / "config.yaml")
        # One line on where the data comes from; a fallback to synthetic data is a warning.
        is_synthetic = "synthetic" in self.source_description
        log.log(logging.WARNING if is_synthetic else logging.INFO, "data: %s", self.source_description)
        if self.gt is not None:
            write_kitti_poses(self.out / "gt_poses_kitti.txt", velo_to_cam_poses(self.gt, self.sequence.T_cam_velo))
        else:  # an earlier run's ground truth (e.g. --poses given then) must not score this run's poses
            (self.out / "gt_poses_kitti.txt").unlink(missing_ok=True)

    def check_learning_config(self) -> None:
        """Fail fast (before round 0) when a learning round could not run (:func:`check_learning_config`)."""
        check_learning_config(self.cfg)

    def check_resume(self) -> None:
        """Refuse to resume (before anything is written) when a round that would be skipped was
        made from other data than this run's (:meth:`finished_round`)."""
        if not self.cfg.output.resume:
            return
        for r in range(self.cfg.training.rounds + 1):
            summary = read_round_summary(self.round_dir(r))
            if summary is None or summary.get("config_fingerprint") != self.round_fingerprint(r):
                return  # recomputed, with every round after it
            self.check_round_data(r, summary)

    def check_round_data(self, r: int, summary: dict[str, Any]) -> None:
        """Raise :class:`ResumeDataError` when finished round ``r`` (its ``summary``) was made from
        other data than this run's (:func:`data_fingerprint`); a summary without a data fingerprint
        (written before it existed) passes."""
        stored = summary.get("data_fingerprint")
        if stored is None:
            log.info("round %d: round.json has no data fingerprint (written before it existed); the data are taken "
                     "to be unchanged", r)
            return
        now = self.data_fingerprint
        if stored == now:
            return
        made = now["files"] is None and stored.get("files") is None  # made frames: no files
        if made and stored.get("n_frames") == now["n_frames"] and stored.get("digest") is None:
            log.info("round %d: round.json has no digest of the synthetic world's pose file (written before it was "
                     "kept); the poses are taken to be unchanged", r)
            return
        if stored.get("n_frames") != now["n_frames"]:
            what = f"{stored.get('n_frames')} frames then, {now['n_frames']} now"
        elif stored.get("files") != now["files"]:
            what = f"{stored.get('files')} files then, {now['files']} now"
        elif made:
            what = "the same number of frames, but the poses of the pose file it is rendered along differ"
        elif _without(stored, "stamps_off_beat") == _without(now, "stamps_off_beat"):
            what = (f"the same files, but {now.get('stamps_off_beat', 0)} of their frame stamps lie off the sensor's "
                    "beat, which the odometry's guess and the deskewing move back onto it since 2026-12-07 "
                    f"({stored.get('stamps_off_beat', 0)} when the round was made)")
        else:
            what = ("the same number of frames, but the files differ (names, sizes or sampled content) or their "
                    "timestamps, ground truth or calibration do")
            moved = float(getattr(self.sequence, "stamps_moved_by_s", 0.0) or 0.0)
            if moved:
                what += (f"; these data's stamps and ground truth are moved {moved:+.4g} s to the sweeps' middles, "
                         "which runs made before 2026-12-06 did not do (nor, before 2026-12-07, by this much for "
                         "bags stamped with their log times or folders whose first scan is a start-up fragment)")
        raise ResumeDataError(
            f"{self.round_dir(r)}: round {r} is finished but was made from other data than {self.source_description} "
            f"({what}); its results would not belong to these data. Use a new --out, or --no-resume (output.resume: "
            f"false) to recompute every round into {self.out}")

    def finished_round(self, r: int) -> dict[str, Any] | None:
        """The summary of round ``r`` if it is finished with the current configuration and data
        (resume; other data: :class:`ResumeDataError`)."""
        if not self.cfg.output.resume:
            return None
        summary = read_round_summary(self.round_dir(r))
        if summary is None:
            return None
        if summary.get("config_fingerprint") != self.round_fingerprint(r):
            log.info("round %d: existing results were made with another configuration; recomputing", r)
            return None
        self.check_round_data(r, summary)
        if self.memory_needed(r) and not (self.round_dir(r) / "memory" / "meta.json").is_file():
            log.warning("round %d: finished in %s but without its memory (a run with --no-memory, or pruned), which "
                        "the learning rounds need: recomputing", r, self.round_dir(r))
            return None
        log.info("round %d: already finished in %s; skipped (resume)", r, self.round_dir(r))
        return summary

    def memory_needed(self, r: int) -> bool:
        """Whether this run reads round ``r``'s memory: round r + 1 trains on it (:meth:`trains`)
        unless it is finished with this configuration; the acceptance test reads round 0's scans, and
        so does every learning round that writes its memory (it stores round 0's scans)."""
        rounds = self.cfg.training.rounds
        if r >= rounds:
            return False
        if r == 0 and self.cfg.training.acceptance.enabled:
            return True
        if r == 0 and self.cfg.output.write_memory and any(not self._finished_as_configured(k)
                                                           for k in range(1, rounds + 1)):
            return True  # a learning round to compute stores round 0's scans in its memory
        if not self.trains(r + 1):
            return False
        return not self._finished_as_configured(r + 1)

    def _finished_as_configured(self, r: int) -> bool:
        """Whether round ``r`` has a summary made with the current configuration (resume)."""
        summary = read_round_summary(self.round_dir(r))
        return summary is not None and summary.get("config_fingerprint") == self.round_fingerprint(r)

    def trains(self, r: int) -> bool:
        """Whether learning round ``r`` trains a network (on round r − 1's memory): not with PCA
        covariances, nor in round 1 with given weights used as they are (:meth:`densified_scans`)."""
        tc = self.cfg.training
        return tc.covariances != "pca" and not (r == 1 and tc.weights is not None and not tc.fine_tune)

    def compute_round(self, r: int, resume_training: bool) -> dict[str, Any]:
        """Round 0: SLAM on the raw scans; round r ≥ 1: train, densify, SLAM on the densified scans.
        Every later round's ``round.json`` is removed first: made from another round ``r``, it must
        not be resumed after an interruption (kept were a later run's rounds spliced onto this one).
        (The final trajectory at the top of ``--out`` is removed when :meth:`run` starts: written
        again at its end, it must not stay beside a new ``config.yaml`` when this run fails.)"""
        for later in sorted(self.out.glob("round_*/round.json")):
            k = later.parent.name.removeprefix("round_")
            if k.isdigit() and int(k) > r:
                later.unlink()
        if r == 0:
            return self.slam_round(0)
        t0 = time.perf_counter()
        densified = self.densified_scans(r, resume_training)
        return self.slam_round(r, densified, train_seconds=time.perf_counter() - t0)

    def judge(self, r: int, reference: int, summaries: dict[str, dict[str, Any]]) -> bool:
        """Round ``r``'s ``accepted`` (and, for r ≥ 1, ``acceptance``: the GT-free test against
        round ``reference``, :mod:`gr_graph.round_acceptance`) in its summary and ``round.json``.

        Round 0 is accepted by definition; with ``training.acceptance.enabled: false`` every round is.
        """
        summary = summaries[str(r)]
        ac = self.cfg.training.acceptance
        if r == 0 or not ac.enabled:
            if summary.get("accepted") is not True or "acceptance" in summary:  # e.g. a verdict of before
                summary["accepted"] = True                                       # the test was disabled
                summary.pop("acceptance", None)
                write_round_summary(self.round_dir(r), summary)
            return True
        from gr_graph.round_acceptance import evaluate_round

        if self._raw_scans is None:  # memory-mapped views of round 0's scans: read per window, not held in RAM
            self._raw_scans = load_memory(self.round_dir(0) / "memory").scans()
        verdict = json.loads(json.dumps(evaluate_round(self.out, r, reference, summaries, ac, scans=self._raw_scans)))
        stored = json.dumps([summary.get("accepted"), summary.get("acceptance")], sort_keys=True)
        if stored != json.dumps([verdict["accepted"], verdict], sort_keys=True):  # (NaN != NaN: compare text)
            summary["accepted"] = bool(verdict["accepted"])
            summary["acceptance"] = verdict
            write_round_summary(self.round_dir(r), summary)  # the round's folder says whether it was accepted
        return summary["accepted"]

    def write_final(self, metrics: dict[str, Any]) -> None:
        """The run's final trajectory at the top of ``--out``: the last round of the unbroken run
        of accepted rounds (:func:`gr_graph.round_acceptance.guarded_round`; round 0 when round 1
        was rejected), ``poses_kitti.txt`` and ``poses_tum.txt`` (atomic copies);
        ``metrics["final_round"]`` names it and ``metrics["final_round_reason"]`` says why."""
        from gr_graph.round_acceptance import accepted_flags, guarded_round

        rounds = metrics["rounds"]
        flags = accepted_flags(rounds)
        accepted = sorted(k for k, ok in flags.items() if ok)
        final, reason = guarded_round(flags)
        if not self.cfg.training.acceptance.enabled:
            reason = "acceptance test disabled: the last round"
        rd = self.round_dir(final)
        for name in ("poses_kitti.txt", "poses_tum.txt"):
            atomic_write_bytes(self.out / name, (rd / name).read_bytes())
        metrics["final_round"] = final
        metrics["final_round_reason"] = reason
        metrics["accepted_rounds"] = accepted
        metrics["rejected_rounds"] = sorted(k for k, ok in flags.items() if not ok)
        metrics["marginals_fallback_rounds"] = sorted(
            int(k) for k, s in rounds.items() if (s.get("marginals") or {}).get("status", "ok") != "ok")
        write_metrics(self.out, metrics)
        log.info("final trajectory: round %d (%s) -> %s", final, reason, self.out / "poses_kitti.txt")

    def converged(self, r: int, summary: dict[str, Any], previous: np.ndarray, poses: np.ndarray) -> bool:
        """Record ``trajectory_change`` (mean position change) in ``summary``; whether it is below delta."""
        change = float(np.mean(np.linalg.norm(poses[:, :3, 3] - previous[:, :3, 3], axis=1)))
        summary["trajectory_change"] = change
        if change < self.cfg.training.convergence_delta:
            log.info("round %d: trajectory moved %.4f m < delta: converged", r, change)
            return True
        return False

    def write_figures(self, metrics: dict[str, Any]) -> None:
        """``trajectory.png`` (the final round) and, with learning rounds, ``rounds.png`` (``output.plot``).

        An earlier run's figure that this run does not draw is removed (it would be taken for this
        run's). A figure that cannot be drawn is logged, removed, and named in ``metrics.json``
        (``figures_failed``): the poses and metrics are written already, and a finished run does not
        fail on a picture."""
        figures: dict[str, Callable[[], Any]] = {}
        if self.cfg.output.plot:
            figures["trajectory.png"] = lambda: self.plot(metrics["final_round"])
            if len(metrics["rounds"]) > 1:
                figures["rounds.png"] = lambda: plot_metrics_rounds(
                    self.out, metrics, title=f"gr_graph learning rounds: {self.sequence.name}, {len(self.sequence)} frames")
        for name in {"trajectory.png", "rounds.png"} - set(figures):
            (self.out / name).unlink(missing_ok=True)
        failed: dict[str, str] = {}
        for name, draw in figures.items():
            try:
                draw()
            except Exception as exc:  # noqa: BLE001 (any plotting error)
                log.warning("%s could not be drawn (%s: %s); the run's poses and metrics are written", self.out / name,
                            type(exc).__name__, exc)
                (self.out / name).unlink(missing_ok=True)
                failed[name] = f"{type(exc).__name__}: {exc}"
        if failed:
            metrics["figures_failed"] = failed
            write_metrics(self.out, metrics)

    def plot(self, r: int) -> None:
        """``trajectory.png``: round ``r`` against the ground truth, with its position ellipses."""
        name = self.sequence.name
        plot_round(self.round_dir(r), self.out / "trajectory.png", self.gt,
                   title=f"gr_graph round {r}: {name}, {len(self.sequence)} frames, "
                         f"{self.cfg.channels} channels, {self.cfg.sensor.model}")

    # -------------------------------------------------------------- one round
    def round_dir(self, r: int) -> Path:
        return round_dir(self.out, r)

    def kept_predictions(self) -> int:
        """How many frames' covariances a densified view keeps for the learned edge noise: more
        than the SLAM reader can have read ahead (:func:`gr_graph.frame_loop.frames_read_ahead`)."""
        return max(16, frames_read_ahead(self.cfg.data.prefetch, self.cfg.data.read_threads) + 8)

    def densified_scans(self, r: int, resume_training: bool) -> DensifiedSequence:
        """Algorithm 3, one iteration, up to the SLAM call: train f_θ on the memory of round
        r−1 (Algorithm 1), then densify every scan with it (Algorithm 2, lines 3-9).

        Training goes to ``round_<r>/training`` (``model.pt``, ``checkpoint.pt``, log); round 1
        starts from ``training.weights`` when given (with ``training.fine_tune`` false it uses
        them without training), rounds r ≥ 2 from round r−1's ``model.pt`` (``training.warm_start``). An existing
        checkpoint is resumed only if ``resume_training`` (round r−1 was not recomputed in
        this run); a checkpoint it cannot continue (:class:`training.trainer.CheckpointMismatch`) restarts training.
        """
        from training.train import train_from_memory  # imports torch: only when a learning round runs
        from training.trainer import CheckpointMismatch

        tc = self.cfg.training
        if tc.covariances == "pca":  # ablation: no network, no training
            from gr_graph.pca_covariances import PcaCovariances

            pca = PcaCovariances(self.cfg.preprocess.num_neighbors, tc.trainer.net.eps)
            return densified_sequence(self.sequence, pca, tc, device=self.cfg.device, preprocess=self.cfg.preprocess,
                                      keep_predictions=self.kept_predictions())
        init = None
        if r == 1 and tc.weights is not None:
            from gr_graph.pretrained import resolve_weights

            init = resolve_weights(tc.weights)
            log.info("round 1 %s the weights %s", "starts from" if tc.fine_tune else "uses, without training,", init)
            if not tc.fine_tune:  # --densify: the given weights as they are
                return densified_sequence(self.sequence, init, tc, device=self.cfg.device,
                                          preprocess=self.cfg.preprocess,
                                          keep_predictions=self.kept_predictions())
        if r >= 2 and tc.warm_start:
            init = self.round_dir(r - 1) / "training" / "model.pt"
            if not init.is_file():
                raise FileNotFoundError(f"round {r}: warm start needs {init} (round {r - 1}'s model)")
        train_cfg = tc.trainer_config(self.cfg.device, self.cfg.output.progress, init)
        memory, train_dir = self.round_dir(r - 1) / "memory", self.round_dir(r) / "training"
        try:
            ckpt = train_from_memory(memory, train_dir, train_cfg, resume=resume_training)
        except CheckpointMismatch as exc:  # another configuration or data, more epochs, an unreadable file
            log.warning("round %d: %s; training restarts from scratch", r, exc)
            ckpt = train_from_memory(memory, train_dir, train_cfg, resume=False)
        # predictions are kept longer than the reader runs ahead, for the learned edge noise
        return densified_sequence(self.sequence, ckpt, tc, device=self.cfg.device, preprocess=self.cfg.preprocess,
                                  keep_predictions=self.kept_predictions())

    def slam_round(self, r: int, densified: DensifiedSequence | None = None,
                   train_seconds: float | None = None) -> dict[str, Any]:
        """Run F_SLAM on the raw scans (round 0) or on ``densified`` (rounds r ≥ 1) and write
        round ``r``'s outputs (:mod:`gr_graph.round_output`); return its summary."""
        cfg = self.cfg
        rd = self.round_dir(r)
        rd.mkdir(parents=True, exist_ok=True)
        (rd / "round.json").unlink(missing_ok=True)
        if (rd / "memory").exists():  # an earlier configuration's: never left for a later round to train on
            shutil.rmtree(rd / "memory")
            if r == 0:
                self._raw_scans = None
        map_path(rd).unlink(missing_ok=True)  # nor its map for --viz (written again when output.map is on)
        t0 = time.perf_counter()
        edge_noise = self.edge_noise(densified)
        try:
            res = run_slam(self.sequence if densified is None else densified, self.slam_config(r),
                           desc=f" round {r}", edge_noise=edge_noise)
        except UnusableScansError as exc:  # nothing of the round is written: no trajectory of guesses
            if not any(rd.iterdir()):
                rd.rmdir()
            raise UnusableScansError(f"round {r}: data {self.source_description}: {exc}", exc.n_usable,
                                     exc.n_frames) from exc
        if self.owns_sequence and release_render_cache(self.sequence):  # outputs and training read no frames
            log.info("round %d: every frame read; the synthetic town is freed (rebuilt if frames are read again)", r)
        mean_points = float(np.mean([len(s) for s in res.scans])) if res.scans else 0.0
        T_cv = np.asarray(self.sequence.T_cam_velo, np.float64)
        timer = StageTimer()
        with timer("output"):
            write_round_results(rd, res, T_cv, self.gt)
        map_counts = None
        if cfg.output.map.enabled:
            with timer("map"):
                try:
                    map_counts = write_round_map(rd, res, cfg.output.map.voxel_size)
                    # what the map's points are: a learning round's densified scans hold samples of N(s, C)
                    map_counts["scans"] = ("densified (samples of the network's covariances included)"
                                           if densified is not None and cfg.training.densify else "measured")
                except (OSError, ValueError) as exc:  # a view of the result: never lose the round over it
                    log.error("round %d: the map %s was not written: %s", r, map_path(rd), exc)
                    map_counts = {"error": f"{map_path(rd)}: {type(exc).__name__}: {exc}"}
        if cfg.output.write_memory:
            with timer("memory"):
                self.write_memory(r, res)
        summary = round_summary(r, res, self.round_fingerprint(r), mean_points, self.data_fingerprint)
        if map_counts is not None:
            summary["map"] = map_counts
        if densified is not None:
            summary["densify"] = densified.stats()
            summary["edge_noise"] = registration_edge_noise_summary() if edge_noise is None else edge_noise.summary()
            en = summary["edge_noise"]
            trained = r > 1 or cfg.training.fine_tune or cfg.training.weights is None  # else no training this round
            summary["covariance_failures"] = covariance_failures(
                summary["densify"], rd / "training" / "summary.json" if trained else None, en)
            log.info("round %d: %d odometry edges with learned information H(C) (%d floored), %d fallbacks %s",
                     r, en["n_learned"], en["n_floored"], en["n_fallback"], en["fallbacks"])
        if self.gt is not None:
            summary.update(trajectory_summary(res, self.gt, T_cv, cfg.loops.min_frame_gap, cfg.loops.min_path_length))
            if res.covariances is not None:  # NEES of edges and marginals against ground truth
                try:
                    summary["noise_consistency"] = round_noise_consistency(rd, summary.get("marginals"),
                                                                           cfg.graph.min_information_eigenvalue)
                except Exception as exc:  # a diagnostic: never lose the round over it
                    log.warning("round %d: noise consistency not computed (%s: %s)", r, type(exc).__name__, exc)
                    summary["noise_consistency"] = {"error": f"{type(exc).__name__}: {exc}"}
        runtime = {**res.runtime, **timer.seconds}
        runtime["total"] = time.perf_counter() - t0
        if train_seconds is not None:
            runtime["training"] = train_seconds  # not in "total" (the SLAM round); densification is in "read"
        summary["runtime_s"] = runtime
        summary["frames_per_second"] = len(res.poses) / max(runtime["total"], 1e-9)
        write_round_summary(rd, summary)
        return summary

    def slam_config(self, r: int) -> SlamConfig:
        """The configuration SLAM runs with in round ``r`` (``training.slam_voxel_size`` in rounds r ≥ 1)."""
        if r == 0 or self.cfg.training.slam_voxel_size is None:
            return self.cfg
        return self.cfg.model_copy(update={"preprocess": self.cfg.preprocess.model_copy(
            update={"voxel_size": self.cfg.training.slam_voxel_size})})

    def edge_noise(self, densified: DensifiedSequence | None) -> LearnedEdgeNoise | None:
        """The learned edge noise of a learning round (``training.edge_noise: learned``), else None."""
        if densified is None or self.cfg.training.edge_noise != "learned":
            return None
        return LearnedEdgeNoise(densified.prediction, self.cfg)

    def write_memory(self, r: int, res: SlamResult) -> None:
        """``round_<r>/memory``; rounds r ≥ 1 store round 0's scans (module docstring)."""
        scans = None
        if r > 0:
            raw = load_memory(self.round_dir(0) / "memory")
            if raw.n_scans != len(res.scans):
                raise RuntimeError(f"round {r}: round 0 memory has {raw.n_scans} scans, this round {len(res.scans)}")
            scans = raw.scans()  # memory-mapped views, no copy in RAM
            del raw
        info = {"round": r, "channels": self.cfg.channels, "sensor": self.cfg.sensor.model,
                "source": self.source_description, "edge_H": EDGE_H_DESCRIPTION}
        build_memory(res, self.cfg, info=info, scans=scans, directory=self.round_dir(r) / "memory")

    def _anchored_gt(self) -> np.ndarray | None:
        gt = self.sequence.gt_poses
        if gt is None:
            return None
        gt = np.asarray(gt, np.float64)[: len(self.sequence)]
        return np.linalg.inv(gt[0]) @ gt
