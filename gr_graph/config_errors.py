"""Readable messages for invalid configurations (pydantic validation errors).

Used by ``gr_graph.config.load_config`` (``python -m gr_graph.slam``) and by the trainer's
``training.config`` (``python -m training.train``), so that both refuse a bad configuration the
same way: one line per problem, naming the key by its dotted path; an unknown key also lists
the valid keys of the section it appeared in, at any nesting level (``training.trainer.net``).
"""

from __future__ import annotations

import types
import typing
from typing import Any

from pydantic import BaseModel, ValidationError

__all__ = ["describe_validation_error", "model_at"]


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The pydantic model classes in a field annotation (``Model``, ``Model | None``, ...)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return [m for arg in typing.get_args(annotation) for m in _models_in(arg)]
    return []


def model_at(model: type[BaseModel], path: tuple[Any, ...]) -> type[BaseModel] | None:
    """The model class of the section at ``path`` below ``model`` (None if it is not a model)."""
    for key in path:
        field = model.model_fields.get(key) if isinstance(key, str) else None
        models = _models_in(field.annotation) if field is not None else []
        if not models:
            return None
        model = models[0]
    return model


def describe_validation_error(exc: ValidationError, model: type[BaseModel], what: str = "configuration") -> str:
    """One message for all errors of ``exc`` raised while validating ``model``.

    Parameters
    ----------
    exc : pydantic.ValidationError
    model : type of BaseModel
        The model that was validated (to look up the valid keys of a section).
    what : str
        Names the input, e.g. ``"configuration file cfg.yaml"``; starts the message.

    Returns
    -------
    str
        ``"<what>: unknown key 'training.trainer.net.foo' (valid keys of training.trainer.net:
        n_points, k0, ...)"``, or ``"<what>: training.epochs: Input should be greater than or
        equal to 0 (got -1)"``; several problems are joined by ``"; "``.
    """
    problems = []
    for err in exc.errors():
        loc = tuple(err.get("loc", ()))
        where = ".".join(str(p) for p in loc)
        if err.get("type") == "extra_forbidden":
            section = ".".join(str(p) for p in loc[:-1])
            owner = model_at(model, loc[:-1])
            valid = ", ".join(owner.model_fields) if owner is not None else "?"
            problems.append(f"unknown key {where!r} (valid keys{' of ' + section if section else ''}: {valid})")
            continue
        msg = str(err.get("msg", "invalid"))
        if err.get("type") == "value_error" and "error" in err.get("ctx", {}):
            msg = str(err["ctx"]["error"])  # a validator's own message, without pydantic's "Value error, "
        got = err.get("input")
        shown = "" if isinstance(got, dict) or not loc else f" (got {got!r})"
        problems.append(f"{where}: {msg}{shown}" if where else f"{msg}")
    return f"{what}: " + "; ".join(problems)
