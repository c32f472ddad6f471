"""The pieces every command line of the project shares: one spelling per flag, help with
examples and defaults, and logging setup.

Commands: ``gr_graph.slam``, ``gr_graph.global_registration``, ``gr_graph.densify_cli``,
``gr_graph.datasets.synthetic`` (and ``.plots``), ``gr_graph.datasets.realism``, ``training.train``,
``training.ddp``; the first four are also console commands (``gr-slam``, ``gr-registration``,
``gr-densify``, ``gr-train``: ``[project.scripts]`` in pyproject.toml). A flag that means the
same thing is spelled the same everywhere:

==================  ===================================================================
``--out DIR``       output directory (realism: the JSON file)
``--config FILE``   YAML file of settings
``--seed N``        random seed
``--device D``      ``cpu`` or ``cuda``
``--frames A:B``    half-open frame range
``--channels C``    64, 32 or 16 laser rings (of a 64-beam sensor)
``--sensor NAME``   sensor / beam model: hdl64e, vlp16, os1-64 (``gr_graph.sensors``)
``--data-root DIR`` KITTI odometry root
``--point-format``  ``xyzi`` (16-byte KITTI points) or ``xyz`` (12 bytes, no intensity)
``--threads N``     worker threads
``--no-progress``   no progress bars
``--log-level L``   DEBUG, INFO, WARNING or ERROR (any case)
==================  ===================================================================
"""

from __future__ import annotations

import argparse
import logging
import sys
import textwrap
from collections.abc import Sequence
from typing import Any

from gr_graph.datasets.channels import SUPPORTED_CHANNELS
from gr_graph.datasets.point_layout import POINT_FORMATS
from gr_graph.sensors import SENSOR_MODELS

__all__ = [
    "LOG_LEVELS",
    "HelpFormatter",
    "make_parser",
    "add_log_level",
    "add_no_progress",
    "add_out",
    "add_config",
    "add_seed",
    "add_device",
    "add_frames",
    "add_channels",
    "add_sensor",
    "add_data_root",
    "add_point_format",
    "add_threads",
    "setup_logging",
]

LOG_LEVELS: tuple[str, ...] = ("DEBUG", "INFO", "WARNING", "ERROR")
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
DEVICES: tuple[str, ...] = ("cpu", "cuda")
CHANNELS: tuple[int, ...] = SUPPORTED_CHANNELS
POINT_FORMAT_CHOICES: tuple[str, ...] = tuple(POINT_FORMATS)
SENSOR_CHOICES: tuple[str, ...] = tuple(SENSOR_MODELS)
_WIDTH = 79


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the description's and the examples' line breaks and appends ``(default: X)``
    to every option whose default means something (not None, not False, not a flag)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (
            "%(default)" in text
            or "default:" in text
            or not action.option_strings
            or action.default is None
            or action.default is False
            or action.default == argparse.SUPPRESS
            or action.nargs == 0
        ):
            return text
        return f"{text} (default: %(default)s)"


def make_parser(prog: str, description: str, examples: Sequence[str]) -> argparse.ArgumentParser:
    """An ``ArgumentParser`` with the project's help layout: description, options with
    defaults, then the example commands.

    Paragraphs of ``description`` (separated by blank lines) are re-wrapped, except those
    that start with whitespace (literal blocks, kept as written).
    """
    paragraphs = [par if par[:1].isspace() else textwrap.fill(" ".join(par.split()), _WIDTH)
                  for par in description.strip("\n").split("\n\n")]
    epilog = "examples:\n" + "\n".join(f"  {cmd}" for cmd in examples)
    return argparse.ArgumentParser(prog=prog, description="\n\n".join(paragraphs), epilog=epilog,
                                   formatter_class=HelpFormatter)


def _log_level(text: str) -> str:
    return text.strip().upper()


def number_in(kind: type, low: float, high: float | None = None, low_open: bool = False) -> Any:
    """An argparse ``type``: a number of ``kind`` (int or float) from ``low`` (excluded with ``low_open``,
    then also finite) up to, not including, ``high``; the error names the range."""
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if high is not None:
            if not low <= value < high:
                raise argparse.ArgumentTypeError(f"{text} is not in [{low:g}, {high:g})")
        elif low_open:
            if not low < value < float("inf"):
                raise argparse.ArgumentTypeError(f"{text} is not a finite number > {low:g}")
        elif not value >= low:
            raise argparse.ArgumentTypeError(f"{text} is below {low}")
        return value
    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


