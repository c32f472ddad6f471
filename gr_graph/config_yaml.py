"""Configuration files' YAML, read as a user means it.

PyYAML follows YAML 1.1, which reads an integer written with leading zeros as octal (``seq: 010``
would be sequence 8) and two numbers joined by a colon as base 60 (``frames: 10:50`` would be 650).
:func:`read_config_yaml` is the safe loader with the first read in decimal, as YAML 1.2 does, and
the second kept as the text written (a frame range). Hexadecimal (``0x``) and binary (``0b``)
integers keep their base. Used by the SLAM and training configs.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

__all__ = ["read_config_yaml", "read_config_file"]


class _ConfigLoader(yaml.SafeLoader):
    """YAML's safe loader, but for integers with leading zeros (decimal) or a colon (text)."""


def _decimal_int(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> int | str:
    written = str(loader.construct_scalar(node))
    if ":" in written:  # YAML 1.1's base 60: the text (e.g. a frame range)
        return written
    text = written.replace("_", "")
    digits = text.lstrip("+-")
    if len(digits) > 1 and digits.startswith("0") and digits.isdigit():
        return int(text, 10)
    return yaml.SafeLoader.construct_yaml_int(loader, node)


_ConfigLoader.add_constructor("tag:yaml.org,2002:int", _decimal_int)


def read_config_yaml(text: str) -> Any:
    """The objects of YAML ``text`` (safe loading; integers with leading zeros in decimal, YAML 1.1's
    base-60 integers as their text).

    Raises
    ------
    yaml.YAMLError
        Text that is not valid YAML.
    """
    return yaml.load(text, Loader=_ConfigLoader)  # noqa: S506 (a SafeLoader)


def read_config_file(path: str | os.PathLike[str], what: str = "config file") -> tuple[str, Any]:
    """The text of the YAML/JSON file ``path`` and its objects (:func:`read_config_yaml`).

    Raises
    ------
    FileNotFoundError
        If there is no file at ``path`` (the message starts with ``what``).
    ValueError
        Naming the file: not UTF-8 text, not readable, or not valid YAML.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{what} not found: {p}")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{p}: not a UTF-8 text file ({exc.reason} at byte {exc.start}): not a config file") from None
    except OSError as exc:  # e.g. not readable
        raise ValueError(f"{p}: cannot be read ({exc.strerror or exc})") from None
    try:
        return text, read_config_yaml(text)
    except yaml.YAMLError as exc:  # e.g. a tab in the indentation, an unclosed bracket
        raise ValueError(f"{p}: not valid YAML: {exc}") from None
