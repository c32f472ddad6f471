"""gr_graph: LiDAR SLAM with self-supervised geometry reasoning.

See the README and ``../shared/paper`` for the method. Sub-packages:

- :mod:`gr_graph.datasets`: KITTI loader, channel subsampling, synthetic KITTI-00 renderer.
- :mod:`gr_graph.memory`: the on-disk memory M = (scans, edges, poses, correspondences).
"""

__version__ = "0.1.0"
