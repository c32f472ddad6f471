"""Writing a study's result beside the others: ``benchmarks/results/<name>.md`` and ``.json``.

Shared by the benchmark and study scripts (run as ``python benchmarks/<script>.py``, so this folder
is on ``sys.path``); the files are written atomically (``gr_graph.atomic``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"


def print_and_write(name: str, text: str, document: dict[str, Any], write: bool) -> None:
    """Print the markdown ``text``; with ``write``, also store it as ``results/<name>.md`` and
    ``document`` as ``results/<name>.json``."""
    print(text)
    if write:
        from gr_graph.atomic import atomic_write_json, atomic_write_text

        atomic_write_text(RESULTS / f"{name}.md", text + "\n")
        atomic_write_json(RESULTS / f"{name}.json", document)


def last_change(values: list[float] | tuple[float, ...]) -> str:
    """``+x %``: the last of ``values`` against the first (``n/a`` when the first is 0)."""
    return f"{100.0 * (values[-1] / values[0] - 1.0):+.0f} %" if values[0] > 0 else "n/a"


def change_percent(values: list[float] | tuple[float, ...], reference: list[float] | tuple[float, ...]) -> str:
    """``+m ± s %``: the per-run change of ``values`` against ``reference`` in percent, mean ± sample
    std over the runs (one run: the change alone, no spread)."""
    import numpy as np

    v = 100.0 * (np.asarray(values, float) / np.asarray(reference, float) - 1.0)
    return f"{v.mean():+.1f} ± {v.std(ddof=1):.1f} %" if len(v) > 1 else f"{v[0]:+.1f} %"
