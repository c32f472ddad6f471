"""Configuration of the SLAM pipeline: pydantic sections, YAML loading and dumping.

Every section has conservative, fast defaults. A run's configuration is the defaults,
overridden by a YAML file (``--config``), overridden by command-line options; the
resolved configuration is written as ``config.yaml`` next to every result.

Sections
--------
data        which sequence, where, how many channels, which frames
sensor      the LiDAR that took the scans (gr_graph.sensors.SensorConfig): beams, vertical field of
            view, rings / per-point times in the data and their units, scan period
preprocess  range crop and voxel downsampling (the stored scans are the downsampled ones)
odometry    the VGICP front end (small_gicp) and its failure detection
loops       loop-closure candidates (proximity, Scan Context) and geometric verification
graph       the gtsam pose graph: noise models, robust kernel, optimiser, marginals
output      what is written and where
training    the learning rounds (Algorithm 3): training, densification, convergence
"""

from __future__ import annotations

import os
import types
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from gr_graph.atomic import atomic_write_text
from gr_graph.config_errors import describe_validation_error
from gr_graph.config_yaml import read_config_file
from gr_graph.sensors import SensorConfig, SensorError, loop_rmse_threshold
from training.config import RUN_KEYS, TrainConfig, TrainOptions


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class DataConfig(_Section):
    """Which frames to run on."""

    seq: str = "00"
    data_root: str | None = Field(None, description="KITTI odometry root; None: env GR_GRAPH_KITTI_ROOT or synthetic")
    dataset: Literal["auto", "kitti", "kitti_raw", "folder", "rosbag", "synthetic"] = Field(
        "auto", description="kind of data: auto guesses it from data.path (without a path: KITTI when a root "
        "is found, else synthetic); kitti_raw: a raw drive; folder: .bin/.pcd/.ply/.npy scans; rosbag: ROS1/ROS2 "
        "bag or MCAP")
    path: str | None = Field(None, description="the data to run on (bag, folder of scans, KITTI raw drive or "
                             "odometry root); None: data_root / synthetic")
    topic: str | None = Field(None, description="bags: the sensor_msgs/PointCloud2 topic (needed when there "
                              "are several)")
    timestamps: str | None = Field(None, description="folders of scans: file of one timestamp (s) a scan; None: "
                                   "times.txt/timestamps.txt next to the scans, else 0.1 s apart")
    poses: str | None = Field(None, description="folders of scans and bags: ground-truth LiDAR poses, KITTI "
                              "(12 columns) or TUM (8), one a scan; None: poses.txt next to the scans")
    channels: Literal[64, 32, 16] | None = Field(
        None, description="rings kept: every 1st, 2nd or 4th of a 64-beam sensor (sensor.n_beams == 64 only); "
        "None: all the sensor's beams")
    frames: tuple[int, int] | None = Field(None, description="half-open frame range [A, B)")
    prefetch: int = Field(4, ge=0, description="frames read (rendered) ahead in a worker thread; 0: none")
    read_threads: int = Field(
        2, ge=1, description="worker threads reading ahead where a sequence's frames can be made concurrently (the "
        "densified scans of the learning rounds: the network pass of each frame); other sequences read in one. "
        "Changes no result (each frame's densification is seeded by its index)")
    render_process: bool | None = Field(
        None, description="synthetic worlds: render the frames in a separate process, ahead of the reads (ray casting "
        "and the SLAM would otherwise take turns holding Python's GIL); the same frames. None: on when 500 frames or "
        "more are read. Other sequences ignore it")
    frame_cache: bool | None = Field(
        None, description="keep every frame read in <out>/frames (uncompressed: ~1 MB a 16-channel frame, 3.6 MB a "
        "64-channel one; deleted when the run ends; never filling the disk past 2 GB free) so that the learning rounds read it back instead of making it again; None: on for "
        "sequences that make their frames (synthetic worlds) when learning rounds run, off for recordings")
    point_format: Literal["xyzi", "xyz"] = Field(
        "xyzi", description="KITTI .bin layout: float32 x,y,z,intensity (16 bytes a point) or x,y,z (12 bytes)"
    )
    kitti_vertical_correction_deg: float = Field(
        0.0, ge=-2.0, le=2.0, description="raise every point's elevation (any data: KITTI folders and raw drives, the synthetic sequence, folders, bags) "
        "by this angle (HDL-64E vertical-angle error; KISS-ICP 1.3.0 uses 0.205, published values 0.195-0.22; the "
        "kitti/raw presets have 0.22); 0: off (any KITTI-layout folder, synthetic exports included, is read unchanged)"
    )
    route_seed: int = Field(0, ge=0, description="synthetic sequence: seed of the generated route")
    trajectory: str | None = Field(None, description="synthetic sequence: render along this KITTI/TUM "
                                   "pose file or KITTI root instead of the generated route")
    synthetic_preset: Literal["clean", "kitti", "raw"] | None = Field(
        None, description="synthetic sequence: the world and its sensor (clean: plain town, ideal sensor, "
        "for unit tests; kitti: residential world with moving actors and KITTI-like sensor errors; raw: kitti with "
        "the full motion distortion); None: the sequence's default (kitti)")

    @field_validator("seq", mode="before")
    @classmethod
    def _yaml_sequence_number(cls, v: Any) -> Any:
        """YAML reads an unquoted ``00`` or ``05`` as an integer: taken as the two-digit KITTI sequence."""
        return f"{v:02d}" if isinstance(v, int) and not isinstance(v, bool) and v >= 0 else v

    @field_validator("frames", mode="before")
    @classmethod
    def _parse_frames(cls, v: Any) -> Any:
        from gr_graph.datasets.registry import parse_frames

        if isinstance(v, str):
            return parse_frames(v)
        if isinstance(v, (list, tuple)) and len(v) == 2:
            return parse_frames(tuple(v))
        return v  # None, or a type pydantic rejects


