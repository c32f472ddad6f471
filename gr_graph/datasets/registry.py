"""Open a LiDAR sequence: a path of any supported format, KITTI on disk, or the synthetic sequence.

Datasets (``dataset``; ``auto`` guesses from ``path`` with :func:`guess_dataset`):

- ``kitti``: a KITTI odometry root (``sequences/XX/velodyne``, :mod:`.kitti`);
- ``kitti_raw``: a KITTI raw drive (``velodyne_points/data``, :mod:`.kitti_raw`);
- ``folder``: a folder of ``.bin``/``.pcd``/``.ply``/``.npy`` scans (:mod:`.folder`);
- ``rosbag``: a ROS1 ``.bag``, a ROS2 bag folder or a ``.mcap``/``.db3`` file (:mod:`.rosbag`);
- ``synthetic``: the rendered sequence (:mod:`.synthetic`).

Without a path, the KITTI root is looked for, in order: the ``data_root`` argument, the
environment variable ``GR_GRAPH_KITTI_ROOT``, then ``./data/kitti`` and ``~/data/kitti``; the
synthetic sequence is used when none is found. A root that is given explicitly but lacks the
sequence is an error, never a silent switch to synthetic data.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gr_graph.datasets.base import (
    DatasetError,
    LidarFrame,
    LidarSequence,
    check_index,
    find_in_chain,
    inherit_sweep_attributes,
)
from gr_graph.datasets.channels import SUPPORTED_CHANNELS, subsample_channels
from gr_graph.sensors import CUSTOM, SensorConfig, SensorError, frame_sensor_problem

if TYPE_CHECKING:
    from gr_graph.config import DataConfig

log = logging.getLogger(__name__)

KITTI_ROOT_ENV = "GR_GRAPH_KITTI_ROOT"

RENDER_PROCESS_MIN_FRAMES = 500
"""``render_process=None``: the synthetic sequence renders in a separate process when at least this many
frames are read (starting the process and building the town there cost seconds; a short read is
faster in this process, which also keeps its town for the next sequence)."""
DATASETS = ("auto", "kitti", "kitti_raw", "folder", "rosbag", "synthetic")
"""Values of ``data.dataset`` / ``--dataset``."""
_DEFAULT_ROOTS = (Path("data/kitti"), Path("~/data/kitti"))


class SequenceView:
    """A lazy view of a sequence: a frame range and/or a per-frame transform.

    Frame indices of the view are local (``0..len-1``); each frame keeps its original
    ``index`` in the parent sequence. ``gt_poses`` are the parent's, sliced (same world).

    Parameters
    ----------
    parent : LidarSequence
    start, stop : int
        The half-open frame range ``[start, stop)`` of the parent.
    transform : callable, optional
        Applied to every frame as it is read (e.g. channel subsampling).
    label : str
        Suffix appended to the parent's name.
    """

    def __init__(
        self,
        parent: LidarSequence,
        start: int = 0,
        stop: int | None = None,
        transform: Callable[[LidarFrame], LidarFrame] | None = None,
        label: str = "",
    ) -> None:
        n = len(parent)
        stop = n if stop is None else stop
        if not 0 <= start < stop <= n:
            raise DatasetError(f"{parent.name}: frame range {start}:{stop} is outside 0:{n} or empty")
        self.parent = parent
        self.start, self.stop = start, stop
        self.transform = transform
        self.name = parent.name + label
        self.timestamps = np.asarray(parent.timestamps)[start:stop]
        self.gt_poses = None if parent.gt_poses is None else np.asarray(parent.gt_poses)[start:stop]
        self.T_cam_velo = parent.T_cam_velo
        inherit_sweep_attributes(self, parent)

    def __len__(self) -> int:
        return self.stop - self.start

    def __getitem__(self, index: int) -> LidarFrame:
        frame = self.parent[self.start + check_index(index, len(self), self.name)]
        return frame if self.transform is None else self.transform(frame)

    def __iter__(self) -> Iterator[LidarFrame]:
        for i in range(len(self)):
            yield self[i]


def _split_frame_spec(text: str) -> tuple[int | None, int | None]:
    """The two integers of ``"A:B"``, None for an empty side."""
    parts = text.split(":")
    if len(parts) != 2:
        raise DatasetError(f"frames {text!r}: expected 'A:B' (B exclusive)")
    try:
        return tuple(int(p) if p.strip() else None for p in parts)  # type: ignore[return-value]
    except ValueError as exc:
        raise DatasetError(f"frames {text!r}: A and B must be integers") from exc


def parse_frames(spec: str | slice | tuple[int, int] | None, n: int | None = None) -> tuple[int, int]:
    """The one frame-range parser: ``"A:B"`` / ``slice`` / ``(A, B)`` / None -> half-open ``(A, B)``.

    Empty sides mean the start and the end (A may be empty: 0). A range that is empty or
    reaches outside ``0..n`` is an error, never silently clipped.

    Parameters
    ----------
    spec : str, slice, (int, int) or None
        The range; None is the whole sequence.
    n : int, optional
        Frames in the sequence. Without it (a configuration read before the sequence is
        opened) B must be given and only ``0 <= A < B`` is checked; the length is checked
        when the sequence is opened.

    Raises
    ------
    DatasetError
        (a ``ValueError``) naming the problem: not ``A:B``, not integers, a step, B missing
        without ``n``, an empty range or one outside the sequence.
    """
    if spec is None:
        if n is None:
            raise DatasetError("frames: None needs the sequence length")
        return 0, n
    if isinstance(spec, str):
        start, stop = _split_frame_spec(spec)
    elif isinstance(spec, slice):
        if spec.step not in (None, 1):
            raise DatasetError("frames: steps other than 1 are not supported")
        start, stop = spec.start, spec.stop
    else:
        start, stop = spec
    for side in (start, stop):  # int() would floor 1.5 and read true as 1
        if side is not None and (isinstance(side, bool) or not isinstance(side, (int, np.integer))):
            raise DatasetError(f"frames {spec!r}: A and B must be integers")
    start = 0 if start is None else int(start)
    if stop is None and n is None:
        raise DatasetError(f"frames {spec!r}: B is needed here (A:B, B exclusive)")
    stop = n if stop is None else int(stop)
    if n is None:
        if not 0 <= start < stop:
            raise DatasetError(f"frames {start}:{stop}: need 0 <= A < B")
    elif not 0 <= start < stop <= n:
        raise DatasetError(f"frames {start}:{stop}: need 0 <= A < B <= {n} (the sequence has {n} frames)")
    return start, stop


def find_kitti_root(seq: str, data_root: str | os.PathLike[str] | None = None) -> Path | None:
    """Return the KITTI root holding ``sequences/<seq>/velodyne``, or None when none is found.

    Raises
    ------
    DatasetError
        If ``data_root`` (or ``$GR_GRAPH_KITTI_ROOT``) is given but lacks the sequence.
    """
    explicit = data_root if data_root is not None else os.environ.get(KITTI_ROOT_ENV)
    if explicit:
        root = Path(explicit).expanduser()
        if not (root / "sequences" / seq / "velodyne").is_dir():
            raise DatasetError(f"{root}: no sequences/{seq}/velodyne (given as the KITTI root)")
        return root
    for candidate in _DEFAULT_ROOTS:
        root = candidate.expanduser()
        if (root / "sequences" / seq / "velodyne").is_dir():
            return root
    return None


def _is_kitti_velodyne_folder(p: Path) -> bool:
    """Whether ``p`` is the ``velodyne`` folder of a KITTI odometry sequence (``sequences/XX/velodyne``,
    beside its ``calib.txt``): read as that sequence, with its calibration and ground truth, not as a
    plain folder of scans."""
    return p.name == "velodyne" and p.parent.parent.name == "sequences" and (p.parent / "calib.txt").is_file()


def guess_dataset(path: str | os.PathLike[str]) -> str:
    """The dataset kind of a path (one of :data:`DATASETS` but ``auto`` and ``synthetic``).

    A ``.bag``/``.mcap``/``.db3`` file or a folder with ``metadata.yaml``: ``rosbag``; a folder
    with ``sequences/`` (or a ``sequences/XX`` folder with ``velodyne/``, or that ``velodyne`` folder itself):
    ``kitti``; a folder
    with ``velodyne_points/data`` (or ``velodyne_points`` itself): ``kitti_raw``; a folder of
    point files: ``folder`` (hidden files such as macOS ``._x.pcd`` do not count, as in
    :func:`gr_graph.datasets.folder.point_files`).

    Raises
    ------
    DatasetError
        Naming the path and what was looked for, when it matches none.
    """
    from gr_graph.datasets.kitti_raw import is_kitti_raw_drive
    from gr_graph.datasets.point_files import POINT_FILE_SUFFIXES
    from gr_graph.datasets.rosbag import BAG_SUFFIXES, is_bag

    p = Path(path).expanduser()
    if not p.exists():
        raise DatasetError(f"{p}: no such file or folder")
    if is_bag(p):
        return "rosbag"
    if p.is_dir():
        if (p / "sequences").is_dir() or ((p / "velodyne").is_dir() and p.parent.name == "sequences") \
                or _is_kitti_velodyne_folder(p):
            return "kitti"
        if is_kitti_raw_drive(p) or (p.name == "velodyne_points" and (p / "data").is_dir()):
            return "kitti_raw"
        if any(c.is_file() and c.suffix.lower() in POINT_FILE_SUFFIXES and not c.name.startswith(".")
               for c in p.iterdir()):
            return "folder"
    elif p.suffix.lower() in POINT_FILE_SUFFIXES:
        raise DatasetError(f"{p}: a single scan; give the folder holding the scans")
    raise DatasetError(
        f"{p}: not a recognised dataset (looked for a ROS bag: {'/'.join(BAG_SUFFIXES)} or a folder with "
        "metadata.yaml; a KITTI odometry root with sequences/; a KITTI raw drive with velodyne_points/data; "
        f"a folder of {'/'.join(POINT_FILE_SUFFIXES)} scans); pass --dataset to say which"
    )


OPTION_KINDS: dict[str, tuple[str, ...]] = {
    "seq": ("kitti", "synthetic"),
    "data_root": ("kitti",),
    "topic": ("rosbag",),
    "timestamps": ("folder",),
    "poses": ("folder", "rosbag"),
    "point_format": ("kitti", "kitti_raw", "folder"),
    "route_seed": ("synthetic",),
    "synthetic_preset": ("synthetic",),
}
"""The kinds of data (:data:`DATASETS`) each ``data`` option concerns; the others ignore it, with
a warning (:func:`ignored_options`). ``trajectory`` is missing: with other data it is an error."""
def ignored_options(kind: str, **given: object) -> list[str]:
    """The options among ``given`` (``data`` keys of :data:`OPTION_KINDS` and their values) that
    were set to something other than their default but that data of ``kind`` ignores, as
    ``key=value`` strings in :data:`OPTION_KINDS`' order.

    A value equal to its default (``gr_graph.config.DataConfig``'s) cannot be told from one not given,
    and is never listed.
    """
    from gr_graph.config import DataConfig  # (the configuration imports this module)

    unknown = set(given) - set(OPTION_KINDS)
    if unknown:
        raise KeyError(f"not data options of OPTION_KINDS: {sorted(unknown)}")
    return [f"{key}={given[key]}" for key, kinds in OPTION_KINDS.items()
            if key in given and given[key] is not None and given[key] != DataConfig.model_fields[key].default
            and kind not in kinds]


def warn_ignored_options(kind: str, **given: object) -> list[str]:
    """Log one warning naming the options :func:`ignored_options` finds for data of ``kind``
    (e.g. ``--synthetic-preset`` given with a bag, ``--topic`` with a folder); returns them."""
    ignored = ignored_options(kind, **given)
    if ignored:
        log.warning("ignored for %s data (they concern other kinds of data): %s", kind, ", ".join(ignored))
    return ignored


def _open_path(kind: str, p: Path, point_format: str, topic: str | None, timestamps: str | None,
               poses: str | None, sensor: SensorConfig | None = None) -> tuple[LidarSequence, str]:
    """Open a ``kitti_raw``, ``folder`` or ``rosbag`` path."""
    if kind == "kitti_raw":
        from gr_graph.datasets.kitti_raw import KittiRawSequence

        drive = p.parent if p.name == "velodyne_points" else p
        seq: LidarSequence = KittiRawSequence(drive, point_format=point_format, sensor=sensor)
        source = f"KITTI raw drive {drive}"
    elif kind == "folder":
        from gr_graph.datasets.folder import FolderSequence

        folder_seq = FolderSequence(p, point_format=point_format, timestamps=timestamps, poses=poses,
                                    sensor=sensor)
        seq = folder_seq
        source = f"folder {p} ({len(folder_seq)} {folder_seq.files[0].suffix} files)"
    elif kind == "rosbag":
        from gr_graph.datasets.rosbag import RosbagSequence

        bag = RosbagSequence(p, topic=topic, poses=poses, sensor=sensor)
        seq = bag
        source = f"bag {p}, topic {bag.topic}"
    else:
        raise DatasetError(f"dataset {kind!r} takes no path here")
    extras = []
    if getattr(seq, "gt_poses", None) is not None:
        extras.append("ground truth")
    if not getattr(seq, "motion_compensated", True):
        extras.append("per-point times" if kind != "kitti_raw" else "not motion-compensated")
    return seq, source + (f" ({', '.join(extras)})" if extras else "")


def open_sequence(
    seq: str = "00",
    data_root: str | os.PathLike[str] | None = None,
    channels: int | None = None,
    frames: str | slice | tuple[int, int] | None = None,
    synthetic_seed: int = 0,
    point_format: str = "xyzi",
    kitti_vertical_correction_deg: float = 0.0,
    route_seed: int = 0,
    trajectory: str | os.PathLike[str] | None = None,
    synthetic_preset: str | None = None,
    path: str | os.PathLike[str] | None = None,
    dataset: str = "auto",
    topic: str | None = None,
    timestamps: str | os.PathLike[str] | None = None,
    poses: str | os.PathLike[str] | None = None,
    sensor: SensorConfig | str | None = None,
    render_process: bool | None = False,
) -> tuple[LidarSequence, str]:
    """Open a sequence for SLAM: ``path`` of any supported format, else KITTI if a root is given or
    found, else the synthetic sequence.

    Parameters
    ----------
    path : path, optional
        A dataset of any kind of :data:`DATASETS` (guessed unless ``dataset`` says); a KITTI
        odometry root here is the same as ``data_root``.
    dataset : str
        One of :data:`DATASETS`; ``auto`` guesses from ``path`` (without a path: KITTI when a
        root is found, else synthetic).
    topic : str, optional
        Bags: the ``sensor_msgs/PointCloud2`` topic (needed when there are several).
    timestamps, poses : path, optional
        Folders of scans: timestamps and ground-truth poses files (bags: poses only); see
        :mod:`gr_graph.datasets.folder`.
    seq : str
        KITTI sequence name. The synthetic fallback exists for ``"00"`` only.
    data_root : path, optional
        KITTI odometry root; see the module docstring for where else it is looked for.
    channels : {64, 32, 16}, optional
        Keep every 1st / 2nd / 4th laser ring of a 64-beam sensor; None (default): every ring
        of the sensor.
    frames : "A:B", slice or (A, B), optional
        Frame range.
    synthetic_seed : int
        Seed of the synthetic town and noise.
    route_seed : int
        Seed of the synthetic sequence's generated route.
    trajectory : path, optional
        Render the synthetic sequence along this trajectory (KITTI/TUM pose file or KITTI
        root) instead of the generated route.
    point_format : {"xyzi", "xyz"}
        Layout of the KITTI ``.bin`` files: float32 x, y, z, intensity (KITTI) or x, y, z
        (12 bytes a point). Unused by the synthetic sequence.
    kitti_vertical_correction_deg : float
        KITTI and the synthetic sequence: raise every point's elevation by this angle (see
        :func:`gr_graph.datasets.kitti.correct_vertical_angle`; the ``kitti`` and ``raw``
        presets' sensors point 0.22 deg higher than their calibration says, like KITTI's
        HDL-64E); 0 reads the scans unchanged. Given for other recordings (a KITTI raw drive, a folder,
        a bag), it is applied to them too, and the description says so.
    synthetic_preset : str, optional
        Preset of the synthetic sequence, its world and sensor effects (``clean``, ``kitti``,
        ``raw``; default: ``kitti``, see
        :data:`gr_graph.datasets.synthetic.sequence.DEFAULT_PRESET`). Ignored for KITTI data.
    sensor : SensorConfig or str, optional
        The sensor (a ``SensorConfig`` or a catalogue name; default: the HDL-64E). The synthetic
        sequence renders with its beam model (catalogue models only); a KITTI-layout folder is
        read with its beam count (ring recovery expects ``n_beams`` scan lines). Frames are
        checked against its ``has_ring`` / ``has_time``. The view's ``sensor`` attribute.
    render_process : bool or None
        The synthetic sequence: render the frames in a separate process, ahead of the reads
        (:mod:`gr_graph.datasets.synthetic.render_process`; the same frames); None: when
        :data:`RENDER_PROCESS_MIN_FRAMES` or more are read. Other sequences ignore it.

    Returns
    -------
    (sequence, description)
        The sequence and a one-line description of where it comes from.
    """
    if channels is not None and channels not in SUPPORTED_CHANNELS:
        raise DatasetError(f"channels must be one of {SUPPORTED_CHANNELS} (or None: all), got {channels}")
    try:
        sensor = (SensorConfig() if sensor is None else SensorConfig(model=sensor) if isinstance(sensor, str)
                  else sensor)
        n_rings = sensor.effective_beams(channels)
    except (SensorError, ValueError) as exc:
        raise DatasetError(f"sensor: {exc}") from None
    if dataset not in DATASETS:
        raise DatasetError(f"dataset must be one of {DATASETS}, got {dataset!r}")
    seq = f"{int(seq):02d}" if str(seq).isdigit() else str(seq)
    base: LidarSequence
    kind = dataset
    if path is not None:
        p = Path(path).expanduser()
        kind = guess_dataset(p) if dataset == "auto" else dataset
        if not p.exists():
            raise DatasetError(f"{p}: no such file or folder")
        if kind == "synthetic":
            raise DatasetError(f"the synthetic sequence takes no path (got {p}); drop it or pick another --dataset")
        if kind == "kitti":
            if _is_kitti_velodyne_folder(p):  # sequences/XX/velodyne: its sequence folder
                p = p.parent
            if (p / "velodyne").is_dir() and p.parent.name == "sequences":
                p, seq = p.parent.parent, p.name
            data_root = p
        else:
            warn_ignored_options(kind, seq=seq, data_root=data_root, topic=topic, timestamps=timestamps, poses=poses,
                                 point_format=point_format, route_seed=route_seed,
                                 synthetic_preset=synthetic_preset)
            if trajectory is not None:
                raise DatasetError(f"a trajectory ({trajectory}) renders the synthetic sequence; "
                                   f"it cannot be combined with {p}")
            base, source = _open_path(kind, p, point_format, topic, None if timestamps is None else str(timestamps),
                                      None if poses is None else str(poses), sensor)
            if kitti_vertical_correction_deg:  # asked for: applied (a KITTI raw drive is the HDL-64E's data too)
                base, source = _vertical_corrected(base, source, float(kitti_vertical_correction_deg))
            return _view(base, source, frames, sensor, n_rings)
    elif kind in ("kitti_raw", "folder", "rosbag"):
        raise DatasetError(f"dataset {kind!r} needs a path (python -m gr_graph.slam PATH, or data.path)")
    root = None if kind == "synthetic" else find_kitti_root(seq, data_root)
    if kind == "kitti" and root is None:
        raise DatasetError(f"dataset 'kitti': no KITTI root with sequence {seq} found "
                           f"(pass a path or --data-root, or set {KITTI_ROOT_ENV})")
    if kind == "synthetic" and data_root is not None:
        raise DatasetError(f"dataset 'synthetic' with a KITTI root ({data_root}): pick one")
    if root is not None and trajectory is not None:
        raise DatasetError(f"a trajectory ({trajectory}) renders the synthetic sequence; "
                           f"it cannot be combined with the KITTI root {root}")
    warn_ignored_options("synthetic" if root is None else "kitti", seq=seq, topic=topic, timestamps=timestamps,
                         poses=poses, point_format=point_format, route_seed=route_seed,
                         synthetic_preset=synthetic_preset)
    if root is not None:
        from gr_graph.datasets.kitti import KittiSequence

        base = KittiSequence(root, seq, point_format=point_format, n_rings=sensor.beams,
                             vertical_correction_deg=kitti_vertical_correction_deg,
                             recover_ring_index=sensor.has_ring is not False, per_point_times=sensor.has_time is not False)
        source = f"KITTI sequence {seq} from {root}" + ("" if point_format == "xyzi" else f" ({point_format} points)")
        if kitti_vertical_correction_deg:
            source += f", vertical-angle correction {kitti_vertical_correction_deg:g} deg"
        if sensor.model != "hdl64e":
            source += f", sensor {sensor.model} ({sensor.beams} beams)"
    else:
        if seq != "00":
            raise DatasetError(
                f"no KITTI root with sequence {seq} found (pass --data-root or set {KITTI_ROOT_ENV}); "
                "the synthetic fallback exists for sequence 00 only"
            )
        from gr_graph.datasets.synthetic import SyntheticSequence

        if sensor.model == CUSTOM:
            raise DatasetError("the synthetic sequence renders catalogue sensors only (sensor.model: "
                               "hdl64e, vlp16, os1-64), not a custom sensor")
        # fewer channels: only the kept rings are cast. Each ray keeps its draws from the full beam
        # grid, so the frames equal those of every ring rendered and subsampled, bit for bit (tested),
        # in a third of the time at 16 channels
        synth = SyntheticSequence(seed=synthetic_seed, route_seed=route_seed, trajectory=trajectory,
                                  preset=synthetic_preset, sensor=sensor.model,
                                  n_rings=n_rings if n_rings < sensor.beams else None)
        base = synth
        start, stop = parse_frames(frames, len(synth))
        if render_process or (render_process is None and stop - start >= RENDER_PROCESS_MIN_FRAMES):
            from gr_graph.datasets.synthetic.render_process import RenderProcessSequence

            base = RenderProcessSequence(synth)
        source = (
            f"no KITTI root given or found: using the {synth.preset!r} preset of the synthetic world (ray cast "
            f"along {synth.path.source}, town seed {synthetic_seed}, the {synth.world} world"
            f"{' with moving actors' if synth.actors_config is not None else ''}, {synth.beams.describe()}, "
            f"sensor effects: "
            f"{synth.effects.describe()})"
        )
        if kitti_vertical_correction_deg:  # the presets' sensors carry KITTI's vertical-angle error too
            base, source = _vertical_corrected(base, source, float(kitti_vertical_correction_deg))
    return _view(base, source, frames, sensor, n_rings)


def _vertical_corrected(base: LidarSequence, source: str, angle_deg: float) -> tuple[LidarSequence, str]:
    """``base`` with every point's elevation raised by ``angle_deg`` (``data.kitti_vertical_correction_deg``)
    as it is read, and its description saying so."""
    from gr_graph.datasets.kitti import correct_vertical_angle

    view = SequenceView(base, transform=lambda f: replace(f, points=correct_vertical_angle(f.points, angle_deg)))
    return view, source + f", vertical-angle correction {angle_deg:g} deg"


def _check_scan_sizes(base: LidarSequence, start: int, stop: int) -> None:
    """Refuse, when a sequence of scan files opens, one in frames ``start:stop`` cut short: a ``.bin``
    whose size does not fit its point format (:func:`~gr_graph.datasets.point_layout.check_bin_sizes`),
    a binary PCD / PLY or a ``.npy`` with fewer data than its header promises
    (:func:`~gr_graph.datasets.point_files.check_scan_sizes`). The run would otherwise stop only when
    SLAM reaches it. Files outside the range are not looked at (``--frames`` is how a drive with a
    scan cut short at its end is still run)."""
    from gr_graph.datasets.point_files import check_scan_sizes
    from gr_graph.datasets.point_layout import check_bin_sizes

    owner = find_in_chain(base, "files", accept=lambda f: isinstance(f, list) and len(f) == len(base))
    if owner is None or not owner.files:
        return
    if owner.files[0].suffix.lower() == ".bin":
        check_bin_sizes(owner.files[start:stop], getattr(owner, "point_format", "xyzi"))
    else:
        check_scan_sizes(owner.files[start:stop])


def _view(base: LidarSequence, source: str, frames: str | slice | tuple[int, int] | None,
          sensor: SensorConfig, n_rings: int) -> tuple[LidarSequence, str]:
    """The frame range and channel subsampling (to ``n_rings`` of ``sensor``'s beams) of ``base``
    as a :class:`SequenceView` whose ``sensor`` is ``sensor``; frames are checked against it."""
    start, stop = parse_frames(frames, len(base))
    name = base.name
    _check_scan_sizes(base, start, stop)
    if sensor.frame_stamp is not None and getattr(base, "stamps_moved_by_s", None) is None:
        log.warning("%s: sensor.frame_stamp (%s) is read by the folder and bag loaders only; these data keep their "
                    "stamps (KITTI's mark the sweep's middle, the synthetic world's too)", source, sensor.frame_stamp)

    named = sensor.named_beams is not None

    def transform(frame: LidarFrame) -> LidarFrame:
        # a named sensor bounds the ring indices; the default (nothing said) does not: the loader
        # counted the data's rings (a 128-ring recording is no error)
        problem = frame_sensor_problem(frame, sensor, None if named else max(int(frame.n_rings), sensor.beams))
        if problem is not None:
            raise DatasetError(f"{name}, frame {frame.index}: {problem}")
        if n_rings in (sensor.beams, frame.n_rings):  # all rings, or a source that made only the kept ones
            return frame
        if frame.ring is None:
            raise DatasetError(f"{name}, frame {frame.index}: no ring indices, cannot keep {n_rings} of {sensor.beams} "
                               "channels: the data has no per-point ring field ('ring') and its rings could not be "
                               "recovered; leave --channels out, or add the field")
        if frame.n_rings != sensor.beams:
            raise DatasetError(f"{name}, frame {frame.index}: {frame.n_rings} rings, but --channels keeps one ring "
                               f"in {sensor.beams // n_rings} of a {sensor.beams}-beam sensor ({sensor.model}): "
                               "name the sensor that took the data (--sensor), or leave --channels out")
        return subsample_channels(frame, n_rings)

    label = "" if n_rings == sensor.beams else f"-{n_rings}ch"
    view = SequenceView(base, start, stop, transform, label)
    view.sensor = sensor
    counted = None if named else counted_rings(base)
    rings = f"{n_rings} channels"
    if counted not in (None, sensor.beams):  # the default sensor's figures (thresholds) apply to other data
        rings += f" ({counted} rings in the data; no sensor named: the {sensor.model}'s figures apply)"
    return view, f"{source}, frames {start}:{stop}, {rings}"


def counted_rings(sequence: LidarSequence) -> int | None:
    """The rings a folder or bag loader counted in the data (``conventions.n_rings``), None when the
    sequence has no such count (KITTI, the synthetic world; no ring field; a named sensor's beams)."""
    from gr_graph.datasets.frame_fields import FieldConventions

    owner = find_in_chain(sequence, "conventions", accept=lambda c: isinstance(c, FieldConventions))
    if owner is None:
        return None
    conv = owner.conventions
    return int(conv.n_rings) if conv.has_ring and not conv.fixed_rings else None


def open_configured_sequence(data: DataConfig, synthetic_seed: int = 0,
                             sensor: SensorConfig | None = None) -> tuple[LidarSequence, str]:
    """:func:`open_sequence` with the fields of a ``gr_graph.config.DataConfig`` (``cfg.data``)
    and the ``sensor`` section (``cfg.sensor``; default: the HDL-64E).

    The one place that maps the ``data`` config section to a sequence, so that a key added
    there (e.g. ``point_format``) reaches the loader from every caller.
    """
    return open_sequence(seq=data.seq, data_root=data.data_root, channels=data.channels, frames=data.frames,
                         synthetic_seed=synthetic_seed, point_format=data.point_format,
                         kitti_vertical_correction_deg=data.kitti_vertical_correction_deg,
                         route_seed=data.route_seed, trajectory=data.trajectory,
                         synthetic_preset=data.synthetic_preset, path=data.path, dataset=data.dataset,
                         topic=data.topic, timestamps=data.timestamps, poses=data.poses, sensor=sensor,
                         render_process=data.render_process)
