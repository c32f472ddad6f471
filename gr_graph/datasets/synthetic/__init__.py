"""Synthetic LiDAR: the project's own generated route rendered through a procedural town.

- :class:`SyntheticSequence`: the LidarSequence (frames rendered on demand, ground truth).
- :mod:`.route`: the route (street grid, speeds, stops, revisits) from a route seed;
  :mod:`.path`: the route or a given trajectory (``--trajectory``) as the sensor path;
  :mod:`.rig`: the rig's own calibration (``T_cam_velo``, ``P0``).
- :mod:`.town`: the procedural scene; :mod:`.sensor`: the HDL-64E beam model and ray caster;
  :mod:`.effects`: the sensor effects and the presets ``clean``, ``kitti``, ``raw``;
  :mod:`.writer`: export in KITTI layout (``python -m gr_graph.datasets.synthetic``);
  :mod:`.plots`: the pictures in ``docs/images``.
"""

from gr_graph.datasets.synthetic.sequence import SyntheticSequence

__all__ = ["SyntheticSequence"]