class PreprocessConfig(_Section):
    """Per-scan preprocessing, done once per scan."""

    min_range: float = Field(2.5, ge=0.0, description="drop points closer than this (car body) [m]")
    max_range: float = Field(100.0, gt=0.0, description="drop points farther than this [m]")
    voxel_size: float = Field(0.5, gt=0.0, description="voxel downsampling; the stored scans use it [m]")
    num_neighbors: int = Field(10, ge=5, description="neighbours for the per-point GICP covariances")
    min_points: int = Field(100, ge=10, description="fewer points after preprocessing: the scan is unusable")

    @model_validator(mode="after")
    def _range_not_empty(self) -> PreprocessConfig:
        if self.min_range >= self.max_range:
            raise ValueError(f"min_range {self.min_range:g} m is not below max_range {self.max_range:g} m: no point "
                             "would be kept")
        return self


class OdometryConfig(_Section):
    """VGICP front end (small_gicp) with a constant-velocity initial guess."""

    mode: Literal["map", "scan"] = Field(
        "map", description="'map': new scan onto a sliding local voxel map; 'scan': onto the previous scan only"
    )
    voxel_resolution: float = Field(1.0, gt=0.0, description="VGICP voxel size of the target map [m]")
    map_horizon: int = Field(20, ge=1, description="'map' mode: voxels unseen for this many map insertions are "
                             "dropped (every scan is one, unless map keyframes leave scans out)")
    map_keyframe_translation: float = Field(
        0.0, ge=0.0, description="'map' mode: a scan enters the target map only when it moved at least this far "
        "[m] or turned at least map_keyframe_rotation_deg since the last scan that entered; a threshold of 0 is "
        "not used, 0 and 0: every scan (a stopped vehicle then fills the map with one ring pattern, which holds "
        "the registrations at motion start back: benchmarks/results/findings.md, Odometry at motion start)"
    )
    map_keyframe_rotation_deg: float = Field(
        0.0, ge=0.0, description="'map' mode: see map_keyframe_translation [deg]"
    )
    max_correspondence_distance: float = Field(1.0, gt=0.0)
    max_iterations: int = Field(30, ge=1)
    num_threads: int = Field(
        1, ge=1, description="threads of small_gicp's preprocessing and registration; more than 1 is faster but "
        "not reproducible: the downsampled points come back in another order on every run, so runs differ in "
        "the last bits (the published runs use 1)")
    min_inlier_ratio: float = Field(0.3, ge=0.0, le=1.0, description="below: registration failed")
    max_deviation_translation: float = Field(
        2.0, gt=0.0, description="result further than this from the constant-velocity guess: diverged [m]"
    )
    max_deviation_rotation_deg: float = Field(15.0, gt=0.0)
    corr_max_distance: float = Field(1.0, gt=0.0, description="memory correspondences: max NN distance [m]")
    deskew: Literal["auto", "on", "off"] = Field(
        "auto", description="constant-velocity motion compensation of each raw scan to mid-sweep before "
        "preprocessing; 'auto': on for sequences whose scans are not motion-compensated (motion_compensated=False: "
        "raw drives, data with per-point times, the synthetic 'raw' variant), off for KITTI odometry folders"
    )
    deskew_scan_period: float | None = Field(
        None, gt=0.0, description="sweep duration [s]; None: the sequence's scan_period, else the frame spacing"
    )

    @field_validator("deskew", mode="before")
    @classmethod
    def _yaml_on_off(cls, v: Any) -> Any:
        """YAML 1.1 reads an unquoted ``on`` / ``off`` as a boolean: taken as the word meant."""
        return {True: "on", False: "off"}.get(v, v) if isinstance(v, bool) else v


