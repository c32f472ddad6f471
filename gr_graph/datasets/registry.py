"""Open a LiDAR sequence by name: KITTI on disk when present, the synthetic sequence otherwise.

The KITTI root is looked for, in order: the ``data_root`` argument, the environment variable
``GR_GRAPH_KITTI_ROOT``, then ``./data/kitti`` and ``~/data/kitti``. A root that is given
explicitly but lacks the sequence is an error, never a silent switch to synthetic data.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gr_graph.datasets.base import DatasetError, LidarFrame, LidarSequence, check_index, inherit_sweep_attributes
from gr_graph.datasets.channels import SUPPORTED_CHANNELS, subsample_channels

if TYPE_CHECKING:
    from gr_graph.config import DataConfig

log = logging.getLogger(__name__)

KITTI_ROOT_ENV = "GR_GRAPH_KITTI_ROOT"
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


def open_sequence(
    seq: str = "00",
    data_root: str | os.PathLike[str] | None = None,
    channels: int = 64,
    frames: str | slice | tuple[int, int] | None = None,
    synthetic_seed: int = 0,
    point_format: str = "xyzi",
    kitti_vertical_correction_deg: float = 0.0,
    route_seed: int = 0,
    trajectory: str | os.PathLike[str] | None = None,
    synthetic_preset: str | None = None,
) -> tuple[LidarSequence, str]:
    """Open a sequence for SLAM: KITTI if a root is given or found, else the synthetic sequence.

    Parameters
    ----------
    seq : str
        KITTI sequence name. The synthetic fallback exists for ``"00"`` only.
    data_root : path, optional
        KITTI odometry root; see the module docstring for where else it is looked for.
    channels : {64, 32, 16}
        Keep every 1st / 2nd / 4th laser ring.
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
        KITTI only: elevation correction of every point (see
        :func:`gr_graph.datasets.kitti.correct_vertical_angle`); 0 reads the scans unchanged.
    synthetic_preset : str, optional
        Preset of the synthetic sequence, its world and sensor effects (``clean``, ``kitti``,
        ``raw``; default: ``kitti``, see
        :data:`gr_graph.datasets.synthetic.sequence.DEFAULT_PRESET`). Ignored for KITTI data.

    Returns
    -------
    (sequence, description)
        The sequence and a one-line description of where it comes from.
    """
    if channels not in SUPPORTED_CHANNELS:
        raise DatasetError(f"channels must be one of {SUPPORTED_CHANNELS}, got {channels}")
    seq = f"{int(seq):02d}" if str(seq).isdigit() else str(seq)
    root = find_kitti_root(seq, data_root)
    base: LidarSequence
    if root is not None and trajectory is not None:
        raise DatasetError(f"a trajectory ({trajectory}) renders the synthetic sequence; "
                           f"it cannot be combined with the KITTI root {root}")
    if root is not None:
        from gr_graph.datasets.kitti import KittiSequence

        base = KittiSequence(root, seq, point_format=point_format,
                             vertical_correction_deg=kitti_vertical_correction_deg)
        source = f"KITTI sequence {seq} from {root}" + ("" if point_format == "xyzi" else f" ({point_format} points)")
        if kitti_vertical_correction_deg:
            source += f", vertical-angle correction {kitti_vertical_correction_deg:g} deg"
    else:
        if seq != "00":
            raise DatasetError(
                f"no KITTI root with sequence {seq} found (pass --data-root or set {KITTI_ROOT_ENV}); "
                "the synthetic fallback exists for sequence 00 only"
            )
        from gr_graph.datasets.synthetic import SyntheticSequence

        if point_format != "xyzi":
            log.warning("point_format %r concerns KITTI .bin files; without a KITTI root it has no effect",
                        point_format)
        if kitti_vertical_correction_deg:
            log.warning("kitti_vertical_correction_deg %g concerns KITTI .bin files; without a KITTI root it has "
                        "no effect", kitti_vertical_correction_deg)
        synth = SyntheticSequence(seed=synthetic_seed, route_seed=route_seed, trajectory=trajectory,
                                  preset=synthetic_preset)
        base = synth
        source = (
            f"no KITTI root given or found: using the {synth.preset!r} preset of the synthetic world (ray cast "
            f"along {synth.path.source}, town seed {synthetic_seed}, the {synth.world} world"
            f"{' with moving actors' if synth.actors_config is not None else ''}, sensor effects: "
            f"{synth.effects.describe()})"
        )
    start, stop = parse_frames(frames, len(base))
    transform = None if channels == 64 else (lambda f: subsample_channels(f, channels))
    label = "" if channels == 64 else f"-{channels}ch"
    view = SequenceView(base, start, stop, transform, label)
    return view, f"{source}, frames {start}:{stop}, {channels} channels"


def open_configured_sequence(data: DataConfig, synthetic_seed: int = 0) -> tuple[LidarSequence, str]:
    """:func:`open_sequence` with the fields of a ``gr_graph.config.DataConfig`` (``cfg.data``).

    The one place that maps the ``data`` config section to a sequence, so that a key added
    there (e.g. ``point_format``) reaches the loader from every caller.
    """
    return open_sequence(seq=data.seq, data_root=data.data_root, channels=data.channels, frames=data.frames,
                         synthetic_seed=synthetic_seed, point_format=data.point_format,
                         kitti_vertical_correction_deg=data.kitti_vertical_correction_deg,
                         route_seed=data.route_seed, trajectory=data.trajectory,
                         synthetic_preset=data.synthetic_preset)
