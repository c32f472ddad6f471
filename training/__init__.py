"""Self-supervised training of the covariance network (Algorithm 1 of the paper).

Modules
-------
config      ``NetConfig``, ``TrainOptions``, ``TrainConfig`` (pydantic; unknown keys are an error)
network     f_theta (PointNet++-style, geometric or plain Cholesky head)
neighbors   k-NN / hierarchy indices precomputed with scipy's cKDTree
se3_torch   SE(3) exp/log in torch (gtsam conventions: [omega, v], right perturbation)
pose_layer  differentiable WLS pose T(C) (no-grad solve + one exact-Hessian Newton step = IFT)
losses      correspondence NLL and pose NLL
dataset     training pairs from a memory's edges
trainer     Algorithm 1: Adam, checkpoints / exact resume, JSON-lines log, DDP support, bit-identical reruns
train       ``python -m training.train`` and ``train_from_memory`` (used by gr_graph.slam)
ddp         ``torchrun ... -m training.ddp``: multi-process data-parallel training
predict     ``predict_covariances(model_or_checkpoint, points)`` -> (N, 3, 3)
densify     Algorithm 2 lines 3-9: anisotropy filter + sampling (numpy)
toy_scenes  ray-cast scenes with known normals and noise (tests, benchmark)
"""