class LoopConfig(_Section):
    """Loop closures: candidates, descriptor, verification."""

    enabled: bool = True
    check_every: int = Field(5, ge=1, description="look for a loop at every n-th frame")
    min_frame_gap: int = Field(100, ge=1, description="candidates are at least this many frames older")
    min_path_length: float = Field(
        0.0, ge=0.0, description="candidates also lie at least this much path back along the estimate [m]; 0: off. "
        "A vehicle stopped for longer than min_frame_gap frames otherwise closes loops with itself (gr_graph."
        "loop_closure.newest_candidate)")
    radius: float = Field(10.0, gt=0.0, description="proximity candidates within this distance on the estimate [m]")
    use_proximity: bool = True
    use_scan_context: bool = True
    sc_rings: int = Field(20, ge=2)
    sc_sectors: int = Field(60, ge=4)
    sc_max_radius: float = Field(80.0, gt=0.0)
    sc_height_offset: float = Field(
        2.0, description="Scan Context bins hold the highest z + this [m], heights below 0 count as 0: about the "
        "sensor's height above the ground, z pointing up (a sensor mounted higher: raise it)")
    sc_num_candidates: int = Field(10, ge=1, description="ring-key nearest neighbours rescored by the full descriptor")
    sc_threshold: float = Field(0.2, gt=0.0, description="Scan Context distance below which a candidate is kept")
    coarse_correspondence_distance: float = Field(5.0, gt=0.0, description="verification, first stage [m]")
    max_correspondence_distance: float = Field(1.0, gt=0.0, description="verification, final stage [m]")
    min_inlier_ratio: float = Field(0.6, ge=0.0, le=1.0, description="fraction of source points within 1 m")
    max_rmse: float | None = Field(
        None, gt=0.0, description="RMSE of inlier distances, final stage [m]; None: from the sensor's ring spacing, "
        "0.35 * (s / s_HDL64) ** 0.25 with s = vertical field of view / rings kept (gr_graph.sensors."
        "loop_rmse_threshold; HDL-64E: 0.350 / 0.416 / 0.495 at 64 / 32 / 16 channels, VLP-16 0.51, OS1-64 0.40)"
    )
    max_correction: float = Field(
        30.0, gt=0.0, description="reject when verification moves the guess further than this [m]"
    )
    cooldown: int = Field(3, ge=0, description="after an accepted loop, skip this many checks")
    reoptimize_every: int = Field(50, ge=1, description="re-optimise the graph after new loops, at most every n frames")


