"""Configuration files' YAML, read as a user means it.

PyYAML follows YAML 1.1, which reads an integer written with leading zeros as octal (``seq: 010``
would be sequence 8) and two numbers joined by a colon as base 60 (``frames: 10:50`` would be 650).
:func:`read_config_yaml` is the safe loader with the first read in decimal, as YAML 1.2 does, and
the second kept as the text written (a frame range). Hexadecimal (``0x``) and binary (``0b``)
integers keep their base. Used by the SLAM and training configs.
"""

from __future__ import annotations

from typing import Any

import yaml

__all__ = ["read_config_yaml"]


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
