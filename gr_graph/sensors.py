"""The LiDAR sensors gr_graph knows, and the ``sensor`` section that describes a sequence's sensor.

Two things live here, both about *which sensor took the scans*:

- a catalogue of spinning sensors (:data:`SENSOR_MODELS`, :func:`sensor_model`): beam
  elevations, columns per revolution, range and rotation period, with the datasheet numbers
  they come from. The synthetic renderer (:mod:`gr_graph.datasets.synthetic.sensor`) draws its
  beam patterns from it;
- :class:`SensorConfig`, the ``sensor`` section of the SLAM configuration (re-exported by
  :mod:`gr_graph.config`): the model name, beam count, vertical field of view or per-beam
  elevations, whether the data carries ring indices and per-point times, the time unit and
  reference, the scan period. Loaders read it to interpret their files; the pipeline reads it
  for every threshold that depends on how sparse the rings are (:func:`loop_rmse_threshold`).

Channel subsampling (the paper's 64 -> 32 -> 16, keeping every 2nd / 4th ring) applies to
64-beam sensors only (:meth:`SensorConfig.effective_beams`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

__all__ = [
    "SensorModel", "SENSOR_MODELS", "DEFAULT_SENSOR", "CUSTOM", "sensor_model", "sensor_names",
    "hdl64_elevations_deg", "SensorConfig", "SensorError", "TIME_UNITS", "loop_rmse_threshold",
    "check_sequence_sensor", "frame_sensor_problem",
]


class SensorError(ValueError):
    """A sensor description is invalid, or does not fit the data or the requested channels."""


def hdl64_elevations_deg() -> np.ndarray:
    """The 64 HDL-64E beam elevations in degrees, ring 0 (highest) first, strictly decreasing.

    Two blocks as on the HDL-64E S2: the upper 32 beams every 1/3 deg (+2.0 .. -8.33 deg), the
    lower 32 evenly from -8.83 to -24.9 deg (about 0.52 deg). Vertical field of view +2.0 to
    -24.9 deg (26.9 deg; Velodyne HDL-64E S2 datasheet).
    """
    upper = 2.0 - np.arange(32) / 3.0
    lower_top = upper[-1] - 0.5
    lower = lower_top - np.arange(32) * (24.9 + lower_top) / 31.0
    return np.concatenate([upper, lower])


@dataclass(frozen=True)
class SensorModel:
    """A spinning LiDAR of the catalogue.

    Attributes
    ----------
    name : str
        Catalogue name (``hdl64e``, ``vlp16``, ``os1-64``).
    description : str
        One line: what it is and where its numbers come from.
    elevations_deg : tuple of float
        Nominal beam elevations in degrees, ring 0 (the highest beam) first, strictly decreasing.
    n_azimuth : int
        Firings (columns) per revolution at ``scan_period``.
    max_range : float
        Largest range the synthetic renderer returns for it (m).
    scan_period : float
        Rotation period the renderer uses (s): 10 Hz for every model here, the rate of the
        generated routes (each model also runs at other rates).
    """

    name: str
    description: str
    elevations_deg: tuple[float, ...]
    n_azimuth: int
    max_range: float
    scan_period: float = 0.1

    @property
    def n_beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def vertical_fov_deg(self) -> tuple[float, float]:
        """(top, bottom) elevation in degrees."""
        return float(self.elevations_deg[0]), float(self.elevations_deg[-1])


SENSOR_MODELS: dict[str, SensorModel] = {
    m.name: m for m in (
        SensorModel(
            "hdl64e",
            "Velodyne HDL-64E (S2), KITTI's sensor: 64 beams, +2.0 to -24.9 deg (26.9 deg vertical field of "
            "view, upper block every 1/3 deg, lower block ~0.5 deg), 2,000 columns at 10 Hz (about 1.3 M points/s "
            "over 64 lasers), 120 m (HDL-64E S2 datasheet)",
            tuple(float(e) for e in hdl64_elevations_deg()), n_azimuth=2000, max_range=120.0),
        SensorModel(
            "vlp16",
            "Velodyne VLP-16 (Puck): 16 beams, +15 to -15 deg every 2.0 deg (30 deg vertical field of view), "
            "0.2 deg azimuth resolution at 10 Hz = 1,800 columns (0.1-0.4 deg at 5-20 Hz), 100 m range, "
            "+-3 cm typical range accuracy (VLP-16 datasheet 63-9229 and user manual 63-9243)",
            tuple(15.0 - 2.0 * k for k in range(16)), n_azimuth=1800, max_range=100.0),
        SensorModel(
            "os1-64",
            "Ouster OS1-64 with uniform beam spacing: 64 beams evenly over 45 deg (+22.5 to -22.5 deg, "
            "0.71 deg apart; OS1 Rev 6/7 datasheets; the first-generation OS1-64 covered 33.2 deg), "
            "1,024 columns at 10 Hz (512, 1,024 or 2,048 configurable, 10 or 20 Hz), 120 m at 80 % "
            "reflectivity, range repeatability +-1.5-3 cm (OS1 datasheet)",
            tuple(float(e) for e in np.linspace(22.5, -22.5, 64)), n_azimuth=1024, max_range=120.0),
    )
}
"""The catalogue, by name."""

DEFAULT_SENSOR = "hdl64e"
"""KITTI's sensor and the synthetic sequence's default."""

CUSTOM = "custom"
"""``sensor.model`` of a sensor described by its fields alone (not in the catalogue)."""

TIME_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
"""Seconds per unit of per-point times."""


def sensor_names() -> tuple[str, ...]:
    """Names of the catalogue's models."""
    return tuple(SENSOR_MODELS)