class GraphConfig(_Section):
    """Pose graph and its noise models."""

    prior_sigma: float = Field(1e-4, gt=0.0, description="prior on the first pose (all 6 dof)")
    odometry_noise: Literal["hessian", "fixed"] = "hessian"
    hessian_scale: float = Field(
        0.1, gt=0.0, description="multiplies the variance-factor-scaled registration Hessian (correlated points)"
    )
    min_information_eigenvalue: float = Field(1e-2, gt=0.0, description="floor on information eigenvalues")
    registration_covariance: Literal["scaled_hessian", "cluster_robust"] = Field(
        "scaled_hessian", description="information of registered edges (odometry and loops, where no learned noise "
        "replaces it): 'scaled_hessian' hessian_scale * H / sigma0^2; 'cluster_robust' the inverse of the sandwich "
        "covariance H^-1 M H^-1 from the residual gradients summed over cubes of cluster_size "
        "(gr_graph.registration_covariance; no hessian_scale)")
    cluster_size: float = Field(12.0, gt=0.0, description="cluster_robust (registration_covariance or "
                                "training.learned_noise_covariance): side of the cubes whose residuals may be "
                                "correlated [m]")
    min_clusters: int = Field(20, ge=7, description="cluster_robust: fewer clusters with correspondences fall back "
                              "to scaled_hessian, or for the learned noise to H(C) (counted in the round summary); at "
                              "least 7, the 6x6 spread of the cluster sums has rank at most their number")
    fixed_sigmas: tuple[float, float, float, float, float, float] = (0.002, 0.002, 0.002, 0.05, 0.05, 0.05)
    fallback_sigmas: tuple[float, float, float, float, float, float] = (0.05, 0.05, 0.05, 1.0, 1.0, 1.0)
    loop_kernel: Literal["cauchy", "huber", "none"] = "cauchy"
    loop_kernel_k: float = Field(2.3849, gt=0.0, description="kernel threshold in whitened units")
    loop_variance: Literal["fixed", "estimated", "estimated_axes"] = Field(
        "fixed", description="loop edges' information: 'fixed' as registered (and calibrated); 'estimated' divided "
        "by the loops' variance factor from the graph's residuals, odometry held fixed; 'estimated_axes' that, then "
        "one more factor per tangent axis (roll, pitch, yaw, x, y, z) shared by all loops that only weakens them "
        "where an axis' residuals need it (gr_graph.noise_calibration)")
    ground_tilt_offset: bool = Field(
        False, description="widen every registered edge's covariance (odometry and loops) by its ground-tilt offset: "
        "the roll and pitch correction that would map the source scan's ground plane onto the target's, rank one "
        "(gr_graph.ground_tilt); the registrations' pull towards equal sensor attitude, which their residuals "
        "cannot show")
    max_iterations: int = Field(100, ge=1)
    relative_error_tol: float = Field(1e-6, gt=0.0)
    marginals: bool = True


class MapOutputConfig(_Section):
    """The optimised map of each round (``round_<r>/map.ply``, :mod:`gr_graph.map_export`)."""

    enabled: bool = Field(True, description="write the scans placed with the final trajectory as a PLY map")
    voxel_size: float = Field(0.2, gt=0.0, description="voxel of the map: one point (the centroid) per voxel [m]")


class OutputConfig(_Section):
    """What is written."""

    out_dir: str = "runs/slam"
    plot: bool = True
    map: MapOutputConfig = MapOutputConfig()
    write_memory: bool = True
    resume: bool = Field(True, description="skip rounds whose round.json exists and whose config matches")
    progress: bool = True

    @field_validator("out_dir")
    @classmethod
    def _expand_home(cls, v: str) -> str:
        """``~/runs/x`` means the home folder's, not a folder named ``~`` (as the data paths)."""
        return os.path.expanduser(v)


