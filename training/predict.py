"""Inference: per-point covariances of a whole scan with a trained f_theta."""

from __future__ import annotations

import os

import numpy as np
import torch

from training.network import CovarianceNet, neighborhoods_to_torch
from training.trainer import load_model

__all__ = ["predict_covariances"]


def predict_covariances(
    checkpoint_or_model: str | os.PathLike[str] | CovarianceNet,
    points: np.ndarray,
    n_points: int | None = None,
    device: str = "cpu",
    seed: int = 0,
    full_passes: bool = False,
) -> np.ndarray:
    """Covariances ``C = L L^T + eps I`` (m^2, frame of ``points``) of every point of a scan.

    The scan is split into ``ceil(N / n_points)`` random disjoint parts of (almost) equal size,
    each a uniform random subsample like the network's training input, and each part goes
    through the network on its own (so memory stays bounded for any N). A part then holds
    between ``n_points / 2`` and ``n_points`` points, sparser than the network's training input
    (``n_points`` points) when N is not a multiple of it; the network's neighbourhoods, and so its
    covariances, depend on that density. ``full_passes`` fills every part up to ``min(n_points,
    N)`` points with other points of the scan (seeded) and keeps only the part's own rows: every
    point is predicted at the training density (``training.prediction_passes: training_size``).

    Parameters
    ----------
    checkpoint_or_model : path or CovarianceNet
        ``model.pt`` / ``checkpoint.pt`` from the trainer, or a network.
    points : (N, 3) array
        The scan (LiDAR frame). Rows must be finite.
    n_points : int, optional
        Points per network pass (default: the network's ``NetConfig.n_points``).
    device : str
        ``"cpu"`` or ``"cuda"`` for a checkpoint; a network given as such runs on the device of its weights.
    seed : int
        Seeds the split (deterministic output).
    full_passes : bool
        Fill each part up to ``min(n_points, N)`` points (see above); False: the parts alone.

    Returns
    -------
    np.ndarray
        ``(N, 3, 3)`` float64 symmetric positive-definite covariances.
    """
    if isinstance(checkpoint_or_model, CovarianceNet):  # a network runs where its weights are
        device = str(next(checkpoint_or_model.parameters()).device)
    model = load_model(checkpoint_or_model, device)
    x = np.asarray(points, np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"predict_covariances: points must be (N, 3), got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("predict_covariances: points contain non-finite rows")
    N = len(x)
    out = np.empty((N, 3, 3), np.float64)
    if N == 0:
        return out
    cfg = model.config
    n_points = int(n_points or cfg.n_points)
    n_parts = max(1, int(np.ceil(N / n_points)))
    rng = np.random.default_rng(seed)
    perm = rng.permutation(N)
    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode():
            for part in np.array_split(perm, n_parts):
                rows = part
                if full_passes and len(part) < min(n_points, N):  # filled up to the training input's size
                    others = np.setdiff1d(perm, part, assume_unique=True)
                    rows = np.concatenate([part, rng.choice(others, min(n_points, N) - len(part), replace=False)])
                pts = x[rows].astype(np.float32)
                nb = neighborhoods_to_torch(cfg.neighborhoods(pts, start=int(rng.integers(len(pts)))), device)
                _, C = model(torch.as_tensor(pts, device=device), nb)
                out[part] = C[: len(part)].double().cpu().numpy()
    finally:
        model.train(was_training)
    if not np.isfinite(out).all():
        raise FloatingPointError("predict_covariances: the network produced non-finite covariances")
    return 0.5 * (out + out.transpose(0, 2, 1))
