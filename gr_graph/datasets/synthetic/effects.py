"""Sensor effects of the synthetic HDL-64E and the presets ``clean``, ``kitti`` and ``raw``.

Each effect is physically motivated, switchable on its own, and documented with the source
of its numbers (author/year; "assumption" where no source fixes a number). The renderer
(:func:`~gr_graph.datasets.synthetic.sensor.render_scan`) applies them; this module holds
their parameters, the per-laser calibration draw and the sweep motion (SE(3) interpolation).

Effects
-------
motion distortion (:class:`MotionDistortion`)
    A sweep takes ``sweep_seconds`` = 0.1 s (HDL-64E S2 at 10 Hz, the rate of KITTI's scans,
    Geiger et al. 2013). Every azimuth column is measured from the sensor pose at its own time,
    interpolated on SE(3) between the 10 Hz poses of the path; the ground-truth pose of a frame
    is the pose at the middle of the sweep. The sensor spins clockwise seen from above, the
    sweep starts and ends facing backwards and faces forward (x) at mid-sweep (KITTI triggers
    its cameras when the laser faces forward, Geiger et al. 2013). ``mode``:

    - ``"off"``: an instantaneous scan from the frame's pose (the ``clean`` world);
    - ``"raw"``: full distortion, points in the sensor frame of their own time (KITTI raw
      scans are not motion-compensated); the frame carries each point's sweep fraction
      ``time`` in [0, 1];
    - ``"compensated"``: KITTI odometry scans were motion-compensated with the vehicle's
      GPS/IMU (KITTI odometry readme). The points are re-projected into the mid-sweep frame
      with a constant body velocity (the central difference of the poses around the frame)
      perturbed by the IMU's velocity errors: ``velocity_sigma`` = 0.05 km/h RMS = 0.014 m/s
      (OXTS RT3003 datasheet, the unit of KITTI, Geiger et al. 2013) and ``rate_sigma`` =
      0.01 deg/s per axis (assumption: the order of a tactical-grade gyro's in-run bias). The
      residual is that velocity error plus the sweep's departure from constant velocity.

per-laser calibration errors (:class:`CalibrationErrors`)
    Each laser fires in a direction and with a range bias that differ from what the sensor's
    calibration file assumes; the sensor reports ``nominal direction * ((1 + scale) r + offset)``
    for a true range ``r`` along the true direction. Drawn once per sensor seed, Gaussian per
    laser: elevation 0.03 deg, azimuth 0.03 deg, range offset 1.5 cm, range scale 0.05 %. Glennie
    & Lichti (2010) re-calibrate an HDL-64E S2 per laser (elevation, azimuth, range offset and
    scale among the parameters) and obtain a three-fold lower planar misclosure RMSE than with
    the factory calibration, i.e. factory residuals of a few cm; the sigmas above give a few cm
    at 20-50 m (the values are our choice inside that bound). Plus KITTI's global vertical-angle
    error: every beam points ``vertical_offset_deg`` = 0.22 deg higher than the calibration says, so
    the points lie too low and must be raised by 0.22 deg (IMLS-SLAM, Deschaud 2018; CT-ICP,
    Dellenbach et al. 2022; KISS-ICP, Vizzo et al. 2023, uses 0.205 deg; range 0.195-0.22 deg).

range noise (:class:`RangeNoise`)
    ``sigma(r, theta) = floor * sqrt(1 + r^2 / (reference_range^2 * max(cos theta, min_cos)))``:
    a floor of 1.5 cm (HDL-64E S2 datasheet: range accuracy < 2 cm 1-sigma) plus a term that
    grows as the echo weakens: the received power falls as ``cos(theta) / r^2`` (Lambertian
    target, Soudarissanane et al. 2011) and the timing jitter as ``1 / sqrt(SNR)``.
    ``reference_range`` = 40 m (assumption: the range where the jitter term equals the floor,
    which keeps sigma at 2.1 cm at 40 m normal incidence, near the datasheet's figure).

mixed pixels (:class:`MixedPixels`)
    The beam has a divergence of ``divergence_rad`` = 2.5 mrad (HDL-64E S2 datasheet, about
    2-3 mrad); at 2000 azimuth steps, neighbouring rays of a ring are 3.1 mrad apart, so the
    footprint of a ray straddles a depth edge between it and its azimuth neighbour when the edge
    (uniformly placed between them) lies within half a divergence of the ray. The echo then
    mixes foreground and background in proportion to the footprint covered (1-D footprint);
    when the two surfaces are closer than ``merge_distance_m`` = 2 m (assumption: the echoes of
    a few-ns pulse overlap) the sensor reports their weighted mean range, a point in mid-air;
    otherwise it resolves the (stronger) own surface. Only depth edges mix: a gap between
    neighbours that exceeds the mean of the neighbouring gaps by more than ``min_edge_m`` =
    0.1 m (a jump, not the steady range slope of an oblique plane). Only azimuth neighbours of the same laser
    are used, so a 16/32-ring render stays the corresponding rings of the 64-ring render.

rough surfaces (:class:`Roughness`)
    Grass, gravel, bushes, bark and brick are not planes: each return is displaced along the
    surface normal by a fixed random height field of the material (0.1 m cells hashed from the
    world position, so every frame sees the same bumps; a height ``h`` along the normal moves the
    return by ``h / cos(theta)`` along the ray, theta capped at the sensor's grazing cut-off),
    uniform with standard deviation per
    material: terrain (grass, gravel) 3 cm, foliage (bushes, crowns) 5 cm, trunk 1 cm,
    building (brick, plaster) 0.5 cm, wall 1 cm, sidewalk 0.3 cm, road 0.2 cm, poles/cars/glass 0
    (assumptions: the heights of lawn grass, gravel and leaves, and of mortar joints).

Presets (:func:`preset`): ``clean`` (no effect: today's render, bit-identical), ``kitti``
(every effect, compensated motion) and ``raw`` (every effect, full distortion with per-point
times). These are the sensor side of a preset; its world (the town and the moving actors) is
chosen by :func:`gr_graph.datasets.synthetic.sequence.preset_world`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from factors.se3 import exp_se3_batch, log_se3
from gr_graph.datasets.stamp_shift import poses_at_times
from gr_graph.datasets.synthetic.meshes import MATERIAL, MATERIAL_NAMES

PRESETS = ("clean", "kitti", "raw")
EFFECT_NAMES = ("motion", "calibration", "range_noise", "mixed_pixels", "roughness")


@dataclass(frozen=True)
class MotionDistortion:
    """Motion distortion of a sweep (see the module docstring).

    Attributes
    ----------
    mode : str
        ``"off"``, ``"raw"`` (full distortion, per-point times) or ``"compensated"``.
    sweep_seconds : float
        Duration of one revolution (s).
    velocity_sigma : float
        Per-axis error of the compensating linear velocity (m/s).
    rate_sigma_deg : float
        Per-axis error of the compensating angular rate (deg/s).
    """

    mode: str = "off"
    sweep_seconds: float = 0.1
    velocity_sigma: float = 0.014
    rate_sigma_deg: float = 0.01

    def __post_init__(self) -> None:
        if self.mode not in ("off", "raw", "compensated"):
            raise ValueError(f"motion mode must be off, raw or compensated, got {self.mode!r}")
        if not (self.sweep_seconds > 0 and self.velocity_sigma >= 0 and self.rate_sigma_deg >= 0):
            raise ValueError(f"invalid motion distortion {self}")

    @property
    def enabled(self) -> bool:
        return self.mode != "off"


@dataclass(frozen=True)
class CalibrationErrors:
    """Per-laser intrinsic calibration errors (Gaussian sigmas) and the global vertical offset."""

    enabled: bool = False
    elevation_sigma_deg: float = 0.03
    azimuth_sigma_deg: float = 0.03
    range_offset_sigma_m: float = 0.015
    range_scale_sigma: float = 0.0005
    vertical_offset_deg: float = 0.22


@dataclass(frozen=True)
class RangeNoise:
    """Range noise growing with range and incidence (replaces the constant ``range_sigma``)."""

    enabled: bool = False
    floor_sigma_m: float = 0.015
    reference_range_m: float = 40.0
    min_cos: float = 0.1

    def sigma(self, r: np.ndarray, cos_inc: np.ndarray) -> np.ndarray:
        """Standard deviation (m) at range ``r`` (m) and incidence cosine ``cos_inc``."""
        c = np.maximum(np.abs(cos_inc), self.min_cos)
        return self.floor_sigma_m * np.sqrt(1.0 + r * r / (self.reference_range_m ** 2 * c))


@dataclass(frozen=True)
class MixedPixels:
    """Returns mixing foreground and background where a beam footprint straddles a depth edge."""

    enabled: bool = False
    divergence_rad: float = 0.0025
    merge_distance_m: float = 2.0
    min_edge_m: float = 0.1


def _default_roughness() -> dict[str, float]:
    return {"road": 0.002, "sidewalk": 0.003, "terrain": 0.03, "building": 0.005, "wall": 0.01,
            "pole": 0.0, "trunk": 0.01, "foliage": 0.05, "car": 0.0, "glass": 0.0}


@dataclass(frozen=True)
class Roughness:
    """Per-material surface roughness: a fixed random height field along the normal."""

    enabled: bool = False
    sigma_m: dict[str, float] = field(default_factory=_default_roughness)
    cell_m: float = 0.1

    def sigma_by_material_id(self) -> np.ndarray:
        """``(n_materials,)`` sigma (m) indexed by material id."""
        unknown = set(self.sigma_m) - set(MATERIAL)
        if unknown:
            raise ValueError(f"roughness: unknown materials {sorted(unknown)} (known: {MATERIAL_NAMES})")
        out = np.zeros(max(len(MATERIAL_NAMES), 256), dtype=np.float32)
        for name, s in self.sigma_m.items():
            out[MATERIAL[name]] = s
        return out


@dataclass(frozen=True)
class SensorEffects:
    """The switchable sensor effects of one render (default: none, the ``clean`` preset)."""

    motion: MotionDistortion = field(default_factory=MotionDistortion)
    calibration: CalibrationErrors = field(default_factory=CalibrationErrors)
    range_noise: RangeNoise = field(default_factory=RangeNoise)
    mixed_pixels: MixedPixels = field(default_factory=MixedPixels)
    roughness: Roughness = field(default_factory=Roughness)

    def enabled(self, name: str) -> bool:
        """Whether effect ``name`` (one of :data:`EFFECT_NAMES`) is on."""
        return bool(getattr(self, _check_name(name)).enabled)

    @property
    def is_clean(self) -> bool:
        """True when no effect is on (the renderer then takes its original path)."""
        return not any(self.enabled(n) for n in EFFECT_NAMES)

    def with_effect(self, name: str, on: bool, motion_mode: str = "compensated") -> "SensorEffects":
        """A copy with effect ``name`` switched on or off (motion on: ``motion_mode``)."""
        name = _check_name(name)
        cur = getattr(self, name)
        if name == "motion":
            new = replace(cur, mode=motion_mode if on else "off")
        else:
            new = replace(cur, enabled=on)
        return replace(self, **{name: new})

    def describe(self) -> str:
        on = [n if n != "motion" else f"motion={self.motion.mode}" for n in EFFECT_NAMES if self.enabled(n)]
        return "+".join(on) if on else "none"


def _check_name(name: str) -> str:
    if name not in EFFECT_NAMES:
        raise ValueError(f"unknown sensor effect {name!r}; choose from {EFFECT_NAMES}")
    return name


def preset(name: str) -> SensorEffects:
    """The effects of preset ``name``: ``clean``, ``kitti`` or ``raw``."""
    if name == "clean":
        return SensorEffects()
    if name not in PRESETS:
        raise ValueError(f"unknown synthetic preset {name!r}; choose from {PRESETS}")
    fx = SensorEffects()
    for n in EFFECT_NAMES:
        fx = fx.with_effect(n, True, motion_mode="compensated" if name == "kitti" else "raw")
    return fx


# ----------------------------------------------------------------------------- calibration

@dataclass(frozen=True)
class LaserCalibration:
    """Drawn per-laser errors of one sensor (64 lasers, ring 0 = highest beam).

    Attributes
    ----------
    elevation_rad, azimuth_rad : np.ndarray
        ``(64,)`` true minus nominal beam angles (rad), the global vertical offset included.
    range_offset_m, range_scale : np.ndarray
        ``(64,)``: the sensor reports ``(1 + range_scale) r + range_offset_m``.
    """

    elevation_rad: np.ndarray
    azimuth_rad: np.ndarray
    range_offset_m: np.ndarray
    range_scale: np.ndarray


def draw_laser_calibration(cfg: CalibrationErrors, seed: int, n_beams: int = 64) -> LaserCalibration:
    """Per-laser errors of the sensor of ``seed`` (fixed for the sensor, not per frame)."""
    rng = np.random.default_rng([int(seed), 0xCA1B])
    el = np.radians(cfg.elevation_sigma_deg) * rng.standard_normal(n_beams)
    az = np.radians(cfg.azimuth_sigma_deg) * rng.standard_normal(n_beams)
    off = cfg.range_offset_sigma_m * rng.standard_normal(n_beams)
    scale = cfg.range_scale_sigma * rng.standard_normal(n_beams)
    return LaserCalibration(el + np.radians(cfg.vertical_offset_deg), az, off, scale)


def column_times(phase: float, n_azimuth: int) -> np.ndarray:
    """Sweep fraction in [0, 1) of each azimuth column (0.5 when facing forward).

    Column ``a`` points at azimuth ``phase + 2 pi a / n`` (counter-clockwise from x); the
    sensor spins clockwise and starts facing backwards (azimuth pi).
    """
    az = phase + 2.0 * np.pi * np.arange(n_azimuth) / n_azimuth
    return np.mod(np.pi - az, 2.0 * np.pi) / (2.0 * np.pi)


def interpolate_poses(times: np.ndarray, poses: np.ndarray, t: np.ndarray, i: int) -> np.ndarray:
    """Poses ``(len(t), 4, 4)`` at times ``t`` near frame ``i``, on SE(3).

    Interpolates along the constant-twist segment between the path's poses around ``i``
    (``i-1 .. i`` before ``times[i]``, ``i .. i+1`` after; the end segments extrapolate):
    :func:`gr_graph.datasets.stamp_shift.poses_at_times` on the path's frames ``i-1 .. i+1``, which
    raises ``ValueError`` when their times do not strictly increase (the trajectory readers refuse
    such files, naming them).
    """
    lo, hi = max(i - 1, 0), min(i + 2, len(poses))
    return poses_at_times(times[lo:hi], poses[lo:hi], t)


@dataclass(frozen=True)
class SweepMotion:
    """The sensor motion during one sweep, for :func:`~gr_graph.datasets.synthetic.sensor.render_scan`.

    Attributes
    ----------
    T_w_col : np.ndarray
        ``(n_azimuth, 4, 4)`` true sensor pose of each azimuth column.
    T_mid_col_est : np.ndarray or None
        ``(n_azimuth, 4, 4)`` the compensation's estimate of ``T_mid^-1 T_col`` (None: raw,
        points stay in the sensor frame of their time).
    column_fraction : np.ndarray
        ``(n_azimuth,)`` sweep fraction of each column in [0, 1).
    column_time : np.ndarray
        ``(n_azimuth,)`` absolute time (s) of each column.
    """

    T_w_col: np.ndarray
    T_mid_col_est: np.ndarray | None
    column_fraction: np.ndarray
    column_time: np.ndarray


def sweep_motion(cfg: MotionDistortion, times: np.ndarray, poses: np.ndarray, i: int,
                 phase: float, n_azimuth: int, rng: np.random.Generator) -> SweepMotion:
    """The sweep of frame ``i`` (pose ``poses[i]`` at mid-sweep, time ``times[i]``).

    ``rng`` draws the compensation's velocity errors (6 normals, always drawn).
    """
    frac = column_times(phase, n_azimuth)
    t_col = times[i] + (frac - 0.5) * cfg.sweep_seconds
    T_w_col = interpolate_poses(times, poses, t_col, i)
    err = rng.standard_normal(6)
    est = None
    if cfg.mode == "compensated":
        n = len(poses)
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        if b > a and times[b] > times[a]:
            xi = log_se3(np.linalg.inv(poses[a]) @ poses[b]) / (times[b] - times[a])
        else:
            xi = np.zeros(6)
        # gtsam order [omega, v]: err[:3] perturbs the velocity, err[3:] the rate
        xi = xi + np.concatenate([np.radians(cfg.rate_sigma_deg) * err[3:], cfg.velocity_sigma * err[:3]])
        est = exp_se3_batch((t_col - times[i])[:, None] * xi)
    return SweepMotion(T_w_col, est, frac, t_col)


# ----------------------------------------------------------------------------- roughness

def hashed_uniform(cells: np.ndarray, seed: int) -> np.ndarray:
    """A fixed pseudo-random value in [-1, 1) per integer cell ``(N, 3)`` (splitmix-style hash)."""
    c = cells.astype(np.int64).astype(np.uint64)
    h = np.full(len(c), np.uint64(int(seed) * 0x9E3779B97F4A7C15 % 2 ** 64), dtype=np.uint64)
    with np.errstate(over="ignore"):
        for k, m in enumerate((0xBF58476D1CE4E5B9, 0x94D049BB133111EB, 0xD6E8FEB86659FD93)):
            h ^= c[:, k] * np.uint64(m)
            h ^= h >> np.uint64(31)
            h *= np.uint64(0x9E3779B97F4A7C15)
            h ^= h >> np.uint64(29)
    return (h >> np.uint64(11)).astype(np.float64) / 2.0 ** 53 * 2.0 - 1.0
