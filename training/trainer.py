"""Algorithm 1 of the paper: self-supervised training of f_theta from a memory.

For each epoch the memory's edges are visited in a seeded random order; every pair gives
``lambda_corr * L_corr + lambda_pose * L_pose`` (:mod:`training.losses`) and Adam takes a step
every ``pairs_per_step`` pairs (the paper: every pair). Robustness:

* a pair with too few correspondences, non-finite input, non-finite network output, a
  degenerate WLS Hessian or a failing loss is *skipped and counted* (``skipped`` in the log,
  ``skip_counts`` in the checkpoint and summary); more than ``max_skip_fraction`` skipped pairs
  in an epoch raises :class:`TrainingError`;
* a step whose (averaged) gradient is non-finite is not applied (counted as
  ``nonfinite_grad``), so the weights never receive a NaN; gradients are norm-clipped.

Outputs in ``out_dir``: ``checkpoint.pt`` (latest state, written atomically every
``checkpoint_every`` steps and at each epoch end; resuming from it reproduces the
uninterrupted run exactly), ``train_log.jsonl`` (one JSON line per pair), ``model.pt`` (the
final network: weights + NetConfig) and ``summary.json`` (counts, configuration, step timing
and provenance: commit, packages, seed, device, thread count).

Reproducibility: the same memory, configuration (seed included) and torch thread count give
bit-identical ``model.pt``, ``checkpoint.pt`` and ``train_log.jsonl`` in separate processes.
Everything random is drawn from generators seeded by ``(seed, epoch, edge)`` or from torch's
seeded generator; the loop runs under :func:`deterministic_algorithms` (see there for the
operation that varied without it); the log holds no wall-clock times (they go to
``summary.json``); checkpoints are written so that their bytes do not depend on the
temporary file name (:func:`save_atomic`).

Data parallel: with ``world_size > 1`` (see :mod:`training.ddp`) the network is wrapped in
``torch.nn.parallel.DistributedDataParallel``; step ``s`` of an epoch uses the pairs
``perm[s*B*W : (s+1)*B*W]``, rank ``r`` taking ``B`` of them, and DDP averages the gradients,
so one step equals a single-process step with ``pairs_per_step = B*W``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from gr_graph.atomic import atomic_path, atomic_write_text
from gr_graph.memory import Memory
from gr_graph.provenance import provenance
from training.config import NetConfig, TrainConfig, TrainConfigError, TrainOptions
from training.dataset import ConcatPairDataset, PairDataset, PairSample, SkipSample
from training.losses import LossError, corr_nll, default_gamma, pose_nll
from training.network import CovarianceNet, neighborhoods_to_torch
from training.pose_layer import PoseLayerError, solve_pose

log = logging.getLogger(__name__)

__all__ = ["TrainConfig", "TrainOptions", "TrainConfigError", "TrainingError", "CheckpointMismatch", "Trainer", "save_atomic", "load_model",
           "require_device",
           "CHECKPOINT_FORMAT",
           "deterministic_algorithms"]

CHECKPOINT_NAME = "checkpoint.pt"
MODEL_NAME = "model.pt"
LOG_NAME = "train_log.jsonl"
SUMMARY_NAME = "summary.json"
#: Version of the layout of ``model.pt`` / ``checkpoint.pt`` (key ``format_version``); files
#: without the key are version 0 (same layout) and load as well.
CHECKPOINT_FORMAT = 1


class TrainingError(RuntimeError):
    """Training cannot proceed (incompatible checkpoint, too many skipped pairs, no device).

    An invalid configuration raises :class:`training.config.TrainConfigError` (a ValueError).
    """


class CheckpointMismatch(TrainingError):
    """``checkpoint.pt`` cannot be resumed by this run: another configuration, other training data,
    more epochs than asked for, or an unreadable file. Training from scratch (``resume=False``)
    replaces it; :mod:`gr_graph.pipeline` does so, logged."""


def require_device(device: str, what: str = "--device") -> None:
    """Raise :class:`TrainingError` (naming ``what``: the option, or the file to be loaded) when
    ``device`` is a CUDA device and this torch has none."""
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        raise TrainingError(f"{what}: device {device!r} asked for, but this torch ({torch.__version__}) has no CUDA "
                            "device (use --device cpu, the default)")


def _without_edge_hashes(description: Any) -> Any:
    """A dataset description (:meth:`training.dataset.PairDataset.describe`) without its ``edges_sha256``
    entries: the counts alone, as checkpoints written before the hash was kept hold them."""
    if isinstance(description, dict):
        return {k: _without_edge_hashes(v) for k, v in description.items() if k != "edges_sha256"}
    if isinstance(description, list):
        return [_without_edge_hashes(v) for v in description]
    return description


def save_atomic(obj: Any, path: Path) -> None:
    """``torch.save`` to ``path`` atomically (temporary sibling, fsync, ``os.replace``).

    torch names the folder inside its zip archive after the file it is given, which here
    would be the random temporary name; writing through an open file gives the fixed name
    ``archive``, so the same object gives the same bytes in every run.
    """
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        torch.save(obj, fh)


@contextlib.contextmanager
def deterministic_algorithms() -> Iterator[None]:
    """Run the block with ``torch.use_deterministic_algorithms(True)``; restore the setting after.

    Needed for reproducible training on CPU with more than one thread: a gather written as
    ``features[index]`` backpropagates through an ``index_put_`` with accumulation, which torch
    parallelises with atomic float adds when deterministic algorithms are off, so the order of
    the additions, and the rounding of the gradient, changes from run to run. In deterministic
    mode torch accumulates serially (the network's own gathers use ``index_select``,
    :func:`training.network._rows`: the same additions in the same order, faster). Any op
    without a deterministic implementation then raises instead of silently varying.
    """
    previous = torch.are_deterministic_algorithms_enabled()
    previous_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(previous, warn_only=previous_warn)


def newer_format(state: dict[str, Any], path: Path) -> str | None:
    """Why the checkpoint ``state`` (read from ``path``) is of a newer layout than this gr_graph reads, or
    None (files without ``format_version`` are version 0). A version that is not an integer raises."""
    version = int(state.get("format_version", 0))
    if version > CHECKPOINT_FORMAT:
        return f"{path}: checkpoint format version {version} is newer than this gr_graph reads ({CHECKPOINT_FORMAT})"
    return None


def load_model(checkpoint: str | os.PathLike[str] | CovarianceNet, device: str = "cpu") -> CovarianceNet:
    """A :class:`CovarianceNet` from a ``model.pt`` / ``checkpoint.pt`` path (or pass-through).

    The checkpoint's ``format_version`` (:data:`CHECKPOINT_FORMAT`; checkpoints written before
    it existed count as version 0 and load the same way) and its network configuration
    (``net_config``, validated as :class:`training.config.NetConfig`) are checked, and the
    weights must fit that configuration.

    Raises
    ------
    FileNotFoundError
        If there is no file at the path.
    TrainingError
        Naming the file: not a torch checkpoint, not one of the trainer's, a newer format
        version, an invalid network configuration, or weights that do not fit it.
    """
    if isinstance(checkpoint, CovarianceNet):
        return checkpoint
    path = Path(checkpoint)
    if not path.is_file():
        raise FileNotFoundError(f"no model checkpoint at {path}")
    require_device(device, str(path))
    try:
        state = torch.load(path, map_location=device, weights_only=True)  # tensors and plain data, no code
    except Exception as exc:  # torch raises pickle, zip and runtime errors for foreign files
        raise TrainingError(f"{path}: not a torch checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(state, dict) or "model_state" not in state or "net_config" not in state:
        raise TrainingError(f"{path}: not a training checkpoint (missing model_state / net_config); "
                            "use a model.pt written by `python -m training.train` or a gr_graph.slam --rounds run")
    try:
        newer = newer_format(state, path)
    except (TypeError, ValueError) as exc:
        raise TrainingError(f"{path}: damaged checkpoint (format_version: {exc})") from None
    if newer:
        raise TrainingError(f"{newer}; update gr_graph")
    try:
        net_config = NetConfig(**state["net_config"])
    except (TypeError, ValueError) as exc:
        raise TrainingError(f"{path}: the checkpoint's network configuration does not fit this gr_graph's "
                            f"CovarianceNet: {exc}") from None
    model = CovarianceNet(net_config)
    try:
        model.load_state_dict(state["model_state"])
    except RuntimeError as exc:
        raise TrainingError(f"{path}: the weights do not fit the checkpoint's network configuration "
                            f"{net_config.to_dict()}: {str(exc).splitlines()[0]}") from None
    return model.to(device)


class Trainer:
    """Runs Algorithm 1 over a memory (or several); see the module docstring.

    Parameters
    ----------
    memory : Memory or sequence of Memory
        The memory to train from; several memories are trained on as one set of edges
        (:class:`training.dataset.ConcatPairDataset`).
    out_dir : path
        Where checkpoints, the log and the final model go.
    config : TrainConfig
    rank, world_size : int
        Process rank and count for data-parallel runs (a process group must exist).
    """

    def __init__(self, memory: Memory | Sequence[Memory], out_dir: str | os.PathLike[str], config: TrainConfig,
                 rank: int = 0, world_size: int = 1):
        memories = list(memory) if isinstance(memory, (list, tuple)) else [memory]
        if not memories:
            raise TrainingError("no memory to train on")
        self.memory = memories[0]
        self.out_dir = Path(out_dir)
        self.config = config
        self.rank = rank
        self.world_size = world_size
        require_device(config.device, "the trainer's device")
        if config.device.startswith("cuda") and "CUBLAS_WORKSPACE_CONFIG" not in os.environ:
            # cuBLAS is deterministic only with a fixed workspace (torch raises in deterministic
            # mode otherwise); read when the first cuBLAS handle is made, i.e. after this point
            os.environ["CUBLAS_WORKSPACE_CONFIG"] = ":4096:8"
            log.info("CUBLAS_WORKSPACE_CONFIG=:4096:8 set for deterministic cuBLAS")
        self.device = torch.device(config.device)
        if len(memories) == 1:
            self.dataset: PairDataset | ConcatPairDataset = PairDataset(
                memories[0], config.net, config.max_corr, config.min_corr, config.seed, config.augment_yaw)
        else:
            self.dataset = ConcatPairDataset(memories, config.net, config.max_corr, config.min_corr, config.seed,
                                             config.augment_yaw)
        torch.manual_seed(config.seed)
        self.model = CovarianceNet(config.net).to(self.device)
        if config.init_checkpoint:
            init = load_model(config.init_checkpoint, str(self.device))
            if init.config.to_dict() != config.net.to_dict():
                raise TrainingError(f"init_checkpoint {config.init_checkpoint}: network config differs from config.net")
            self.model.load_state_dict(init.state_dict())
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.lr)
        self.gamma = default_gamma(config.gamma_rot_std, config.gamma_trans_std).to(self.device)
        self.ddp_model: torch.nn.Module = self.model
        if world_size > 1:
            from torch.nn.parallel import DistributedDataParallel

            self.ddp_model = DistributedDataParallel(self.model)
        self.epoch = 0
        self.step = 0
        self.skip_counts: Counter[str] = Counter()
        self.epoch_skipped = 0  # pairs of the current epoch skipped so far (checked against max_skip_fraction)
        self.step_seconds: list[float] = []  # wall time of each step run by this process
        self.threads_used: set[int] = set()  # torch thread counts of every process that trained these weights
        self._resumed = False  # fit() continued a checkpoint
        self._dummy: tuple[torch.Tensor, dict[str, torch.Tensor]] | None = None

    # ------------------------------------------------------------------ losses of one pair
    def forward(self, sample: PairSample) -> torch.Tensor:
        """Network covariances ``(n, 3, 3)`` float32 of the sample's input points."""
        pts = torch.as_tensor(sample.q_points, device=self.device)
        nb = neighborhoods_to_torch(sample.nb, self.device)
        _, C = self.ddp_model(pts, nb)
        return C

    def pair_loss(self, sample: PairSample, C: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        """``lambda_corr * L_corr + lambda_pose * L_pose`` of one pair given the network output.

        Raises :class:`SkipSample` for non-finite outputs, degenerate Hessians or loss failures.
        """
        cfg = self.config
        if not bool(torch.isfinite(C).all()):
            raise SkipSample("nonfinite_output", f"edge {sample.edge}: non-finite network output")
        Cq = C.to(torch.float64)[torch.as_tensor(sample.q_index, device=self.device)]
        p = torch.as_tensor(sample.p_corr, device=self.device)
        q = torch.as_tensor(sample.q_corr, device=self.device)
        T_hat = torch.as_tensor(sample.T_hat, device=self.device)
        d = q - p @ T_hat[:3, :3].T - T_hat[:3, 3]
        info: dict[str, float] = {}
        try:
            loss = torch.zeros((), dtype=torch.float64, device=self.device)
            if cfg.lambda_corr > 0:
                lc = corr_nll(Cq, d, cfg.corr_reduction, cfg.corr_likelihood, cfg.corr_dof)
                loss = loss + cfg.lambda_corr * lc
                info["corr"] = float(lc.detach())
            if cfg.lambda_pose > 0:
                res = solve_pose(p, q, Cq, T0=T_hat)
                lp = pose_nll(res.T, T_hat, res.H, self.gamma)
                loss = loss + cfg.lambda_pose * lp
                info["pose"] = float(lp.detach())
        except PoseLayerError as exc:
            raise SkipSample("degenerate_H", f"edge {sample.edge}: {exc}") from exc
        except LossError as exc:
            raise SkipSample("loss_error", f"edge {sample.edge}: {exc}") from exc
        if not bool(torch.isfinite(loss)):
            raise SkipSample("nonfinite_loss", f"edge {sample.edge}: non-finite loss")
        info["loss"] = float(loss.detach())
        return loss, info

    def _dummy_output(self) -> torch.Tensor:
        if self._dummy is None:
            g = np.random.default_rng(0)
            pts = g.normal(size=(32, 3)).astype(np.float32)
            self._dummy = (torch.as_tensor(pts, device=self.device), neighborhoods_to_torch(self.config.net.neighborhoods(pts), self.device))
        return self.ddp_model(*self._dummy)[1]

    # ------------------------------------------------------------------ checkpoints
    def state(self, epoch_skipped: int) -> dict[str, Any]:
        """Everything needed to resume exactly; ``epoch_skipped``: the epoch's skipped pairs over every
        rank (:meth:`skipped_this_epoch`)."""
        return {
            "format_version": CHECKPOINT_FORMAT,
            "model_state": self.model.state_dict(),
            "optimizer_state": self.optimizer.state_dict(),
            "net_config": self.config.net.to_dict(),
            "train_config": self.config.to_dict(),
            "resume_key": self.config.resume_key(),
            "dataset": self.dataset.describe(),
            "epoch": self.epoch,
            "step": self.step,
            "world_size": self.world_size,
            "skip_counts": dict(self.skip_counts),
            "epoch_skipped": epoch_skipped,
            "torch_rng": torch.get_rng_state(),
            "threads_used": sorted(self.threads_used),
            "device": self.device.type,
        }

    def save_checkpoint(self) -> Path:
        """Write ``checkpoint.pt`` atomically (rank 0 only; every rank calls it); returns its path.

        It holds the epoch's skipped pairs summed over the ranks (:meth:`skipped_this_epoch`)."""
        path = self.out_dir / CHECKPOINT_NAME
        skipped = self.skipped_this_epoch()  # a collective: before the rank test
        if self.rank == 0:
            save_atomic(self.state(skipped), path)
        return path

    def skipped_this_epoch(self) -> int:
        """Pairs of the current epoch skipped so far, over every rank (an all-reduce when distributed)."""
        if self.world_size == 1:
            return self.epoch_skipped
        import torch.distributed as dist

        total = torch.tensor([self.epoch_skipped], dtype=torch.int64, device=self.device)
        dist.all_reduce(total)
        return int(total.item())

    def try_resume(self) -> bool:
        """Load ``checkpoint.pt`` if present; True if resumed.

        Raises :class:`CheckpointMismatch` for a checkpoint this run cannot continue: unreadable,
        of another configuration, world size or training data, or past the epochs asked for (a
        3-epoch checkpoint is not a 1-epoch model).
        """
        path = self.out_dir / CHECKPOINT_NAME
        if not path.is_file():
            return False
        hint = "use another --out directory, --no-resume, or delete the checkpoint"
        try:  # tensors onto the CPU first: torch.set_rng_state takes a CPU tensor only
            st = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # truncated or foreign file: pickle, zip and runtime errors
            raise CheckpointMismatch(f"{path}: unreadable checkpoint ({type(exc).__name__}: {exc}); {hint}") from None
        needed = ("model_state", "optimizer_state", "epoch", "step", "skip_counts", "torch_rng")
        if not isinstance(st, dict) or any(k not in st for k in needed):
            raise CheckpointMismatch(f"{path}: not a training checkpoint (needs {', '.join(needed)}); {hint}")
        self._continue_from(st, path, hint)
        log.info("resumed from %s at epoch %d step %d", path, self.epoch, self.step)
        self._truncate_log()
        return True

    def _continue_from(self, st: dict[str, Any], path: Path, hint: str) -> None:
        """:meth:`try_resume`'s checks of the checkpoint ``st`` (CheckpointMismatch naming ``path``) and its
        loading. A field of the wrong type, weights of another shape or a broken RNG state is a damaged
        checkpoint (refused as the others; the model and optimizer are left as they were); the trainer's
        counters change only once everything is loaded."""

        def damaged(exc: Exception) -> CheckpointMismatch:
            first_line = (str(exc).splitlines() or [""])[0]
            return CheckpointMismatch(f"{path}: damaged checkpoint ({type(exc).__name__}: {first_line}); {hint}")

        fields_errors = (ValueError, KeyError, TypeError, AttributeError, RuntimeError)
        try:  # the checkpoint's fields, read before anything is compared or loaded
            newer = newer_format(st, path)
            stored_key = dict(st.get("resume_key") or {})
            epoch, step = int(st["epoch"]), int(st["step"])
            skip_counts = Counter(st["skip_counts"])
            # the ranks' sum (rank 0 carries it); checkpoints before the count was kept: the skips before are unknown
            epoch_skipped = int(st.get("epoch_skipped", 0)) if self.rank == 0 else 0
            device_before = st.get("device")  # checkpoints before it was kept: unknown
            device_type_before = None if device_before is None else torch.device(device_before).type
            before = {int(n) for n in st.get("threads_used", [])}  # checkpoints before the count was kept: unknown
        except fields_errors as exc:
            raise damaged(exc) from None
        if newer:
            raise CheckpointMismatch(f"{newer}; {hint}")
        described = now = self.dataset.describe()
        stored = st.get("dataset", now)
        if stored != now and _without_edge_hashes(stored) == stored:  # written before the hash was kept:
            now = _without_edge_hashes(now)  # its counts only
        if stored != now:
            raise CheckpointMismatch(f"{path}: checkpoint was written with a different configuration (other "
                                     f"training data: {stored}, now {described}); {hint}")
        if "init_checkpoint_sha256" in stored_key:  # checkpoints of before the path left the key: its content counts
            stored_key.pop("init_checkpoint", None)
        if stored_key != self.config.resume_key() or st.get("world_size") != self.world_size:
            raise CheckpointMismatch(
                f"{path}: checkpoint was written with a different configuration or world size; {hint}")
        if epoch > self.config.epochs:
            raise CheckpointMismatch(f"{path}: checkpoint was written with a different configuration ({epoch} "
                                     f"epochs trained, {self.config.epochs} asked for); {hint}")
        model_before = {k: v.clone() for k, v in self.model.state_dict().items()}
        optimizer_before = self.optimizer.state_dict()
        try:
            self.model.load_state_dict(st["model_state"])
            self.optimizer.load_state_dict(st["optimizer_state"])
            torch.set_rng_state(st["torch_rng"].cpu())
        except fields_errors as exc:
            self.model.load_state_dict(model_before)  # a retrain after the refusal starts from where it was
            self.optimizer.load_state_dict(optimizer_before)
            raise damaged(exc) from None
        self.epoch, self.step, self.skip_counts, self.epoch_skipped = epoch, step, skip_counts, epoch_skipped
        if device_type_before is not None and device_type_before != self.device.type:
            log.warning("%s: resumed on %s, the steps before ran on %s: the weights will differ from an "
                        "uninterrupted run", path, self.device.type, device_before)
        if before and before != {torch.get_num_threads()}:
            log.warning("%s: resumed with %d torch thread(s), the steps before ran with %s: the weights may differ "
                        "in the last bits from an uninterrupted run", path, torch.get_num_threads(), sorted(before))
        self.threads_used |= before

    def _log_path(self) -> Path:
        return self.out_dir / (LOG_NAME if self.rank == 0 else f"train_log.rank{self.rank}.jsonl")

    def _truncate_log(self) -> None:
        """Drop log lines of steps after the checkpoint (they are redone)."""
        path = self._log_path()
        if not path.is_file():
            return
        keep = []
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if (rec.get("epoch", 0), rec.get("step", 0)) < (self.epoch, self.step):
                keep.append(line)
        atomic_write_text(path, "".join(k + "\n" for k in keep))

    # ------------------------------------------------------------------ main loop
    def steps_per_epoch(self) -> int:
        """Adam steps per epoch."""
        return math.ceil(len(self.dataset) / (self.config.pairs_per_step * self.world_size))

    def epoch_order(self, epoch: int) -> np.ndarray:
        """The seeded visiting order of the edges in ``epoch``."""
        return np.random.default_rng([self.config.seed, epoch, 7919]).permutation(len(self.dataset))

    def apply_gradients(self) -> str:
        """Apply the accumulated gradients: clipped to ``config.grad_clip``, then one Adam step.

        Returns ``"applied"``; ``"nonfinite"`` when a gradient is not finite and ``"no_gradient"``
        when every pair of the step was skipped (all gradients zero), both without an Adam step
        (its moments are kept). The gradients are not zeroed.
        """
        params = list(self.model.parameters())
        if not all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in params):
            return "nonfinite"
        if not any(p.grad is not None and bool((p.grad != 0).any()) for p in params):
            return "no_gradient"
        if self.config.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, self.config.grad_clip)
        self.optimizer.step()
        return "applied"

    def fit(self, resume: bool = True, callback: Callable[[dict[str, Any]], None] | None = None) -> Path:
        """Train for ``config.epochs`` epochs (continuing a checkpoint if ``resume``).

        ``callback(record)`` is called after every step (rank 0 and others) with the step's
        record; an exception raised there interrupts training like a kill would (the last
        checkpoint stays valid). Returns the path of ``model.pt``.

        Runs under :func:`deterministic_algorithms`: the same memory, configuration and thread
        count give bit-identical ``model.pt``, ``checkpoint.pt`` and ``train_log.jsonl`` in
        every process. Results may differ between thread counts (reductions split differently);
        the count used is logged and stored in ``summary.json`` (``provenance.num_threads``).
        """
        cfg = self.config
        if cfg.num_threads:
            torch.set_num_threads(cfg.num_threads)
        self.threads_used = {torch.get_num_threads()}
        log.info("training with %d torch thread(s), deterministic algorithms", torch.get_num_threads())
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if len(self.dataset) == 0:
            raise TrainingError("the memory has no edges to train on (none, or every one flagged: its registration "
                                "failed in SLAM)")
        self._resumed = resume and self.try_resume()
        if not self._resumed:
            # from scratch: no checkpoint, nor the log lines of a run killed before its first one, nor the
            # weights and summary of an earlier run
            if self.rank == 0:
                for name in (CHECKPOINT_NAME, MODEL_NAME, SUMMARY_NAME):
                    (self.out_dir / name).unlink(missing_ok=True)
            self._log_path().unlink(missing_ok=True)
        B, W = cfg.pairs_per_step, self.world_size
        n_steps = self.steps_per_epoch()
        from tqdm.auto import tqdm

        with deterministic_algorithms(), open(self._log_path(), "a") as logfh:
            while self.epoch < cfg.epochs:
                order = self.epoch_order(self.epoch)
                run: dict[str, list[float]] = {"loss": [], "corr": [], "pose": []}
                bar = tqdm(total=n_steps, initial=self.step, desc=f"epoch {self.epoch + 1}/{cfg.epochs}",
                           disable=not cfg.progress or self.rank != 0, leave=False)
                while self.step < n_steps:
                    chunk = order[self.step * B * W : (self.step + 1) * B * W]
                    mine = list(chunk[self.rank * B : (self.rank + 1) * B])
                    mine += [-1] * (B - len(mine))  # this rank has no pair left: dummy pass
                    t0 = time.perf_counter()
                    self.optimizer.zero_grad(set_to_none=False)
                    records = []
                    for b, e in enumerate(mine):
                        sync = b == B - 1
                        ctx = self.ddp_model.no_sync() if (W > 1 and not sync) else contextlib.nullcontext()
                        rec: dict[str, Any] = {"epoch": self.epoch, "step": self.step,
                                               "edge": self.dataset.edge_number(int(e)) if e >= 0 else int(e),
                                               "rank": self.rank}
                        with ctx:
                            C = None
                            try:
                                if e < 0:
                                    raise SkipSample("no_pair", "no pair for this rank")
                                sample = self.dataset.sample(int(e), self.epoch)
                                C = self.forward(sample)
                                loss, info = self.pair_loss(sample, C)
                                rec.update(info)
                                (loss / B).backward()
                            except SkipSample as exc:
                                if exc.reason != "no_pair":
                                    self.skip_counts[exc.reason] += 1
                                    self.epoch_skipped += 1
                                    log.warning("skipping pair: %s", exc)
                                rec["skipped"] = exc.reason
                                out = C if C is not None else self._dummy_output()
                                (out.nan_to_num(0.0) * 0.0).sum().backward()
                        records.append(rec)
                    update = self.apply_gradients()
                    grads_ok = update == "applied"
                    if update == "nonfinite":  # the step's pairs are lost: they count as skipped
                        self.skip_counts["nonfinite_grad"] += 1
                        self.epoch_skipped += sum(1 for rec in records if "skipped" not in rec)
                        log.warning("step %d: non-finite gradient, update not applied", self.step)
                    self.step_seconds.append(time.perf_counter() - t0)  # not in the log: it must not vary
                    for rec in records:
                        rec["applied"] = grads_ok
                        logfh.write(json.dumps(rec) + "\n")
                        for k in run:
                            if k in rec:
                                run[k].append(rec[k])
                    logfh.flush()
                    self.step += 1
                    bar.update(1)
                    bar.set_postfix({k: f"{np.mean(v[-50:]):.3f}" for k, v in run.items() if v})
                    if self.step % cfg.checkpoint_every == 0 and self.step < n_steps:
                        self.save_checkpoint()
                    if callback is not None:
                        callback(records[-1])
                bar.close()
                n_pairs = max(1, min(len(self.dataset), n_steps * B * W))  # over every rank
                skipped = self.skipped_this_epoch()  # every rank decides alike
                if skipped > cfg.max_skip_fraction * n_pairs:
                    raise TrainingError(
                        f"epoch {self.epoch}: {skipped} of ~{n_pairs} pairs skipped ({dict(self.skip_counts)})"
                    )
                log.info("epoch %d done: %s", self.epoch, {k: float(np.mean(v)) for k, v in run.items() if v})
                self.epoch += 1
                self.step = 0
                self.epoch_skipped = 0
                self.save_checkpoint()
        return self._finish()

    def _finish(self) -> Path:
        path = self.out_dir / MODEL_NAME
        summary_path = self.out_dir / SUMMARY_NAME
        if self._resumed and not self.step_seconds and summary_path.is_file() and self._model_file_is_current(path):
            # a finished training run again: its summary (runtime, provenance) stays the one that trained
            log.info("%s: training already finished, model.pt and summary.json kept", self.out_dir)
            return path
        if self.rank == 0:
            save_atomic(
                {"format_version": CHECKPOINT_FORMAT, "model_state": self.model.state_dict(),
                 "net_config": self.config.net.to_dict(),
                 "train_config": self.config.to_dict(), "epochs_done": self.epoch},
                path,
            )
            atomic_write_text(summary_path, json.dumps(self.summary(path), indent=2))
        return path

    def _model_file_is_current(self, path: Path) -> bool:
        """Whether ``path`` holds exactly the weights of this run's checkpoint, after as many epochs
        (not a file another run left in the folder, nor one written before a kill)."""
        try:
            stored = torch.load(path, map_location="cpu", weights_only=True)
        except Exception:  # missing, truncated or foreign: written again
            return False
        if not isinstance(stored, dict) or stored.get("epochs_done") != self.epoch:
            return False
        mine, theirs = self.model.state_dict(), stored.get("model_state") or {}
        return set(mine) == set(theirs) and all(torch.equal(mine[k].cpu(), theirs[k]) for k in mine)

    def summary(self, model_path: Path) -> dict[str, Any]:
        """The content of ``summary.json``: counts, configuration, timing and provenance.

        ``runtime_s`` covers the steps run by this process (a resumed run: only the rest);
        ``provenance`` (:func:`gr_graph.provenance.provenance`) holds the commit, package
        versions, seed, device and the torch thread count of this process; ``threads_used``
        every thread count the weights were computed with (more than one after a resume with
        another count; after a resume of a checkpoint written before the counts were kept, only
        the counts from the resume on).
        """
        steps = np.asarray(self.step_seconds, np.float64)
        return {
            "epochs_done": self.epoch,
            "skip_counts": dict(self.skip_counts),
            "dataset": self.dataset.describe(),
            "config": self.config.to_dict(),
            "model": str(model_path),
            "world_size": self.world_size,
            "threads_used": sorted(self.threads_used),
            "runtime_s": {"steps": len(steps), "total": float(steps.sum()),
                          "step_median": float(np.median(steps)) if len(steps) else None},
            "provenance": provenance(seeds={"training": self.config.seed}, device=str(self.device),
                                     num_threads=torch.get_num_threads()),
        }
