"""Synthetic LiDAR: KITTI 00's trajectory rendered through a procedural town.

- :class:`SyntheticSequence`: the LidarSequence (frames rendered on demand, ground truth).
- :mod:`.town`: the procedural scene; :mod:`.sensor`: the HDL-64E beam model and ray caster;
  :mod:`.writer`: export in KITTI layout (``python -m gr_graph.datasets.synthetic``);
  :mod:`.plots`: the pictures in ``docs/images``.
"""

from gr_graph.datasets.synthetic.sequence import SyntheticSequence

__all__ = ["SyntheticSequence"]