class AcceptanceConfig(_Section):
    """GT-free acceptance test of learning rounds (:mod:`gr_graph.round_acceptance`)."""

    enabled: bool = Field(True, description="test each learning round; a rejected round stops the rounds")
    n_windows: int = Field(60, ge=1, description="local maps (windows) spread evenly over the run")
    half_window: int = Field(5, ge=1, description="a window holds the centre frame and this many frames each side")
    radius: float = Field(0.5, gt=0.0, description="neighbourhood radius of the map entropy [m]")
    min_neighbors: int = Field(10, ge=4, description="query points with fewer map neighbours are skipped")
    max_query_points: int = Field(1500, ge=10, description="points of the centre scan queried per window")
    thickness_floor: float = Field(
        0.01, ge=0.0, description="sigma_f [m]: the entropy is that of Sigma + sigma_f^2 I, no surface counts as thinner")
    max_mean_entropy_increase: float = Field(
        0.02, description="reject when the mean map entropy (per window, minus the reference) rose by more [nats]")
    window_quantile: float = Field(0.9, gt=0.0, le=1.0, description="quantile of the per-window entropy increase tested")
    max_window_entropy_increase: float = Field(
        0.1, description="reject when that quantile of per-window entropy increases is above this [nats]")
    min_measurable_fraction: float = Field(
        0.5, ge=0.0, le=1.0, description="reject when a window keeps less than this fraction of the reference's "
        "measurable query points (a map spread too thin to measure; its entropy would look sharp)")
    max_flagged_rate_increase: float = Field(
        0.02, description="reject when the fraction of failed odometry registrations rose by more")
    standstill_step: float = Field(
        0.005, gt=0.0, description="a frame stands still when the reference moved less than this since the last [m]")
    min_standstill_frames: int = Field(
        11, ge=2, description="frames of a standstill stretch (the one where the vehicle stopped and the still ones after it)")
    max_standstill_creep: float = Field(
        0.001, ge=0.0, description="reject when, over a standstill of the reference, the round's net displacement "
        "exceeds the reference's by more than this per frame [m]")
    long_baseline: bool = Field(
        False, description="also measure the long-baseline consistency (gr_graph.long_baseline; a few seconds a "
        "round): frame pairs long_baseline_distance apart registered raw scan to raw scan, each trajectory's relative "
        "poses compared with them; recorded in the verdict (always measured when the threshold below is set)")
    long_baseline_distance: float = Field(25.0, gt=0.0, description="path length between the frames of a pair [m]")
    long_baseline_step: int = Field(10, ge=1, description="a pair starts every this many frames")
    long_baseline_max_frames: int = Field(200, ge=1, description="pairs further apart in frames are left out")
    long_baseline_voxel_size: float = Field(0.25, gt=0.0, description="downsampling of the pairs' scans [m]")
    long_baseline_max_correspondence: float = Field(1.0, gt=0.0, description="GICP correspondence distance [m]")
    long_baseline_min_inliers: float = Field(
        0.3, gt=0.0, le=1.0, description="a registration matching fewer of the source's points fails (left out)")
    long_baseline_min_pairs: int = Field(
        20, ge=1, description="fewer registered pairs: only the pair counts are recorded, nothing decided on")
    max_long_baseline_rotation_increase: float | None = Field(
        None, ge=0.0, description="reject when the median rotation discrepancy with the pairs' registrations rose by more "
        "than this fraction of the reference's (--long-baseline-guard: 0.05, tuned on seeds 3-5 of the vertical-"
        "corrected kitti world); None: not decided on (README: without the correction it rejected the best rounds)")


#: The paper's method where the defaults differ from it (since 2026-12-05): the Gaussian correspondence NLL and
#: Algorithm 2's densification (the samples replace the anisotropic points, the others are dropped); ``gr-slam
#: --paper-method`` sets it. The correspondence NLL stays averaged per pair (``trainer.corr_reduction``), as in
#: every run of this project.
PAPER_TRAINING: dict[str, Any] = {"trainer": {"corr_likelihood": "gaussian"}, "keep_original": False,
                                  "keep_dropped": False}


