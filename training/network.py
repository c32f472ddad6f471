"""The covariance network f_theta: PointNet++-style, per-point Cholesky factor -> C = L L^T + eps I.

Architecture (all neighbour indices precomputed by :mod:`training.neighbors`)::

    SA0  every point:     max_k MLP([x_j - x_i] / r), moments(x_j - x_i)    -> f0 (N, c0 + 7)
    SA1  N/4 centroids:   max_k MLP([x_j - c] / r, f0_j), moments(x_j - c)  -> f1 (N1, c1 + 7)
    SA2  N1/4 centroids:  max_k MLP([x_j - c] / r, f1_j)  over level 1      -> f2 (N2, c2)
    FP2  level 1:         MLP(interp3(f2), f1)                              -> g1 (N1, c1)
    FP1  input points:    MLP(interp3(g1), f0, z / 2, range / 20)           -> g0 (N, c0)
    head (two variants, ``NetConfig.head``):

``"geometric"`` (default): a learned, weighted scatter of the point's neighbours, reshaped::

    S_i = sum_j w_ij o_ij o_ij^T / sum_j w_ij,   o_ij = x_j - x_i,
          j over the k0 nearest input points and the kw nearest level-1 centroids,
          w_ij = sigmoid(MLP(g0_i, f_j, o_ij))                   (attention-like weights)
    C_i  = alpha_i kappa_i S_i (S_i + kappa_i I)^-1 + gamma_i^2 I + eps I

with ``alpha, kappa, gamma > 0`` per point from ``Linear(g0)``. ``C``'s eigenvectors are those of
``S`` (the map ``lambda -> alpha kappa lambda / (lambda + kappa)`` is increasing), so surface
orientation comes from the measured geometry and the network learns *which* neighbours
belong to the point's surface (the wide neighbours span several scan lines, which fixes the
collinear k-NN neighbourhoods of sparse scans) and how to turn their spread into the
residual covariance (``alpha`` ~ scale, ``kappa`` (m^2) saturates the tangential variance,
``gamma`` is an isotropic floor). At initialisation all ``w = 1/2``: a PCA-like start.
``L`` is returned as the Cholesky factor of ``C - eps I`` (positive diagonal).

``"cholesky"``: ``Linear(g0)`` -> 3 log-diagonal + 3 off-diagonal entries,
``L = [[e^a, 0, 0], [b, e^c, 0], [d, e, e^f]] * cov_scale`` (positive diagonal, log-parametrised
and clamped so it cannot overflow).

In both cases ``C = L L^T + eps I`` (m^2, LiDAR frame of the input).
Distances are divided by ``r = 1 m``. ``moments`` are the group's second moments of the
offsets, normalised by their trace (6 numbers: the shape of the neighbourhood, as PCA sees it),
and the log of the trace (its size); they give the MLPs the neighbourhood's second-order
shape directly, which max-pooling alone learns only slowly. The network runs in float32; the
heads form ``L`` and ``C`` in float64 (:func:`geometric_covariance` says why) and return float64.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from training.config import NetConfig
from training.neighbors import Neighborhoods

__all__ = ["NetConfig", "CovarianceNet", "neighborhoods_to_torch", "cholesky_to_cov", "geometric_covariance",
           "geometric_covariance_kxk"]


def _mlp(sizes: list[int], last_act: bool = True) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2 or last_act:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def neighborhoods_to_torch(nb: Neighborhoods | dict, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Convert precomputed neighbourhoods to torch tensors on ``device``."""
    d = nb.as_dict() if isinstance(nb, Neighborhoods) else nb
    return {k: torch.as_tensor(np.asarray(v)).to(device) for k, v in d.items()}


