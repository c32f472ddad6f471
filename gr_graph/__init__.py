"""gr_graph: LiDAR SLAM with self-supervised geometry reasoning.

See the README and the paper for the method. Modules, one concern each:

- :mod:`gr_graph.datasets`: KITTI loader, ring recovery and channel subsampling, the
  synthetic renderer (a generated route through a procedural town), and :func:`gr_graph.datasets.registry.open_sequence`.
- :mod:`gr_graph.preprocess`, :mod:`gr_graph.odometry`, :mod:`gr_graph.loop_closure`,
  :mod:`gr_graph.pose_graph`: the SLAM front and back end (F_SLAM).
- :mod:`gr_graph.pipeline`, :mod:`gr_graph.slam`, :mod:`gr_graph.config`: the rounds, the
  command line (``python -m gr_graph.slam``) and its configuration sections.
- :mod:`gr_graph.memory`: the on-disk memory M = (scans, edges, poses, correspondences).
- :mod:`gr_graph.densify`: scans densified with the learned covariances (Algorithm 2).
- :mod:`gr_graph.trajectory`, :mod:`gr_graph.metrics`, :mod:`gr_graph.global_registration`:
  trajectory files, evo-backed metrics, the global-registration benchmark.
- :mod:`gr_graph.plots`, :mod:`gr_graph.atomic`: figures and atomic file output.
"""

__version__ = "0.1.0"
