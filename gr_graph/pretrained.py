"""The network weights shipped with gr_graph, and how ``--weights`` names a model.

``--weights pretrained`` (``gr-slam``, ``gr-densify``; ``training.weights`` in a configuration)
means the model in this package's ``data/`` folder: ``pretrained.pt`` (a trainer checkpoint,
format checked on load by :func:`training.trainer.load_model`) and ``pretrained.json``, its
model card (what it was trained on, with which command, and what it changes on held-out seeds
of the synthetic world). It is built by ``python -m training.pretrain`` (see there). Any other
value of ``--weights`` is the path of a ``model.pt`` written by ``gr-train`` or by a
``gr-slam --rounds`` run.

No torch import here: resolving a name is cheap and is done when a configuration is checked.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

__all__ = ["PRETRAINED", "PRETRAINED_WEIGHTS", "PRETRAINED_CARD", "resolve_weights", "weights_sha256", "model_card"]

#: The name ``--weights`` takes for the shipped model.
PRETRAINED = "pretrained"
_DATA = Path(__file__).resolve().parent / "data"
#: The shipped checkpoint and its model card.
PRETRAINED_WEIGHTS = _DATA / "pretrained.pt"
PRETRAINED_CARD = _DATA / "pretrained.json"


def resolve_weights(spec: str | os.PathLike[str]) -> Path:
    """The checkpoint file ``spec`` names: ``"pretrained"`` or a path.

    Raises
    ------
    FileNotFoundError
        Naming the path when there is no such file (for ``"pretrained"``: when this
        installation ships no weights, e.g. a source tree where they were not built).
    """
    if str(spec) == PRETRAINED:
        if not PRETRAINED_WEIGHTS.is_file():
            raise FileNotFoundError(f"--weights pretrained: {PRETRAINED_WEIGHTS} is missing from this installation; "
                                    "build it with `python -m training.pretrain` or pass a model.pt path")
        return PRETRAINED_WEIGHTS
    path = Path(spec).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"--weights {spec}: no model checkpoint at {path} (a model.pt written by gr-train or by "
                                "a gr-slam --rounds run, round_<r>/training/model.pt, or 'pretrained')")
    return path


def weights_sha256(spec: str | os.PathLike[str]) -> str:
    """SHA-256 of the checkpoint ``spec`` names (a run's results depend on the file, not its name)."""
    return hashlib.sha256(resolve_weights(spec).read_bytes()).hexdigest()


def model_card() -> dict[str, Any]:
    """The shipped model's card (``pretrained.json``); FileNotFoundError when it is missing."""
    if not PRETRAINED_CARD.is_file():
        raise FileNotFoundError(f"{PRETRAINED_CARD} is missing from this installation")
    return json.loads(PRETRAINED_CARD.read_text())
