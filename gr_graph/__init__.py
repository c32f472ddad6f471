"""gr_graph: LiDAR SLAM with self-supervised geometry reasoning.

See the README and the paper for the method. Modules, one concern each:

- :mod:`gr_graph.datasets`: KITTI loader, ring recovery and channel subsampling, the
  synthetic renderer (a generated route through a procedural town), and :func:`gr_graph.datasets.registry.open_sequence`.
- :mod:`gr_graph.preprocess`, :mod:`gr_graph.odometry`, :mod:`gr_graph.loop_closure`
  (candidates, verification, the check/re-optimise schedule), :mod:`gr_graph.pose_graph`:
  the SLAM front and back end; :mod:`gr_graph.frame_loop`: F_SLAM over a sequence.
- :mod:`gr_graph.pipeline`, :mod:`gr_graph.slam`, :mod:`gr_graph.config`: the rounds and
  resume, the command line (``python -m gr_graph.slam``) and its configuration sections;
  :mod:`gr_graph.config_errors` words an invalid configuration (also the trainer's).
- :mod:`gr_graph.round_output`: a round's folder, its summary, ``metrics.json``, the plot.
- :mod:`gr_graph.memory`: the on-disk memory M = (scans, edges, poses, correspondences);
  :mod:`gr_graph.memory_builder`: the memory of a SLAM run;
  :mod:`gr_graph.correspondences`: nearest-neighbour pairs of an edge under T̂.
- :mod:`gr_graph.densify`: scans densified with the learned covariances (Algorithm 2);
  :mod:`gr_graph.edge_noise`: odometry-edge information H(C) from those covariances.
- :mod:`gr_graph.trajectory`, :mod:`gr_graph.metrics`, :mod:`gr_graph.loop_evaluation`,
  :mod:`gr_graph.global_registration` (solvers: :mod:`gr_graph.global_solvers`): trajectory
  files, evo-backed metrics, loops against ground truth, the global-registration benchmark.
- :mod:`gr_graph.plots`, :mod:`gr_graph.atomic`, :mod:`gr_graph.provenance`: figures, atomic
  file output, the provenance recorded with every result.
- :mod:`gr_graph.deskew`: motion compensation of a sweep; :mod:`gr_graph.cli_common`: the
  flags every command shares.
"""

__version__ = "0.1.0"