def _normalise_name(name: str) -> str:
    return str(name).strip().lower().replace("_", "-")


def sensor_model(name: str) -> SensorModel:
    """The catalogue entry called ``name`` (case and ``_``/``-`` ignored).

    Raises
    ------
    SensorError
        Naming the known models when ``name`` is not one of them.
    """
    key = _normalise_name(name)
    if key not in SENSOR_MODELS:
        raise SensorError(f"unknown sensor model {name!r}; known models: {', '.join(SENSOR_MODELS)} "
                          f"(or {CUSTOM!r} with n_beams and elevations_deg or vertical_fov_deg)")
    return SENSOR_MODELS[key]


#: the keys of every ``sensor`` section in a ``config.yaml`` written before it kept only the given ones
FORMER_FULL_DUMP_KEYS = ("model", "n_beams", "vertical_fov_deg", "elevations_deg", "has_ring", "has_time",
                         "time_unit", "time_reference", "scan_period")


class SensorConfig(BaseModel):
    """The sensor that took the scans: beams, field of view, what the data carries.

    A catalogue ``model`` (``hdl64e``, ``vlp16``, ``os1-64``) fills ``n_beams`` and
    ``vertical_fov_deg`` (and the beam elevations); ``model: custom`` takes them from the fields
    (``n_beams`` and ``elevations_deg`` or ``vertical_fov_deg``, beams then evenly spread). The
    default is KITTI's HDL-64E, also the synthetic sequence's default sensor.

    ``has_ring`` / ``has_time`` say whether the data carries per-point ring indices / times:
    ``None`` (default) = use them when the data has them (KITTI: rings recovered from the
    storage order); ``True`` = required (a frame without them is an error); ``False`` = the data
    has none, or they are to be ignored (folder and bag loaders drop the field, logged).
    Per-point times are read in ``time_unit`` and counted from ``time_reference``
    (:meth:`times_to_fractions` turns them into the sweep fractions of ``LidarFrame.time``).
    ``scan_period`` is the sweep duration in seconds (None: the sequence's: the spacing of the
    frame timestamps, or the span of a full revolution's per-point times where the two differ by
    more than 10 %, :mod:`gr_graph.datasets.frame_fields`). The folder and bag loaders
    (:class:`gr_graph.datasets.frame_fields.FieldConventions`) use ``time_unit`` and
    ``time_reference`` when they are set (None, the default: guessed from the data;
    ``times_to_fractions`` then reads seconds from the sweep's start), and take the ring count
    from a named sensor (:attr:`named_beams`: ``model`` or ``n_beams`` given), else from the data.
    ``frame_stamp`` says where the data's frame stamps lie in the sweep (a driver stamps its first or
    last point, KITTI the instant facing forward); the folder and bag loaders move the stamps to the
    sweep's middle, the instant a deskewed sweep's pose refers to (None: the offset the per-point
    times show, else the stamps as they are; :mod:`gr_graph.datasets.frame_fields`).
    ``config.yaml`` keeps only the sensor fields that were given, so a rerun from it guesses
    what the first run guessed (:func:`gr_graph.config.config_to_yaml`).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    model: str = Field(DEFAULT_SENSOR, description=f"catalogue model ({', '.join(SENSOR_MODELS)}) or "
                                                   f"'{CUSTOM}' (described by the fields below)")
    n_beams: int | None = Field(None, ge=2, le=1024, description="lasers (rings); filled from a catalogue model")
    vertical_fov_deg: tuple[float, float] | None = Field(
        None, description="(top, bottom) beam elevation [deg]; filled from a catalogue model or elevations_deg")
    elevations_deg: tuple[float, ...] | None = Field(
        None, description="custom sensors: per-beam elevation [deg], ring 0 (highest) first; None: beams evenly "
        "spread over vertical_fov_deg (catalogue models use their own)")
    has_ring: bool | None = Field(None, description="data carries ring indices: None = when present, True = "
                                                    "required, False = none")
    has_time: bool | None = Field(None, description="data carries per-point times: None = when present, True = "
                                                    "required, False = none")
    time_unit: Literal["s", "ms", "us", "ns"] | None = Field(
        None, description="unit of per-point times; None: guessed from the data (times_to_fractions: seconds)")
    time_reference: Literal["sweep_start", "sweep_end", "absolute"] | None = Field(
        None, description="per-point times count from the sweep's start (>= 0), back from its end (<= 0), "
        "or are absolute stamps (same clock as the frame timestamps); None: from what the values show "
        "(times_to_fractions: sweep_start)")
    rotation: Literal["clockwise", "counterclockwise"] = Field(
        "clockwise", description="spin seen from above (Velodyne, Ouster: clockwise); deskewing without per-point "
        "times takes them from the azimuth in this direction")
    sweep_start_azimuth_deg: float = Field(
        180.0, ge=-180.0, le=360.0, description="azimuth where a sweep starts [deg] (0 ahead, 90 left; 180: "
        "facing backward, KITTI's); deskewing without per-point times counts the sweep from it")
    scan_period: float | None = Field(None, gt=0.0, description="sweep duration [s]; None: the sequence's (the "
                                                                "frame spacing, or a full revolution's per-point time span "
                                                                "when they differ by more than 10 %)")
    frame_stamp: Literal["sweep_start", "sweep_middle", "sweep_end"] | None = Field(
        None, description="where a frame's stamp lies in its sweep: a deskewed sweep's pose is that of its middle, "
        "and the folder and bag loaders move the stamps (and the ground truth) there; None: from the per-point "
        "times when they say, else the stamps are kept")

    @field_validator("model", mode="before")
    @classmethod
    def _known_model(cls, v: Any) -> Any:
        if not isinstance(v, str):
            return v
        key = _normalise_name(v)
        if key != CUSTOM:
            sensor_model(key)  # raises, naming the known models
        return key

    @model_validator(mode="after")
    def _resolve(self, info: ValidationInfo) -> "SensorConfig":
        # a section completed by command-line options is not a former dump (gr_graph.config.load_config)
        if (info.context or {}).get("sensor_section_from_one_file", True):
            self._forget_former_default_dump()
        if self.model == CUSTOM:
            self._resolve_custom()
        else:
            self._resolve_catalogue(sensor_model(self.model))
        return self

    def _forget_former_default_dump(self) -> None:
        """A ``config.yaml`` written before the sensor section kept only the given keys lists every
        key; its defaults (``time_unit: s``, ``time_reference: sweep_start``, the HDL-64E) were not
        said by anyone, and count as unsaid (guessed from the data) when all the keys are there."""
        if not set(FORMER_FULL_DUMP_KEYS) <= self.model_fields_set:
            return
        unsaid: set[str] = set()
        if self.time_unit == "s" and self.time_reference == "sweep_start":
            self._set("time_unit", None)
            self._set("time_reference", None)
            unsaid |= {"time_unit", "time_reference"}
        if self.model == DEFAULT_SENSOR and self.n_beams == SENSOR_MODELS[DEFAULT_SENSOR].n_beams:
            unsaid |= {"model", "n_beams", "vertical_fov_deg", "elevations_deg"}
        if unsaid:
            object.__setattr__(self, "__pydantic_fields_set__", self.model_fields_set - unsaid)

    def _set(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)  # no re-validation (validate_assignment) from inside

    def _resolve_catalogue(self, m: SensorModel) -> None:
        for field, value in (("n_beams", m.n_beams), ("vertical_fov_deg", m.vertical_fov_deg),
                             ("elevations_deg", None)):
            given = getattr(self, field)
            if field == "elevations_deg":
                if given is not None and not np.allclose(given, m.elevations_deg, atol=1e-6):
                    raise ValueError(f"elevations_deg contradict model {m.name!r}; use model: {CUSTOM} to "
                                     "describe another sensor")
                self._set(field, None)  # catalogue models keep theirs (compact config.yaml)
                continue
            if given is not None and not np.allclose(given, value, atol=1e-6):
                raise ValueError(f"{field} {given} contradicts model {m.name!r} ({value}); use model: {CUSTOM} "
                                 "to describe another sensor")
            self._set(field, value)

    def _resolve_custom(self) -> None:
        if self.n_beams is None:
            raise ValueError(f"model: {CUSTOM} needs n_beams")
        if self.elevations_deg is not None:
            el = np.asarray(self.elevations_deg, np.float64)
            if len(el) != self.n_beams:
                raise ValueError(f"elevations_deg holds {len(el)} beams, n_beams says {self.n_beams}")
            if not (np.all(np.isfinite(el)) and np.all(np.abs(el) <= 90.0) and np.all(np.diff(el) < 0)):
                raise ValueError("elevations_deg must be finite, within +-90 deg and strictly decreasing "
                                 "(ring 0 = highest beam first)")
            fov = (float(el[0]), float(el[-1]))
            if self.vertical_fov_deg is not None and not np.allclose(self.vertical_fov_deg, fov, atol=1e-6):
                raise ValueError(f"vertical_fov_deg {self.vertical_fov_deg} differs from the first and last of "
                                 f"elevations_deg {fov}")
            self._set("vertical_fov_deg", fov)
            return
        if self.vertical_fov_deg is None:
            raise ValueError(f"model: {CUSTOM} needs elevations_deg or vertical_fov_deg")
        top, bottom = self.vertical_fov_deg
        if not (np.isfinite(top) and np.isfinite(bottom) and -90.0 <= bottom < top <= 90.0):
            raise ValueError(f"vertical_fov_deg must be (top, bottom) with -90 <= bottom < top <= 90, got "
                             f"{self.vertical_fov_deg}")

    # ---------------------------------------------------------------- derived quantities
    @property
    def beams(self) -> int:
        """Beam count (``n_beams``, always set after validation)."""
        assert self.n_beams is not None
        return int(self.n_beams)

    @property
    def fov_span_deg(self) -> float:
        """Vertical field of view, top minus bottom beam elevation (deg)."""
        assert self.vertical_fov_deg is not None
        return float(self.vertical_fov_deg[0] - self.vertical_fov_deg[1])

    def beam_elevations_deg(self) -> np.ndarray:
        """Per-beam elevations in degrees, ring 0 (highest) first: the catalogue's, the given
        ``elevations_deg``, or ``n_beams`` evenly spread over ``vertical_fov_deg``."""
        if self.model != CUSTOM:
            return np.asarray(sensor_model(self.model).elevations_deg, np.float64)
        if self.elevations_deg is not None:
            return np.asarray(self.elevations_deg, np.float64)
        top, bottom = self.vertical_fov_deg  # type: ignore[misc]
        return np.linspace(top, bottom, self.beams)

    def effective_beams(self, channels: int | None = None) -> int:
        """Rings in the scans after channel subsampling.

        ``channels`` None or equal to ``n_beams``: all beams. Otherwise the sensor must have
        64 beams and ``channels`` be 32 or 16 (every 2nd / 4th ring, as in the paper).

        Raises
        ------
        SensorError
            For subsampling a sensor that does not have 64 beams, or an unsupported count.
        """
        n = self.beams
        if channels is None or int(channels) == n:
            return n
        if n != 64:
            raise SensorError(f"channel subsampling (64 -> 32 -> 16) applies to 64-beam sensors; sensor "
                              f"{self.model!r} has {n} beams: leave channels unset (or {n}) to use them all")
        if int(channels) not in (32, 16):
            raise SensorError(f"channels must be 64, 32 or 16 for a 64-beam sensor, got {channels}")
        return int(channels)

    def beam_spacing_deg(self, channels: int | None = None) -> float:
        """Mean vertical angle per ring after subsampling: ``fov_span_deg / effective_beams``
        (deg). The HDL-64E has 0.42 deg, 0.84 at 32 channels, 1.68 at 16; the VLP-16 1.875; the
        OS1-64 0.70."""
        return self.fov_span_deg / self.effective_beams(channels)

    # ---------------------------------------------------------------- per-point times
    def times_to_fractions(self, times: np.ndarray, sweep_start: float | None = None,
                           tolerance: float = 0.01) -> np.ndarray:
        """Per-point times as read from the data -> sweep fractions in [0, 1] (``LidarFrame.time``).

        Times are converted from ``time_unit`` to seconds, then counted from the sweep's start:
        ``sweep_start`` times as they are; ``sweep_end`` times (<= 0) shifted by the scan period;
        ``absolute`` stamps minus ``sweep_start`` (the sweep's start on the same clock, s) or,
        without it, minus the earliest point's time. Divided by ``scan_period`` (without one: by
        the times' own span). The arithmetic is :func:`gr_graph.deskew.normalise_times`, which
        the loaders (:class:`gr_graph.datasets.frame_fields.FieldConventions`) apply with these
        settings when they are set (``time_unit`` / ``time_reference`` not None, or a
        ``scan_period``) and with a guessed unit and reference otherwise.

        Parameters
        ----------
        times : (N,) array
            As stored in the data.
        sweep_start : float, optional
            Absolute times: the sweep's start in seconds (e.g. the message stamp).
        tolerance : float
            Fractions up to this far outside [0, 1] are clipped; further out is an error.

        Raises
        ------
        SensorError
            Non-finite times, or times that do not fit into one sweep (e.g. a wrong
            ``time_unit``); the message gives the span found. Callers add the file name.
        """
        from gr_graph.deskew import normalise_times

        t = np.asarray(times, np.float64) * TIME_UNITS[self.time_unit or "s"]
        try:
            return normalise_times(t, self.scan_period, self.time_reference or "sweep_start", sweep_start, tolerance)
        except ValueError as exc:
            if "non-finite" in str(exc):
                raise SensorError(str(exc)) from None
            raise SensorError(f"{exc} (times read in {self.time_unit or 's'}): check sensor.time_unit, "
                              "sensor.time_reference and sensor.scan_period") from None

    # ---------------------------------------------------------------- what the user said
    def given(self, field: str) -> bool:
        """Whether ``field`` was set explicitly (config file, command line, constructor), not
        left at its default. Loaders guess the time unit and reference, and take the ring
        count from the data, unless the corresponding field was given."""
        return field in self.model_fields_set

    @property
    def named_beams(self) -> int | None:
        """The beam count when the sensor was named (``model`` or ``n_beams`` given), else None
        (the default HDL-64E stands for "not said": loaders count rings from the data)."""
        return self.beams if (self.given("model") or self.given("n_beams")) else None


HDL64_FOV_SPAN_DEG = SENSOR_MODELS["hdl64e"].vertical_fov_deg[0] - SENSOR_MODELS["hdl64e"].vertical_fov_deg[1]
"""Vertical field of view of the HDL-64E (26.9 deg) that the loop threshold is calibrated on."""


def loop_rmse_threshold(sensor: SensorConfig, channels: int | None = None, at_64: float = 0.35) -> float:
    """Loop-verification RMSE threshold (m) for the sensor's ring spacing.

    ``at_64 * (s / s_ref) ** 0.25`` with ``s`` the mean vertical angle per ring after
    subsampling (:meth:`SensorConfig.beam_spacing_deg`) and ``s_ref`` the full HDL-64E's
    (26.9 deg / 64). Nearest-neighbour distances between correctly aligned scans grow as rings
    get sparser: 16-channel KITTI-like scans gave 0.31-0.47 m RMSE for correct loops on
    synthetic KITTI 00, hence 0.35 m at 64 HDL-64E rings and the 1/4 power. For the HDL-64E
    this is exactly the former ``0.35 * (64 / channels) ** 0.25`` (0.350 / 0.416 / 0.495 m at
    64 / 32 / 16 channels); VLP-16: 0.509 m; OS1-64: 0.398 m.
    """
    n = sensor.effective_beams(channels)
    # written as (fov / fov_ref) * (64 / n) so that the HDL-64E gives 64 / channels exactly
    ratio = (sensor.fov_span_deg / HDL64_FOV_SPAN_DEG) * (64.0 / n)
    return at_64 * ratio ** 0.25


def check_sequence_sensor(sequence: Any, sensor: SensorConfig) -> None:
    """Refuse a sequence whose own ``sensor`` attribute (when it has one) is another sensor.

    Raises
    ------
    SensorError
        Naming both sensors and the setting to change.
    """
    own = getattr(sequence, "sensor", None)
    if own is None:
        return
    if (own.model, own.beams) != (sensor.model, sensor.beams):
        raise SensorError(
            f"{getattr(sequence, 'name', 'the sequence')} was taken with sensor {own.model!r} ({own.beams} beams) but "
            f"the configuration's sensor is {sensor.model!r} ({sensor.beams} beams): set sensor.model: {own.model} "
            f"(--sensor {own.model})")


def frame_sensor_problem(frame: Any, sensor: SensorConfig, n_rings: int | None = None) -> str | None:
    """What in ``frame`` contradicts ``sensor`` (None when nothing does).

    Checks that ring indices / times are present when ``has_ring`` / ``has_time`` is True and
    that ring indices lie in ``0..n_rings-1`` (default: the sensor's beam count).
    """
    n = sensor.beams if n_rings is None else int(n_rings)
    if frame.ring is None:
        if sensor.has_ring:
            return "no ring indices (sensor.has_ring is true)"
    elif len(frame.ring) and (int(frame.ring.min()) < 0 or int(frame.ring.max()) >= n):
        return (f"ring indices {int(frame.ring.min())}..{int(frame.ring.max())} outside 0..{n - 1} "
                f"(sensor {sensor.model!r}, {n} rings)")
    if frame.time is None and sensor.has_time:
        return "no per-point times (sensor.has_time is true)"
    return None