class TrainingConfig(_Section):
    """Learning rounds (Algorithm 3): training f_theta (Algorithm 1) and densification (Algorithm 2).

    ``trainer`` holds the trainer's hyper-parameters, :class:`training.config.TrainOptions`
    (``lr``, ``lambda_corr``, ``lambda_pose``, ``max_corr``, ``num_threads``, ..., and ``net``:
    :class:`training.config.NetConfig`), validated when the configuration is loaded; an
    unknown key at any level is an error. The run settings of ``training.config.TrainConfig``
    (``epochs``, ``seed``, ``device``, ``progress``, ``init_checkpoint``) are set by the
    pipeline (:meth:`trainer_config`) and may not appear there.
    """

    rounds: int = Field(0, ge=0, description="reciprocal rounds after the raw-scan SLAM (round 0)")
    convergence_delta: float = Field(0.01, ge=0.0, description="stop when poses move less than this [m, mean]")
    tau_ani: float = Field(0.9, ge=0.0, lt=1.0, description="anisotropy filter: keep points with 1 - l_min/l_max > tau_ani")
    samples_per_point: int = Field(4, ge=1, description="M: samples ~ N(s, C) drawn per kept point")
    keep_original: bool = Field(True, description="also keep the filtered points themselves in S+ (paper, and the "
                                "default until 2026-12-05: samples only)")
    keep_dropped: bool = Field(
        True, description="also keep, unchanged, the points the anisotropy filter drops (paper, and the default until "
        "2026-12-05: dropped); with keep_original the scan keeps every point and gains the samples"
    )
    min_kept_points: int = Field(
        200, ge=1, description="fewer points pass the filter and keep_dropped is false: the frame falls back to its "
        "unfiltered points (logged); with keep_dropped every point stays, so no fallback"
    )
    prediction_passes: Literal["split", "training_size"] = Field(
        "split", description="how a scan goes through the network when its covariances are predicted: split: "
        "ceil(N / n_points) disjoint parts of equal size, 1,024-2,048 points each with the default 2,048 (the "
        "published runs); training_size: every pass holds n_points points as training does (each part filled up "
        "with other points of the scan, only the part's own rows kept), so the network's neighbourhoods have "
        "the density it was trained on; about 1.4x the network's work on a 16-channel scan"
    )
    slam_voxel_size: float | None = Field(
        None, gt=0.0, description="voxel size of SLAM preprocessing on densified scans [m]; None: preprocess.voxel_size"
    )
    seed: int = Field(0, ge=0, description="seeds training (weights, sampling) and densification (per frame: (seed, index))")
    epochs: int = Field(3, ge=0, description="training epochs per round (the paper's I)")
    warm_start: bool = Field(True, description="rounds >= 2 start from the previous round's model.pt")
    weights: str | None = Field(
        None, description="round 1 starts from these weights: 'pretrained' (the model shipped with gr_graph, "
        "gr_graph.pretrained) or the path of a model.pt; None: from random weights"
    )
    fine_tune: bool = Field(
        True, description="false (gr-slam --densify): the learning round uses `weights` as they are, without "
        "training (one round; no memory needed)"
    )
    edge_noise: Literal["registration", "learned"] = Field(
        "learned", description="rounds >= 1, odometry edges: 'learned' = pose-likelihood Hessian H(C) of the network's "
        "covariances (Lambda_i = (2 C_qi)^-1); 'registration' = the VGICP information of round 0"
    )
    covariances: Literal["network", "pca"] = Field(
        "network", description="rounds >= 1: per-point covariances from the trained network, or 'pca' (ablation, no "
        "training): the covariance of each preprocessed point's preprocess.num_neighbors nearest neighbours + "
        "trainer.net.eps I (gr_graph.pca_covariances), used for densification and the learned edge noise"
    )
    densify: bool = Field(
        True, description="rounds >= 1: SLAM on the densified scans; false (ablation): SLAM on the raw scans while the "
        "learned edge noise still comes from the covariances"
    )
    stop_on_reject: bool = Field(
        True, description="the learning rounds stop after a rejected round; false: every round runs (the harness's "
        "unguarded 2-step), the acceptance is still recorded"
    )
    learned_noise_edges: Literal["all", "odometry"] = Field(
        "all", description="with edge_noise 'learned': which edges get H(C); 'all' = odometry and loop edges, "
        "'odometry' = loops keep the registration information (the former behaviour)"
    )
    learned_noise_calibration: Literal["graph_residuals", "none"] = Field(
        "graph_residuals", description="with edge_noise 'learned': one scale for every edge's information, "
        "'graph_residuals' = 1 / the a-posteriori variance factor of the optimised graph (gr_graph.noise_calibration)"
    )
    learned_noise_outlier_alpha: float = Field(
        0.0, ge=0.0, lt=1.0, description="with learned_noise_calibration 'graph_residuals': a loop this improbable "
        "against the other edges' variance factor (deletion F test: what it adds to the chi-square) is left out of "
        "the estimate (it stays in the robust graph), at most a tenth of the loops (one with fewer than 20); 0 (the "
        "default): every loop counts. Opt-in: 1e-4 keeps one wrong loop from weakening every edge on constructed "
        "graphs, but on the full synthetic route it left out 5 correct loops (README)"
    )
    learned_noise_covariance: Literal["hessian", "cluster_robust", "cluster_robust_offset"] = Field(
        "hessian", description="with edge_noise 'learned': each edge's information is 'hessian' = H(C), or "
        "'cluster_robust' = the inverse of the sandwich covariance H^-1 M H^-1 of the same learned cost (H and M "
        "one Gauss-Newton step from the edge's pose), M from "
        "its residual gradients summed over cubes of graph.cluster_size (at least graph.min_clusters, else H(C), "
        "counted); 'cluster_robust_offset' that plus the squared offset of the edge's pose from the learned cost's "
        "minimum, axis by axis; opt-in (gr_graph.edge_noise.learned_sandwich_information)"
    )
    learned_noise_scale: float = Field(1.0, gt=0.0, description="multiplies the learned information before the "
                                       "eigenvalue floor")
    learned_noise_min_correspondences: int = Field(
        50, ge=3, description="fewer nearest-neighbour pairs (within odometry.corr_max_distance): registration fallback"
    )
    learned_noise_degeneracy_rel: float = Field(
        1e-4, ge=0.0, lt=1.0, description="H(C) eigenvalue below this x largest (rotations as arc at 10 m): degenerate, fallback"
    )
    acceptance: AcceptanceConfig = Field(
        default_factory=AcceptanceConfig, description="GT-free acceptance test of each learning round")
    trainer: TrainOptions = Field(
        default_factory=TrainOptions, description="trainer hyper-parameters, e.g. {lr: 1e-3, net: {n_points: 1024}}"
    )

    @model_validator(mode="after")
    def _weights_without_training(self) -> TrainingConfig:
        if not self.fine_tune:
            if self.weights is None:
                raise ValueError("training.fine_tune false (--densify) needs training.weights (--weights pretrained|PATH)")
            if self.rounds > 1:
                raise ValueError(f"training.fine_tune false (--densify) runs one learning round (rounds: {self.rounds}); "
                                 "without training every further round would densify the same scans alike")
        return self

    @field_validator("trainer", mode="before")
    @classmethod
    def _no_pipeline_keys(cls, v: Any) -> Any:
        reserved = set(RUN_KEYS) & set(v) if isinstance(v, dict) else set()
        if reserved:
            raise ValueError(f"{sorted(reserved)} are set by the pipeline; use training.epochs/seed and the "
                             "top-level device")
        return v

    def trainer_config(self, device: str = "cpu", progress: bool = True,
                       init_checkpoint: str | os.PathLike[str] | None = None) -> TrainConfig:
        """The trainer's configuration of a learning round: ``trainer`` plus the run settings."""
        return TrainConfig.model_validate({
            **self.trainer.model_dump(), "epochs": self.epochs, "seed": self.seed, "device": device,
            "progress": progress, "init_checkpoint": None if init_checkpoint is None else str(init_checkpoint),
        })


