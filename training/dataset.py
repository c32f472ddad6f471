"""Training samples from the edges (odometry and loop pairs) of a memory.

For edge ``e = (k, l)``: ``P = S_k`` (source), ``Q = S_l`` (target, the scan whose covariances
the network predicts), ``T̂_kl`` and correspondences ``(i, j)``. A sample holds

* ``q_points`` ``(n, 3)`` float32: the network input, a subsample of ``Q`` of at most
  ``n_points`` points that contains every correspondence target used (those first), filled
  up with random other points of ``Q``;
* ``nb``: the precomputed neighbourhoods of ``q_points`` (:mod:`training.neighbors`);
* ``p_corr``, ``q_corr`` ``(m, 3)`` float64 and ``q_index`` ``(m,)``: the correspondences used
  (at most ``max_corr``) and the row of ``q_points`` holding each target point;
* ``T_hat`` ``(4, 4)`` float64.

Edges whose registration failed in SLAM (the memory's ``info["flagged_edges"]``: the odometry
replaced the registration by its constant-velocity guess) are left out: their T̂ and
correspondences rest on that guess, not on the scans' geometry, and a network trained to explain
them learns the failure (counted as ``n_flagged_left_out`` in :meth:`PairDataset.describe`).
Without flagged edges the dataset's positions are the memory's edge numbers.

Sampling is deterministic: sample ``(epoch, e)`` uses ``np.random.default_rng([seed, epoch, e])``,
so it does not depend on what was drawn before (needed for exact resume).

Augmentation (``augment_yaw``): the target frame is rotated about the LiDAR z axis by a random
angle ``a`` (``q -> R_z(a) q``, ``T̂ -> R_z(a) T̂``). Residuals rotate with it and the pose
discrepancy ``Log(T(C)^-1 T̂)`` is unchanged, so the losses are the same functions of the
geometry; the network cannot lean on the absolute heading of walls seen in training and must
read surface orientation from the local geometry (a yaw-rotated scan is an equally valid
LiDAR scan, as the sensor may face anywhere; gravity / the z axis is kept).
"""

from __future__ import annotations

import hashlib

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from gr_graph.memory import Memory
from training.network import NetConfig

log = logging.getLogger(__name__)

__all__ = ["SkipSample", "PairSample", "PairDataset", "ConcatPairDataset"]


class SkipSample(Exception):
    """This pair cannot be used (empty, too few correspondences, non-finite data); ``reason`` says why."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass
class PairSample:
    """One training pair, ready for the network and the losses (see module docstring)."""

    edge: int
    k: int
    l: int
    kind: int
    q_points: np.ndarray
    nb: dict[str, np.ndarray]
    p_corr: np.ndarray
    q_corr: np.ndarray
    q_index: np.ndarray
    T_hat: np.ndarray


class PairDataset:
    """The edges of a memory as training pairs, but those whose registration failed (flagged).

    Parameters
    ----------
    memory : Memory
        Loaded memory (``gr_graph.memory.load_memory``).
    net_config : NetConfig
        Gives ``n_points`` and the neighbourhood sizes.
    max_corr : int
        Correspondences used per pair at most (random subset above that).
    min_corr : int
        Pairs with fewer correspondences are skipped (``SkipSample("empty_pair")``).
    seed : int
        Base seed of the deterministic sampling.
    augment_yaw : bool
        Rotate every sample's target frame by a random yaw (see module docstring).
    """

    def __init__(self, memory: Memory, net_config: NetConfig, max_corr: int = 1024, min_corr: int = 16, seed: int = 0,
                 augment_yaw: bool = False):
        self.memory = memory
        self.net_config = net_config
        self.max_corr = int(max_corr)
        self.min_corr = max(3, int(min_corr))
        self.seed = int(seed)
        self.augment_yaw = bool(augment_yaw)
        flagged = memory.flagged_edges
        self.edge_ids = np.array([e for e in range(memory.n_edges) if e not in flagged], np.int64)
        """The memory's edge number of each position (the flagged edges left out)."""
        if flagged:
            log.log(logging.WARNING if len(self.edge_ids) == 0 else logging.INFO,
                    "training: %d of %d edges left out, their registration failed in SLAM (flagged)",
                    memory.n_edges - len(self.edge_ids), memory.n_edges)

    def __len__(self) -> int:
        return len(self.edge_ids)

    def edge_number(self, i: int) -> int:
        """The memory's edge number of position ``i``.

        Raises
        ------
        IndexError
            ``i`` outside ``0 .. len - 1``.
        """
        if not 0 <= int(i) < len(self):
            raise IndexError(f"position {i} out of range for {len(self)} edges trained on")
        return int(self.edge_ids[int(i)])

    def sample(self, i: int, epoch: int = 0) -> PairSample:
        """Build the sample of position ``i`` (the memory's edge :meth:`edge_number`) for ``epoch``
        (raises :class:`SkipSample`)."""
        mem = self.memory
        e = self.edge_number(i)
        edge = mem.edge(e)
        rng = np.random.default_rng([self.seed, int(epoch), int(e)])
        corr = np.asarray(edge.corr, np.int64)
        if len(corr) < self.min_corr:
            raise SkipSample("empty_pair", f"edge {e} ({edge.k}, {edge.l}): {len(corr)} correspondences < {self.min_corr}")
        P = np.asarray(mem.scan(edge.k))
        Q = np.asarray(mem.scan(edge.l))
        n_points = self.net_config.n_points
        if len(corr) > self.max_corr:
            corr = corr[np.sort(rng.choice(len(corr), self.max_corr, replace=False))]
        uj = np.unique(corr[:, 1])
        if len(uj) > n_points:  # keep only correspondences whose target fits into the input
            keep_j = np.sort(rng.choice(uj, n_points, replace=False))
            corr = corr[np.isin(corr[:, 1], keep_j)]
            uj = keep_j
        n_fill = min(n_points, len(Q)) - len(uj)
        if n_fill > 0:
            mask = np.ones(len(Q), bool)
            mask[uj] = False
            others = np.flatnonzero(mask)
            fill = np.sort(rng.choice(others, n_fill, replace=False))
            sub = np.concatenate([uj, fill])
        else:
            sub = uj
        q_points = np.ascontiguousarray(Q[sub], dtype=np.float32)
        q_index = np.searchsorted(uj, corr[:, 1])
        p_corr = P[corr[:, 0]].astype(np.float64)
        q_corr = Q[corr[:, 1]].astype(np.float64)
        if not (np.isfinite(q_points).all() and np.isfinite(p_corr).all()):
            raise SkipSample("nonfinite_input", f"edge {e}: non-finite points")
        nb = self.net_config.neighborhoods(q_points, start=int(rng.integers(2**31))).as_dict()
        T_hat = np.array(edge.T, np.float64)
        if self.augment_yaw:
            a = rng.uniform(0.0, 2 * np.pi)
            Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
            q_points = np.ascontiguousarray((q_points.astype(np.float64) @ Rz.T).astype(np.float32))
            q_corr = q_corr @ Rz.T
            T_hat[:3] = Rz @ T_hat[:3]
        return PairSample(
            edge=int(e), k=edge.k, l=edge.l, kind=edge.kind, q_points=q_points, nb=nb,
            p_corr=p_corr, q_corr=q_corr, q_index=q_index.astype(np.int64), T_hat=T_hat,
        )

    def describe(self) -> dict[str, Any]:
        """Counts for logs (of the edges trained on; ``n_flagged_left_out`` when some were left out),
        and ``edges_sha256``: a hash of the memory's edges (pairs, kinds, T̂_kl,
        correspondence offsets), so that a checkpoint of other data with the same counts is not
        resumed."""
        m = self.memory
        kinds = np.asarray(m.edge_kind)
        h = hashlib.sha256()
        for part in (m.edges, kinds, m.edge_T, m.corr_offsets):
            h.update(np.ascontiguousarray(part).tobytes())
        used = kinds[self.edge_ids]
        left_out = m.n_edges - len(self)  # said only when there are some: a checkpoint of before still resumes
        return {"n_edges": len(self), "n_odometry": int((used == 0).sum()), "n_loop": int((used == 1).sum()),
                **({"n_flagged_left_out": left_out} if left_out else {}), "edges_sha256": h.hexdigest()[:16]}


