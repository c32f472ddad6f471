"""How much of a pure change of sensor attitude a registration recovers: two renders from one spot.

The clean synthetic world (no sensor effects, exact poses) is rendered from a route pose and
from the same position with the sensor tilted by a known angle about its y axis (pitch) or x
axis (roll). The tilted scan is registered onto the other with the loop verification's last
stage (``preprocess`` at its defaults, small_gicp GICP, correspondences within 1 m), started
from the true relative pose. Reported per channel count: the fraction of the tilt the registration
recovers (1 = unbiased; 0 = it returns the identity whatever the tilt), and the same for the
ground planes of the two preprocessed scans (:func:`gr_graph.ground_tilt.fit_ground_plane`, the
tilt that maps one plane onto the other), mean ± std over the spots.

Usage::

    python benchmarks/tilt_bias_study.py [--channels 16 32 64] [--spots 8] [--tilt-deg 0.25 0.5] [--write]
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_io import print_and_write  # noqa: E402


def spot_fractions(sequence: Any, frame: int, axis: int, tilt_rad: float) -> tuple[float, float]:
    """(registration, ground) fractions of a ``tilt_rad`` tilt about sensor axis ``axis`` recovered at ``frame``."""
    import small_gicp

    from factors.se3 import exp_so3, log_so3
    from gr_graph.config import PreprocessConfig
    from gr_graph.datasets.synthetic.sensor import render_scan
    from gr_graph.datasets.synthetic.sequence import get_town_and_scene
    from gr_graph.ground_tilt import fit_ground_plane, tilt_offset
    from gr_graph.preprocess import preprocess_scan

    town, scene = get_town_and_scene(sequence.town_seed, sequence.path, sequence.town_config)
    T_target = np.asarray(sequence.gt_poses[frame], np.float64)
    w = np.zeros(3)
    w[axis] = tilt_rad
    T_source = T_target.copy()
    T_source[:3, :3] = T_target[:3, :3] @ exp_so3(w)

    def render(T: np.ndarray, k: int) -> np.ndarray:
        return render_scan(scene, town.albedo, town.material, T, sequence.beams, sequence.noise,
                           sequence.frame_rng(frame * 2 + k))[0]

    source, target = render(T_source, 0), render(T_target, 1)
    cfg = PreprocessConfig()
    s, t = preprocess_scan(source, cfg), preprocess_scan(target, cfg)
    truth = np.linalg.inv(T_target) @ T_source
    res = small_gicp.align(t.cloud, s.cloud, t.tree, init_T_target_source=truth, registration_type="GICP",
                           max_correspondence_distance=1.0, max_iterations=30)
    registered = log_so3(np.asarray(res.T_target_source)[:3, :3])[axis]
    ps, pt = fit_ground_plane(s.points), fit_ground_plane(t.points)  # the scans as SLAM stores them
    ground = float("nan")
    if ps is not None and pt is not None:  # the rotation that maps the source's ground onto the target's
        ground = tilt_offset(np.eye(4), ps.normal, pt.normal)[axis]
    return float(registered / tilt_rad), float(ground / tilt_rad)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--channels", type=int, nargs="+", default=[16, 32, 64])
    ap.add_argument("--spots", type=int, default=8, help="route frames, spread evenly over the route")
    ap.add_argument("--tilt-deg", type=float, nargs="+", default=[0.25, 0.5])
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/tilt_bias_study.md / .json")
    args = ap.parse_args(argv)
    from tqdm import tqdm

    from gr_graph.datasets.synthetic import SyntheticSequence

    rows: list[dict[str, Any]] = []
    for channels in args.channels:
        sequence = SyntheticSequence(seed=0, preset="clean", n_rings=channels)
        frames = np.linspace(100, len(sequence.gt_poses) - 100, args.spots).astype(int)
        for tilt in args.tilt_deg:
            for axis, name in ((1, "pitch"), (0, "roll")):
                got = np.array([spot_fractions(sequence, int(f), axis, np.radians(tilt))
                                for f in tqdm(frames, desc=f"{channels} ch, {name} {tilt:g} deg", leave=False)])
                rows.append({"channels": channels, "axis": name, "tilt_deg": tilt, "frames": frames.tolist(),
                             "registration_fraction": got[:, 0].tolist(), "ground_fraction": got[:, 1].tolist()})
    lines = ["| channels | axis | tilt [deg] | registration recovers | ground planes recover |", "|---|---|---|---|---|"]
    for r in rows:
        reg, gnd = np.array(r["registration_fraction"]), np.array(r["ground_fraction"])
        gnd = gnd[np.isfinite(gnd)]
        lines.append(f"| {r['channels']} | {r['axis']} | {r['tilt_deg']:g} | {reg.mean():.2f} ± {reg.std(ddof=1):.2f} | "
                     f"{gnd.mean():.2f} ± {gnd.std(ddof=1):.2f} ({len(gnd)} of {len(reg)}) |")
    command = shlex.join(["python", "benchmarks/tilt_bias_study.py", *(sys.argv[1:] if argv is None else argv)])
    text = ("# A pure change of sensor attitude: how much of it registration and the ground planes recover\n\n"
            f"Command: `{command}`. The clean synthetic world (route seed 0), each spot rendered twice from one "
            "position, the second time tilted by the angle given; fraction recovered, mean ± std over the spots "
            "(1: unbiased).\n\n" + "\n".join(lines) + "\n")
    print_and_write("tilt_bias_study", text, {"rows": rows}, args.write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