class SlamConfig(_Section):
    """The whole configuration of ``python -m gr_graph.slam``."""

    data: DataConfig = DataConfig()
    sensor: SensorConfig = SensorConfig()
    preprocess: PreprocessConfig = PreprocessConfig()
    odometry: OdometryConfig = OdometryConfig()
    loops: LoopConfig = LoopConfig()
    graph: GraphConfig = GraphConfig()
    output: OutputConfig = OutputConfig()
    training: TrainingConfig = TrainingConfig()
    device: Literal["cpu", "cuda"] = "cpu"
    seed: int = Field(0, ge=0, description="seeds the synthetic world (its actors and sensor effects; the route has data.route_seed)")

    @model_validator(mode="after")
    def _channels_fit_sensor(self) -> "SlamConfig":
        try:
            n = self.sensor.effective_beams(self.data.channels)
        except SensorError as exc:
            raise ValueError(f"data.channels: {exc}") from None
        if n != self.sensor.beams and self.sensor.has_ring is False:
            raise ValueError(f"data.channels: subsampling to {n} channels needs ring indices, but sensor.has_ring "
                             "is false")
        return self

    @property
    def channels(self) -> int:
        """Rings in the scans SLAM runs on: ``data.channels``, or all the sensor's beams."""
        return self.sensor.effective_beams(self.data.channels)


def loop_max_rmse(loops: LoopConfig, sensor: SensorConfig, channels: int | None = None) -> float:
    """Loop verification RMSE threshold: ``loops.max_rmse``, or scaled with the sensor's ring
    spacing after subsampling (:func:`gr_graph.sensors.loop_rmse_threshold`: 0.35 m for the full
    HDL-64E, exactly ``0.35 * (64 / channels) ** 0.25`` for its subsampled scans).

    Nearest-neighbour distances between correctly aligned scans grow as rings get sparser
    (16-channel KITTI-like scans: 0.31-0.47 m RMSE for correct loops on synthetic KITTI 00).
    """
    if loops.max_rmse is not None:
        return loops.max_rmse
    return loop_rmse_threshold(sensor, channels)