class ConcatPairDataset:
    """The edges of several memories as one dataset (training on several sequences, sensors or
    channel counts, e.g. the shipped weights of :mod:`training.pretrain`).

    Position ``e`` of the whole is position ``e - offset[m]`` of memory ``m``'s :class:`PairDataset`
    (memories in the given order; without flagged edges, its edge number). Memory ``m`` samples with
    its own seed (:meth:`memory_seed`), so equal local edge numbers of different memories draw
    different subsets.

    Parameters
    ----------
    memories : sequence of Memory
        At least one, in order.
    net_config, max_corr, min_corr, seed, augment_yaw
        As for :class:`PairDataset`.
    """

    def __init__(self, memories: list[Memory], net_config: NetConfig, max_corr: int = 1024, min_corr: int = 16,
                 seed: int = 0, augment_yaw: bool = False):
        if not memories:
            raise ValueError("ConcatPairDataset needs at least one memory")
        self.datasets = [PairDataset(m, net_config, max_corr, min_corr, self.memory_seed(seed, i), augment_yaw)
                         for i, m in enumerate(memories)]
        self.offsets = np.cumsum([0] + [len(d) for d in self.datasets])

    @staticmethod
    def memory_seed(seed: int, m: int) -> int:
        """The sampling seed of memory ``m`` given the run's ``seed`` (one integer, distinct per memory)."""
        return int(seed) * 1_000_003 + int(m)

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def locate(self, e: int) -> tuple[int, int]:
        """``(memory index, local edge)`` of global edge ``e``."""
        if not 0 <= e < len(self):
            raise IndexError(f"edge {e} out of range 0..{len(self) - 1}")
        m = int(np.searchsorted(self.offsets, e, side="right") - 1)
        return m, int(e - self.offsets[m])

    def edge_number(self, e: int) -> int:
        """The number of position ``e`` in the training log: the global position itself (memory ``m``'s
        edges follow those of the memories before it)."""
        self.locate(int(e))  # IndexError outside the range
        return int(e)

    def sample(self, e: int, epoch: int = 0) -> PairSample:
        """Sample of global position ``e`` (its ``edge`` field is the global number)."""
        m, local = self.locate(int(e))
        try:
            s = self.datasets[m].sample(local, epoch)
        except SkipSample as exc:
            raise SkipSample(exc.reason, f"memory {m}: {exc}") from exc
        s.edge = int(e)
        return s

    def describe(self) -> dict[str, Any]:
        """Summed counts, and each memory's."""
        parts = [d.describe() for d in self.datasets]
        keys = dict.fromkeys(k for p in parts for k in p if k != "edges_sha256")  # in order, each once
        total = {k: sum(p.get(k, 0) for p in parts) for k in keys}
        return {**total, "n_memories": len(parts), "memories": parts}