def _rows(src: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``src[idx]`` for a non-negative integer index array ``idx`` of any shape: rows of ``src`` along dim 0.

    Under deterministic algorithms (how the trainer runs) the same values and gradients as
    advanced indexing, bit for bit, and faster: ``src[idx]`` backpropagates through a serial
    ``index_put`` with accumulation, ``index_select`` through ``index_add``, which adds the same
    rows in the same order (a training step 0.96x: ``benchmarks/bench_training_step.py``).
    Negative indices raise instead of counting from the end.
    """
    return torch.index_select(src, 0, idx.reshape(-1)).view(*idx.shape, *src.shape[1:])


def _moments(rel: torch.Tensor) -> torch.Tensor:
    """``(M, k, 3)`` offsets -> ``(M, 7)``: trace-normalised second moments (6) and log trace."""
    S = (rel[..., :, None] * rel[..., None, :]).mean(-3)
    tr = S[..., 0, 0] + S[..., 1, 1] + S[..., 2, 2] + 1e-6
    iu = (torch.tensor([0, 0, 0, 1, 1, 2]), torch.tensor([0, 1, 2, 1, 2, 2]))
    return torch.cat([S[..., iu[0], iu[1]] / tr[..., None], torch.log(tr)[..., None] / 5.0], -1)


def cholesky_to_cov(raw: torch.Tensor, cov_scale: float, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Map raw head outputs ``(N, 6)`` to ``(L, C)``, each ``(N, 3, 3)`` float64."""
    raw = raw.to(torch.float64)  # L L^T of a very anisotropic L loses its small eigenvalues in float32
    a = torch.clamp(raw[:, :3], -12.0, 6.0)
    diag = torch.exp(a)
    n = raw.shape[0]
    L = raw.new_zeros(n, 3, 3)
    L[:, 0, 0] = diag[:, 0]
    L[:, 1, 1] = diag[:, 1]
    L[:, 2, 2] = diag[:, 2]
    L[:, 1, 0] = raw[:, 3]
    L[:, 2, 0] = raw[:, 4]
    L[:, 2, 1] = raw[:, 5]
    L = L * cov_scale
    C = L @ L.transpose(-1, -2) + eps * torch.eye(3, dtype=raw.dtype, device=raw.device)
    return L, C


class _GroupMLP(nn.Module):
    """MLP on ``[offset, neighbour feature]`` of grouped points, first layer split for speed.

    ``Linear([o, f_j]) = W_o o + W_f f_j + b``: ``W_f f`` is computed once per source point and
    then gathered, instead of on every (duplicated) group member; identical to the plain MLP.
    """

    def __init__(self, n_off: int, n_feat: int, sizes: list[int]):
        super().__init__()
        self.off = nn.Linear(n_off, sizes[0])
        self.feat = nn.Linear(n_feat, sizes[0], bias=False)
        self.rest = _mlp(sizes) if len(sizes) > 1 else None  # single layer: linear output

    def forward(self, off: torch.Tensor, feat_src: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        h = self.off(off) + _rows(self.feat(feat_src), idx)
        return h if self.rest is None else self.rest(torch.relu(h))


class CovarianceNet(nn.Module):
    """f_theta: points (N, 3) + precomputed neighbourhoods -> per-point (L, C)."""

    def __init__(self, config: NetConfig | None = None):
        super().__init__()
        self.config = config or NetConfig()
        c = self.config
        c0 = c.c0
        self.sa0 = _mlp([3, c0, c0])
        self.sa1 = _GroupMLP(3, c0 + 7, [c.c1, c.c1])
        self.sa2 = _GroupMLP(3, c.c1 + 7, [c.c2, c.c2])
        self.fp2 = _mlp([c.c2 + c.c1 + 7, c.c1, c.c1])
        self.fp1 = _mlp([c.c1 + c0 + 7 + 2, c0 * 2, c0 * 2])
        self.head = nn.Linear(c0 * 2, 3 if c.head == "geometric" else 6)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        if c.head == "geometric":
            h = 32
            self.att_i = nn.Linear(c0 * 2, h)
            self.att_local = _GroupMLP(4, c0 + 7, [h])
            self.att_wide = _GroupMLP(4, c.c1, [h])
            self.att_out = nn.Linear(h, 1)
            nn.init.zeros_(self.att_out.weight)
            nn.init.zeros_(self.att_out.bias)

    def forward(self, points: torch.Tensor, nb: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Predict ``(L, C)``, each ``(N, 3, 3)`` float64, for ``points`` ``(N, 3)``."""
        x = points.to(torch.float32)
        # SA0: local shape of every point
        rel0 = _rows(x, nb["knn0"]) - x[:, None, :]
        f0 = torch.cat([self.sa0(rel0).amax(1), _moments(rel0)], -1)
        # SA1
        x1 = _rows(x, nb["idx1"])
        rel1 = _rows(x, nb["knn1"]) - x1[:, None, :]
        f1 = torch.cat([self.sa1(rel1, f0, nb["knn1"]).amax(1), _moments(rel1)], -1)
        # SA2
        x2 = _rows(x1, nb["idx2"])
        rel2 = _rows(x1, nb["knn2"]) - x2[:, None, :]
        f2 = self.sa2(rel2, f1, nb["knn2"]).amax(1)
        # FP2: level 2 -> level 1
        i21 = (_rows(f2, nb["up21"]) * nb["w21"][..., None]).sum(1)
        g1 = self.fp2(torch.cat([i21, f1], -1))
        # FP1: level 1 -> points
        i10 = (_rows(g1, nb["up10"]) * nb["w10"][..., None]).sum(1)
        glob = torch.stack([x[:, 2] / 2.0, torch.linalg.norm(x, dim=1) / 20.0], -1)
        g0 = self.fp1(torch.cat([i10, f0, glob], -1))
        raw = self.head(g0)
        if self.config.head == "cholesky":
            return cholesky_to_cov(raw, self.config.cov_scale, self.config.eps)
        # geometric head: attention-weighted neighbour scatter, eigenvalues reshaped
        xw = _rows(x1, nb["knnw"]) - x[:, None, :]  # (N, kw, 3) wide offsets
        ol = torch.cat([rel0, torch.linalg.norm(rel0, dim=-1, keepdim=True)], -1)
        ow = torch.cat([xw, torch.linalg.norm(xw, dim=-1, keepdim=True)], -1)
        hi = self.att_i(g0)[:, None, :]
        hl = self.att_local(ol, f0, nb["knn0"])
        hw = self.att_wide(ow, g1, nb["knnw"])
        logits = self.att_out(torch.relu(hi + torch.cat([hl, hw], 1)))  # (N, k0 + kw, 1)
        return geometric_covariance(raw, logits, torch.cat([rel0, xw], 1), self.config.cov_scale, self.config.eps)


def geometric_covariance(raw: torch.Tensor, logits: torch.Tensor, offsets: torch.Tensor, cov_scale: float,
                         eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The geometric head's ``(L, C)`` (float64, ``(N, 3, 3)`` each) from its inputs.

    ``raw`` ``(N, 3)``: head outputs (log alpha, log kappa, log gamma, clamped); ``logits``
    ``(N, k, 1)``: attention logits (``w = sigmoid(logits)``); ``offsets`` ``(N, k, 3)``:
    neighbour offsets ``o_ij``. ``S = sum_j w_j o_j o_j^T / sum_j w_j`` and
    ``C = alpha kappa S (S + kappa I)^-1 + gamma^2 I + eps I`` (module docstring).

    Numerics (both were the cause of non-finite and indefinite covariances of trained
    networks): the weights enter ``S`` only through their ratios, so they are normalised in
    log space, ``w_j / max_k w_k = exp(logsigmoid(l_j) - max_k logsigmoid(l_k))``: trained
    logits reach -100, where float32 ``sigmoid`` underflows (0 / 0 when every weight of a point
    did). And ``M = S (S + kappa I)^-1`` is formed in float64 as a sum of two Gram matrices, so
    that it is positive semi-definite by construction: with ``S = G^T G`` (``G``'s rows
    ``sqrt(w_j / sum w) o_j``), ``B = S + kappa I``, ``V = G B^-1`` and ``W = G^T V = S B^-1``,

        M = W^T W + kappa V^T V = (S^2 + kappa S) B^-2 = S B^-1

    (``S`` and ``B^-1`` commute). ``B^-1`` comes from ``B``'s 3x3 Cholesky factor written out
    (:func:`_cholesky3`; ``B >= kappa I``, its pivots clamped at ``kappa``), so every operation is on
    3x3 matrices; its gradients are those of the k x k form to ~1e-7 relative on ordinary
    neighbourhoods and less accurate where ``B``'s condition number nears 1e11 (``kappa`` at its
    clamp, needles tens of metres long; ~1 % on the logits' gradient there). The former
    float32 adjugate inverse of ``S + kappa I`` followed by the product with ``S`` lost the small
    eigenvalues when wide neighbours tens of metres away made ``S``'s largest eigenvalue
    ~10^3 m^2 against ``kappa`` ~ 10^-2 m^2: negative eigenvalues of ``C``, or a singular
    ``S + kappa I`` (inf / NaN). An equivalent k x k form, ``G^T (G G^T + kappa I_k)^-1 G``,
    is PSD by construction too but its batched k x k Cholesky and triangular solves made a
    training step 2.3x slower (:func:`geometric_covariance_kxk`, kept as a reference).
    """
    G, alpha, kappa, gamma2 = _head_terms(raw, logits, offsets, cov_scale)
    eye = torch.eye(3, dtype=G.dtype, device=G.device)
    S = G.transpose(-1, -2) @ G
    B_inv = _spd_inverse3(S + kappa[:, None, None] * eye, kappa)
    V = G @ B_inv  # (N, k, 3)
    W = G.transpose(-1, -2) @ V  # S B^-1
    M = W.transpose(-1, -2) @ W + kappa[:, None, None] * (V.transpose(-1, -2) @ V)
    M = (alpha * kappa)[:, None, None] * M + gamma2[:, None, None] * eye
    L, _ = torch.linalg.cholesky_ex(M)
    return L, M + eps * eye


def _head_terms(raw: torch.Tensor, logits: torch.Tensor, offsets: torch.Tensor,
                cov_scale: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``G`` ``(N, k, 3)`` (``S = G^T G``), ``alpha``, ``kappa``, ``gamma^2`` ``(N,)`` of the geometric
    head, float64 (the weights normalised in log space: :func:`geometric_covariance`)."""
    f64 = torch.float64
    logw = torch.nn.functional.logsigmoid(logits.to(f64))
    half = 0.5 * (logw - logw.amax(1, keepdim=True))  # log sqrt(w_j / max w)
    # sqrt(w_j / sum w) as exp(half) / sqrt(sum w): sqrt of a weight that underflowed to 0 would
    # give an infinite derivative (NaN gradients); the sum is >= 1
    G = torch.exp(half) / torch.sqrt(torch.exp(2.0 * half).sum(1, keepdim=True)) * offsets.to(f64)
    a = torch.clamp(raw.to(f64), -12.0, 8.0)
    alpha = 0.5 * torch.exp(a[:, 0])
    kappa = cov_scale**2 * torch.exp(a[:, 1])
    gamma2 = (0.03 * cov_scale) ** 2 * torch.exp(2 * a[:, 2])
    return G, alpha, kappa, gamma2


def geometric_covariance_kxk(raw: torch.Tensor, logits: torch.Tensor, offsets: torch.Tensor, cov_scale: float,
                             eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The geometric head's former k x k form, an independent reference of
    :func:`geometric_covariance` (tests, ``benchmarks/bench_head.py``): same arguments and result.

    ``S (S + kappa I)^-1 = G^T (G G^T + kappa I_k)^-1 G = Y^T Y``, ``Y = R^-1 G``,
    ``R R^T = G G^T + kappa I_k`` (batched LAPACK Cholesky and triangular solve, float64).
    """
    G, alpha, kappa, gamma2 = _head_terms(raw, logits, offsets, cov_scale)
    K = G @ G.transpose(-1, -2) + kappa[:, None, None] * torch.eye(G.shape[1], dtype=G.dtype, device=G.device)
    R, _ = torch.linalg.cholesky_ex(K)  # K >= kappa I: positive definite
    Y = torch.linalg.solve_triangular(R, G, upper=False)
    eye = torch.eye(3, dtype=G.dtype, device=G.device)
    M = (alpha * kappa)[:, None, None] * (Y.transpose(-1, -2) @ Y) + gamma2[:, None, None] * eye
    L, _ = torch.linalg.cholesky_ex(M)
    return L, M + eps * eye


def _cholesky3(A: torch.Tensor, floor: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Entries ``(l00, l10, l11, l20, l21, l22)`` of the Cholesky factor of ``(N, 3, 3)`` SPD ``A``.

    Written out (batched LAPACK calls on 3x3 matrices cost more than the arithmetic). ``floor``
    ``(N,)``: a lower bound of ``A``'s smallest eigenvalue; every squared pivot is at least that
    (``l_ii^2 >= lambda_min(A)``), so clamping the pivots there changes nothing in exact
    arithmetic and keeps rounding from giving a zero or negative pivot (inverse at most
    ``1 / floor``).
    """
    l00 = torch.sqrt(torch.maximum(A[:, 0, 0], floor))
    l10 = A[:, 1, 0] / l00
    l20 = A[:, 2, 0] / l00
    l11 = torch.sqrt(torch.maximum(A[:, 1, 1] - l10 * l10, floor))
    l21 = (A[:, 2, 1] - l20 * l10) / l11
    l22 = torch.sqrt(torch.maximum(A[:, 2, 2] - l20 * l20 - l21 * l21, floor))
    return l00, l10, l11, l20, l21, l22


def _spd_inverse3(A: torch.Tensor, floor: torch.Tensor) -> torch.Tensor:
    """Inverse of ``(N, 3, 3)`` SPD matrices ``A >= floor I`` as ``P^-T P^-1``, ``P = cholesky(A)`` (symmetric)."""
    l00, l10, l11, l20, l21, l22 = _cholesky3(A, floor)
    # P^-1 (lower triangular) by forward substitution
    i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
    i10 = -l10 * i00 * i11
    i21 = -l21 * i11 * i22
    i20 = -(l20 * i00 + l21 * i10) * i22
    zero = torch.zeros_like(i00)
    P_inv = torch.stack([torch.stack([i00, zero, zero], -1), torch.stack([i10, i11, zero], -1),
                         torch.stack([i20, i21, i22], -1)], -2)
    return P_inv.transpose(-1, -2) @ P_inv