class ConfigError(ValueError):
    """The configuration is invalid; the message names each bad key (an unknown one with the
    valid keys of its section) and where the configuration came from."""


def option_choices(section: type[BaseModel], option: str) -> tuple[str, ...]:
    """The values the ``Literal`` option ``option`` of the configuration class ``section`` takes, in
    their declared order (``None`` of an optional one left out): a command line's ``choices``, so they
    are written once, in the configuration.

    Raises
    ------
    TypeError
        If the option is not a ``Literal`` (or an optional one).
    """
    def values(annotation: Any) -> tuple[Any, ...]:
        if get_origin(annotation) is Literal:
            return get_args(annotation)
        if get_origin(annotation) in (Union, types.UnionType):
            return tuple(v for arm in get_args(annotation) if arm is not type(None) for v in values(arm))
        raise TypeError(f"{section.__name__}.{option} is not a Literal option ({annotation!r})")

    return values(section.model_fields[option].annotation)


def load_config(path: str | os.PathLike[str] | None = None, overrides: dict[str, Any] | None = None) -> SlamConfig:
    """Defaults, then a YAML file, then ``overrides`` (nested dict, e.g. ``{"data": {"channels": 32}}``).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ConfigError
        If a key is unknown (at any level) or a value invalid.
    ValueError
        If the file does not hold a mapping.
    """
    data: dict[str, Any] = {}
    written_since_given_keys = False
    if path is not None:
        p = Path(path)
        text, loaded = read_config_file(p)
        loaded = loaded or {}
        written_since_given_keys = text.startswith(GIVEN_SENSOR_KEYS_MARK)
        if not isinstance(loaded, dict):
            raise ValueError(f"{p}: a config file must hold a mapping of sections")
        data = loaded
    # a sensor section listing every key is taken for a config.yaml of before the section kept only the
    # given keys (gr_graph.sensors.SensorConfig): only when one source (the file, or the overrides) lists
    # them all, not when command-line options (--sensor) complete a file's section
    from gr_graph.sensors import FORMER_FULL_DUMP_KEYS

    sections = [] if written_since_given_keys else [data.get("sensor")]  # a file of ours says what was given
    sections.append((overrides or {}).get("sensor"))
    one_file = any(isinstance(d, dict) and set(FORMER_FULL_DUMP_KEYS) <= set(d) for d in sections)
    if overrides:
        data = merge_config(data, overrides)
    try:
        return SlamConfig.model_validate(data, context={"sensor_section_from_one_file": one_file})
    except ValidationError as exc:
        source = f"configuration ({path} and command line)" if path is not None else "configuration"
        raise ConfigError(describe_validation_error(exc, SlamConfig, what=source)) from None


def merge_config(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """``a`` with ``b`` laid over it, nested sections merged key by key (neither input is changed;
    values only in ``b`` are taken as they are)."""
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = merge_config(out[k], v)
        else:
            out[k] = v
    return out


#: first line of every configuration this version writes: its sensor section lists the keys that were given,
#: so a section listing all of them is what was said, not an older full dump (:func:`load_config`)
GIVEN_SENSOR_KEYS_MARK = "# gr_graph configuration (sensor: the keys given)"


def config_to_yaml(cfg: SlamConfig) -> str:
    """The resolved configuration as YAML text (round-trips through :func:`load_config`).

    The ``sensor`` section holds only the fields that were given (config file, command line):
    what was left unsaid is guessed from the data by the loaders (the time unit and reference,
    the ring count; :meth:`gr_graph.sensors.SensorConfig.given`), and a rerun from this file must
    guess it again, not take the defaults as said (a 32-ring folder read as the default HDL-64E's
    64 rings).
    """
    d = cfg.model_dump(mode="json")
    d["sensor"] = cfg.sensor.model_dump(mode="json", exclude_unset=True)
    return GIVEN_SENSOR_KEYS_MARK + "\n" + yaml.safe_dump(d, sort_keys=False)


def dump_config(cfg: SlamConfig, path: str | os.PathLike[str]) -> Path:
    """Write the resolved configuration atomically as YAML."""
    return atomic_write_text(path, config_to_yaml(cfg))
