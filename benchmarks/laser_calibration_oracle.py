"""SLAM on the `kitti` preset with the sensor's per-laser errors removed (not a test).

The `kitti` preset draws per-laser intrinsic errors for its sensor (elevation and azimuth
0.03 deg, range offset 1.5 cm, range scale 5e-4, Gaussian sigmas) on top of the global 0.22 deg
vertical offset (``gr_graph.datasets.synthetic.effects.CalibrationErrors``). This runs
``python -m gr_graph.slam`` unchanged except that the drawn per-laser errors are replaced:

- ``global_only``: every per-laser error zero, the global vertical offset kept (so
  ``--kitti-vertical-correction 0.22`` removes the sensor's whole angular error);
- ``no_elevation``: the per-laser elevation errors zero, the rest kept;
- ``no_range``: the range offsets and scales zero, the angles kept.

The other effects, the world and every noise draw stay as they are (the per-laser draw has its
own generator). Compare the output with a plain run of the same arguments, e.g. with
``benchmarks/loop_variance_study.py``: how much of the drift and of the NEES comes from the
per-laser errors, which no noise model of independent edge errors can describe.

Run::

    python benchmarks/laser_calibration_oracle.py global_only -- --frames 0:1500 --channels 16 \\
        --synthetic-preset kitti --seed 1 --rounds 0 --kitti-vertical-correction 0.22 --out OUT

Uses ground-truth knowledge of the simulated sensor: a diagnosis, never a SLAM setting. The
output folder's ``config.yaml`` names the `kitti` preset all the same (and a learning round's
frame cache in ``OUT/frames`` holds the changed frames): keep such folders apart from real runs.
"""

from __future__ import annotations

import sys

import numpy as np

MODES = ("global_only", "no_elevation", "no_range")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2 or argv[0] not in MODES or argv[1] != "--":
        raise SystemExit(f"usage: laser_calibration_oracle.py {{{','.join(MODES)}}} -- <gr_graph.slam arguments>")
    mode, slam_args = argv[0], argv[2:]

    import gr_graph.datasets.synthetic.sequence as sequence
    from gr_graph.datasets.synthetic.effects import LaserCalibration, draw_laser_calibration
    from gr_graph.slam import main as slam_main

    def drawn_without_errors(cfg, seed: int, n_beams: int = 64) -> LaserCalibration:
        drawn = draw_laser_calibration(cfg, seed, n_beams=n_beams)
        zero = np.zeros_like(drawn.elevation_rad)
        global_offset = zero + np.radians(cfg.vertical_offset_deg)
        if mode == "global_only":
            return LaserCalibration(global_offset, zero, zero, zero)
        if mode == "no_elevation":
            return LaserCalibration(global_offset, drawn.azimuth_rad, drawn.range_offset_m, drawn.range_scale)
        return LaserCalibration(drawn.elevation_rad, drawn.azimuth_rad, zero, zero)

    sequence.draw_laser_calibration = drawn_without_errors  # the name the sequence calls
    return slam_main(slam_args)


if __name__ == "__main__":
    sys.exit(main())
