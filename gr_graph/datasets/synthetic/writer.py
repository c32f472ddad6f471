"""Export a rendered sequence in the KITTI odometry layout.

::

    DIR/sequences/00/velodyne/%06d.bin   float32 x, y, z, intensity (one row per point;
                                         x, y, z only with point_format="xyz")
    DIR/sequences/00/calib.txt           P0 and Tr lines (Tr = velodyne -> camera 0)
    DIR/sequences/00/times.txt           one timestamp (s) per frame
    DIR/sequences/00/synthetic.json      how it was rendered (seeds, rings, path, source frames)
    DIR/sequences/00/times/%06d.npy      (frames with per-point times only, e.g. preset raw)
                                         float32 sweep fraction in [0, 1] per point, file order
    DIR/poses/00.txt                     ground truth in the camera-0 frame, 12 floats a row

Frames ``A:B`` of the synthetic sequence are written as files ``000000 .. B-A-1`` with the
matching rows of ``times.txt`` and ``poses/00.txt`` (the original timestamps and camera-frame
poses, not re-based), so the folder is a self-consistent KITTI sequence; ``synthetic.json``
records ``first_frame = A``. Every file is written atomically (temp file + rename).
"""

from __future__ import annotations

import io
import json
import logging
from pathlib import Path

import numpy as np

from gr_graph.atomic import atomic_write_bytes
from gr_graph.datasets.base import velo_to_cam_poses
from gr_graph.datasets.point_layout import POINT_FORMATS
from gr_graph.datasets.synthetic import rig

log = logging.getLogger(__name__)


def _fmt_rows(rows: np.ndarray) -> str:
    return "".join(" ".join(f"{v:.12e}" for v in row) + "\n" for row in np.atleast_2d(rows))


def write_kitti_layout(seq, out: Path, frames: range | None = None, seq_name: str = "00",
                       overwrite: bool = False, progress: bool = True, point_format: str = "xyzi") -> Path:
    """Render ``frames`` of ``seq`` (a SyntheticSequence) into ``out`` in KITTI layout.

    Parameters
    ----------
    seq : SyntheticSequence
        Any LidarSequence with ``gt_poses`` works; ``seed``/``n_rings`` are recorded if present.
    out : Path
        Dataset root (``DIR``).
    frames : range, optional
        Contiguous frames to write (default: all).
    overwrite : bool
        Remove existing ``.bin`` files in the target velodyne folder first; without it an
        existing, non-empty velodyne folder is an error (mixing runs gives a wrong dataset).
    progress : bool
        Show a progress bar.
    point_format : {"xyzi", "xyz"}
        ``"xyzi"``: KITTI's 16 bytes a point; ``"xyz"``: 12 bytes a point, no intensity (as
        some public datasets ship; read back with ``KittiSequence(..., point_format="xyz")``).

    Returns
    -------
    Path
        The sequence folder ``out/sequences/<seq_name>``.
    """
    from tqdm import tqdm

    if point_format not in POINT_FORMATS:
        raise ValueError(f"point_format must be one of {sorted(POINT_FORMATS)}, got {point_format!r}")
    frames = range(len(seq)) if frames is None else frames
    if frames.step != 1 or len(frames) == 0 or frames.start < 0 or frames.stop > len(seq):
        raise ValueError(f"frames must be a non-empty contiguous range within 0..{len(seq)}, got {frames}")
    if seq.gt_poses is None:
        raise ValueError("write_kitti_layout: the sequence has no ground truth to write")
    out = Path(out)
    seq_dir = out / "sequences" / seq_name
    velo = seq_dir / "velodyne"
    velo.mkdir(parents=True, exist_ok=True)
    (out / "poses").mkdir(parents=True, exist_ok=True)
    existing = sorted(velo.glob("*.bin"))
    if existing:
        if not overwrite:
            raise FileExistsError(f"{velo} already holds {len(existing)} .bin files; "
                                  "pass overwrite=True (--overwrite) to replace them")
        for f in existing:
            f.unlink()
        for f in sorted((seq_dir / "times").glob("*.npy")):
            f.unlink()

    Tr = np.asarray(seq.T_cam_velo, dtype=np.float64)
    path = getattr(seq, "path", None)
    P0 = path.P0 if path is not None else rig.P0()
    calib = f"P0: {_fmt_rows(P0.reshape(1, 12)).strip()}\nTr: {_fmt_rows(Tr[:3].reshape(1, 12)).strip()}\n"
    atomic_write_bytes(seq_dir / "calib.txt", calib.encode())
    idx = np.arange(frames.start, frames.stop)
    times = np.asarray(seq.timestamps, dtype=np.float64)[idx]
    atomic_write_bytes(seq_dir / "times.txt", "".join(f"{t:.12e}\n" for t in times).encode())
    T_cam = velo_to_cam_poses(np.asarray(seq.gt_poses, dtype=np.float64)[idx], Tr)
    atomic_write_bytes(out / "poses" / f"{seq_name}.txt", _fmt_rows(T_cam[:, :3, :].reshape(-1, 12)).encode())
    meta = {
        "generator": "gr_graph.datasets.synthetic",
        "sequence": getattr(seq, "name", type(seq).__name__),
        "seed": getattr(seq, "seed", None),
        "n_rings": getattr(seq, "n_rings", None),
        "sensor": getattr(getattr(seq, "beams", None), "sensor", None),
        "repr": repr(seq),
        "point_format": point_format,
        "first_frame": frames.start,
        "n_frames": len(frames),
        "town_seed": getattr(seq, "town_seed", None),
        "route_seed": getattr(seq, "route_seed", None),
        "trajectory": getattr(seq, "trajectory", None),
        "preset": getattr(seq, "preset", None),
        "world": getattr(seq, "world", None),
        "effects": (seq.effects.describe() if getattr(seq, "effects", None) is not None else None),
        "motion_compensated": getattr(seq, "motion_compensated", True),
        "source": path.source if path is not None else getattr(seq, "name", "sequence"),
    }
    atomic_write_bytes(seq_dir / "synthetic.json", (json.dumps(meta, indent=2) + "\n").encode())

    for k, i in enumerate(tqdm(frames, desc=f"rendering {len(frames)} frames", disable=not progress)):
        f = seq[i]
        arr = np.empty((len(f), POINT_FORMATS[point_format]), dtype=np.float32)
        arr[:, :3] = f.points
        if point_format == "xyzi":
            arr[:, 3] = f.intensity
        atomic_write_bytes(velo / f"{k:06d}.bin", arr.tobytes())
        if f.time is not None:
            tdir = seq_dir / "times"
            tdir.mkdir(exist_ok=True)
            buf = io.BytesIO()
            np.save(buf, f.time.astype(np.float32))
            atomic_write_bytes(tdir / f"{k:06d}.npy", buf.getvalue())
    log.info("wrote %d frames (%d..%d) to %s", len(frames), frames.start, frames.stop - 1, seq_dir)
    return seq_dir
