"""Configuration of the trainer as pydantic models: the network and Algorithm 1's run.

* :class:`NetConfig`: hyper-parameters of the covariance network and of its input sampling
  (stored in every ``model.pt`` / ``checkpoint.pt``);
* :class:`TrainOptions`: the training hyper-parameters a user chooses (learning rate, loss
  weights, ..., ``net``). This is also the type of ``gr_graph``'s ``training.trainer`` section;
* :class:`TrainConfig`: :class:`TrainOptions` plus the settings of one run (``epochs``,
  ``seed``, ``device``, ``progress``, ``init_checkpoint``), which ``gr_graph.slam`` sets
  from ``training.epochs`` / ``training.seed``, the top-level ``device``, ``output.progress``
  and the warm start of rounds >= 2.

Every model forbids unknown keys at every level and validates ranges, also on assignment.
:func:`load_train_config` and :meth:`TrainConfig.from_dict` turn validation errors into a
:class:`TrainConfigError` whose message names the offending key and, for an unknown key,
lists the valid ones (:func:`gr_graph.config_errors.describe_validation_error`).
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from gr_graph.config_errors import describe_validation_error

if TYPE_CHECKING:
    import numpy as np

    from training.neighbors import Neighborhoods

__all__ = ["NetConfig", "TrainOptions", "TrainConfig", "TrainConfigError", "RUN_KEYS", "ADDED_TRAIN_OPTIONS", "load_train_config"]

# TrainConfig keys that belong to one run rather than to the method; gr_graph sets them itself.
RUN_KEYS = ("epochs", "seed", "device", "progress", "init_checkpoint")

#: trainer options added after runs were published, with their defaults: they count in checkpoint
#: resume keys and round fingerprints only when not at their default
ADDED_TRAIN_OPTIONS: dict[str, Any] = {"corr_likelihood": "gaussian", "corr_dof": 4.0}


class TrainConfigError(ValueError):
    """A training configuration is invalid; the message names the key (and, for an unknown
    key, the valid ones)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class NetConfig(_Strict):
    """Hyper-parameters of :class:`training.network.CovarianceNet` and of its input sampling."""

    n_points: int = Field(2048, ge=1, description="points per network input (scans are subsampled / split to this size)")
    k0: int = Field(16, ge=1, description="group size of set-abstraction level 0 (every point)")
    ratio1: int = Field(4, ge=1, description="centroid down-sampling ratio of level 1")
    k1: int = Field(16, ge=1, description="group size of level 1")
    ratio2: int = Field(4, ge=1, description="centroid down-sampling ratio of level 2")
    k2: int = Field(16, ge=1, description="group size of level 2")
    c0: int = Field(32, ge=1, description="feature width of level 0")
    c1: int = Field(64, ge=1, description="feature width of level 1")
    c2: int = Field(128, ge=1, description="feature width of level 2")
    cov_scale: float = Field(0.1, gt=0.0, description="scale of the Cholesky factor at zero output: C ~ cov_scale^2 I [m]")
    eps: float = Field(1e-6, ge=0.0, description="the paper's epsilon added to the diagonal of C [m^2]; > 0 with the "
                       "Cholesky head, whose C can be singular without it (the geometric head adds its own floor)")
    sampling: Literal["random", "fps"] = Field("random", description="centroid sampling of the set-abstraction levels")
    head: Literal["geometric", "cholesky"] = Field("geometric", description="output head (training.network docstring)")
    kw: int = Field(16, ge=1, description="wide neighbours (level-1 centroids) per point of the geometric head")

    @model_validator(mode="after")
    def _cholesky_needs_eps(self) -> "NetConfig":
        if self.head == "cholesky" and self.eps <= 0.0:
            raise ValueError("eps must be > 0 with the Cholesky head (its L Lᵀ can be singular)")
        return self

    def neighborhoods(self, points: np.ndarray, start: int = 0) -> Neighborhoods:
        """Neighbour indices of ``points`` for this configuration (``start`` seeds the sampling)."""
        from training.neighbors import build_neighborhoods

        return build_neighborhoods(points, self.k0, self.ratio1, self.k1, self.ratio2, self.k2, start, self.sampling, self.kw)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (stored in checkpoints)."""
        return self.model_dump()


class TrainOptions(_Strict):
    """The hyper-parameters of Algorithm 1 a user chooses (the paper's Omega), without run settings.

    Pair sampling, losses and the optimiser; ``net`` configures the network. Units: Gamma is
    ``diag(gamma_rot_std^2 (rad^2) x3, gamma_trans_std^2 (m^2) x3)``.
    """

    lr: float = Field(1e-3, gt=0.0, description="Adam learning rate (the paper's eta)")
    lambda_corr: float = Field(1.0, ge=0.0, description="weight of the correspondence NLL")
    lambda_pose: float = Field(1.0, ge=0.0, description="weight of the pose NLL")
    gamma_rot_std: float = Field(2e-3, gt=0.0, description="std of the pose observation noise, rotation [rad]")
    gamma_trans_std: float = Field(2e-2, gt=0.0, description="std of the pose observation noise, translation [m]")
    corr_reduction: Literal["mean", "sum"] = Field("mean", description="over a pair's correspondences; 'sum' is the paper's")
    corr_likelihood: Literal["gaussian", "student_t"] = Field(
        "student_t", description="distribution of the correspondence residuals: 'student_t' (heavy-tailed: "
        "correspondences on another surface weigh little; training.losses) or 'gaussian' (the paper's; the default "
        "until 2026-12-05)")
    corr_dof: float = Field(4.0, gt=0.0, description="degrees of freedom of corr_likelihood 'student_t'")
    max_corr: int = Field(1024, ge=3, description="correspondences per pair used at most (random subset above)")
    min_corr: int = Field(16, ge=3, description="pairs with fewer correspondences are skipped")
    pairs_per_step: int = Field(1, ge=1, description="pairs whose losses are averaged per Adam step (per process)")
    augment_yaw: bool = Field(True, description="random yaw rotation of each sample's target frame")
    checkpoint_every: int = Field(50, ge=1, description="steps between checkpoints (also written at every epoch end)")
    grad_clip: float = Field(10.0, ge=0.0, description="max gradient norm; 0 disables clipping")
    num_threads: int | None = Field(None, ge=1, description="torch threads of the run; None: torch's default (the core count)")
    max_skip_fraction: float = Field(0.5, ge=0.0, le=1.0, description="abort if more of an epoch's pairs are skipped")
    net: NetConfig = Field(default_factory=NetConfig, description="network / input sampling")

    @model_validator(mode="after")
    def _some_loss(self) -> TrainOptions:
        if self.lambda_corr + self.lambda_pose == 0:
            raise ValueError("lambda_corr and lambda_pose must not both be 0")
        return self


class TrainConfig(TrainOptions):
    """:class:`TrainOptions` plus the settings of one training run (see the module docstring)."""

    epochs: int = Field(1, ge=0, description="passes over all edges (the paper's I)")
    seed: int = Field(0, ge=0, description="seeds the initial weights and all sampling")
    device: str = Field("cpu", description="'cpu', 'cuda' or 'cuda:N'")
    progress: bool = Field(True, description="tqdm bar with running losses")
    init_checkpoint: str | None = Field(None, description="start from the weights of this model.pt / checkpoint.pt")

    @field_validator("device")
    @classmethod
    def _known_device(cls, v: str) -> str:
        if not re.fullmatch(r"cpu|cuda(:\d+)?", v):
            raise ValueError("must be 'cpu', 'cuda' or 'cuda:N'")
        return v

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | BaseModel | None = None) -> TrainConfig:
        """Build from a (possibly partial) mapping or a pydantic model (e.g. a :class:`TrainConfig`).

        Raises
        ------
        TrainConfigError
            On an unknown key (at any level, ``net`` included; the message lists the valid
            keys) or an out-of-range value.
        """
        if isinstance(d, BaseModel):
            d = d.model_dump()
        try:
            return cls.model_validate(dict(d or {}))
        except ValidationError as exc:
            raise TrainConfigError(describe_validation_error(exc, cls, what="training config")) from None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-serialisable dict."""
        return self.model_dump()

    def resume_key(self) -> dict[str, Any]:
        """Settings that must match for a checkpoint to be resumed."""
        d = self.to_dict()
        for k in ("epochs", "progress", "device", "num_threads", "checkpoint_every", "max_skip_fraction"):
            d.pop(k)
        for k, default in ADDED_TRAIN_OPTIONS.items():  # count only when set: older checkpoints stay resumable
            if d.get(k) == default:
                d.pop(k)
        if d.get("init_checkpoint"):  # the starting weights' content, not their path (relative or absolute,
            p = Path(d.pop("init_checkpoint"))  # a moved run folder, a harness cell's copy: the same weights)
            d["init_checkpoint_sha256"] = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None
        return d


def load_train_config(path: str | os.PathLike[str] | None = None, overrides: Mapping[str, Any] | None = None) -> TrainConfig:
    """Defaults, then a YAML/JSON file of :class:`TrainConfig` keys, then ``overrides``.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    TrainConfigError
        If the file is not UTF-8 text or valid YAML, not a mapping, or a key is unknown (message: the key, the file and the
        valid keys) or a value out of range.
    """
    data: dict[str, Any] = {}
    what = "training config"
    if path is not None:
        from gr_graph.config_yaml import read_config_file

        p = Path(path)
        try:
            loaded = read_config_file(p, "training config file")[1] or {}
        except ValueError as exc:  # not text, not readable, not YAML: named
            raise TrainConfigError(str(exc)) from None
        if not isinstance(loaded, dict):
            raise TrainConfigError(f"{p}: a training config file must hold a mapping of TrainConfig keys")
        data = loaded
        what = f"training config {p}"
    data.update(overrides or {})
    try:
        return TrainConfig.model_validate(data)
    except ValidationError as exc:
        raise TrainConfigError(describe_validation_error(exc, TrainConfig, what=what)) from None