def at_least(minimum: float, kind: type = int) -> Any:
    """An argparse ``type``: a number of ``kind`` not below ``minimum`` (:func:`number_in`)."""
    return number_in(kind, minimum)


#: an argparse ``type``: a finite number > 0
positive_float = number_in(float, 0.0, low_open=True)


def add_log_level(p: argparse.ArgumentParser, default: str = "INFO") -> None:
    p.add_argument("--log-level", type=_log_level, choices=LOG_LEVELS, default=default,
                   metavar="{" + ",".join(LOG_LEVELS) + "}", help="logging threshold, any case")


class _DeprecatedAlias(argparse.Action):
    """A hidden old spelling of a store-true flag: sets the flag and says which spelling to use."""

    def __init__(self, option_strings: Sequence[str], dest: str, new: str = "", **kwargs: Any) -> None:
        self.new = new
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        print(f"{parser.prog}: warning: {option_string} is deprecated, use {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, True)


def add_no_progress(p: argparse.ArgumentParser, deprecated: Sequence[str] = ()) -> None:
    """``--no-progress`` (dest ``no_progress``); ``deprecated`` old spellings are hidden aliases."""
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    for old in deprecated:
        p.add_argument(old, action=_DeprecatedAlias, dest="no_progress", new="--no-progress")


def add_out(p: argparse.ArgumentParser, help: str, required: bool = False, default: str | None = None) -> None:
    p.add_argument("--out", required=required, default=default, metavar="DIR", help=help)


def add_config(p: argparse.ArgumentParser, help: str) -> None:
    p.add_argument("--config", default=None, metavar="FILE", help=help)


def add_seed(p: argparse.ArgumentParser, help: str, default: int | None = 0) -> None:
    p.add_argument("--seed", type=int, default=default, metavar="N", help=help)


def add_device(p: argparse.ArgumentParser, help: str = "torch device", default: str | None = "cpu") -> None:
    p.add_argument("--device", choices=DEVICES, default=default, help=help)


def add_frames(p: argparse.ArgumentParser, help: str = "half-open frame range A:B (either side may be empty)") -> None:
    p.add_argument("--frames", default=None, metavar="A:B", help=help)


def add_channels(p: argparse.ArgumentParser, help: str = "laser rings kept (every 1st, 2nd or 4th of 64)",
                 default: int | None = 64) -> None:
    p.add_argument("--channels", type=int, choices=CHANNELS, default=default, help=help)


def add_sensor(p: argparse.ArgumentParser, help: str = "sensor (beam model)", default: str | None = None) -> None:
    p.add_argument("--sensor", choices=SENSOR_CHOICES, default=default, help=help)


def add_data_root(p: argparse.ArgumentParser,
                  help: str = "KITTI odometry root (default: $GR_GRAPH_KITTI_ROOT, ./data/kitti, ~/data/kitti, "
                              "else the synthetic sequence)") -> None:
    p.add_argument("--data-root", default=None, metavar="DIR", help=help)


def add_point_format(p: argparse.ArgumentParser, default: str | None = "xyzi",
                     help: str = "layout of the KITTI .bin files: float32 x,y,z,intensity (16 bytes a point) "
                                 "or x,y,z (12 bytes a point, no intensity)") -> None:
    p.add_argument("--point-format", choices=POINT_FORMAT_CHOICES, default=default, help=help)


def add_threads(p: argparse.ArgumentParser, help: str, default: int | None) -> None:
    p.add_argument("--threads", type=int, default=default, metavar="N", help=help)


def setup_logging(level: str) -> None:
    """Log to stderr at ``level`` (one of :data:`LOG_LEVELS`, any case).

    Adds the project's handler format when the root logger has none yet, and always sets the
    root level, so that the level also applies when a host (a notebook, pytest) configured
    logging first.
    """
    name = level.upper()
    if name not in LOG_LEVELS:
        raise ValueError(f"log level {level!r}: choose one of {', '.join(LOG_LEVELS)}")
    logging.basicConfig(level=name, format=LOG_FORMAT)
    logging.getLogger().setLevel(name)
