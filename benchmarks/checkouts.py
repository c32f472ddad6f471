"""Helpers of the benchmarks that compare this checkout with another one (``--compare DIR``).

A measurement runs in fresh processes, alternating between the checkouts on every repeat so
that a machine whose speed drifts affects both alike; each process imports the code of its own
checkout (``PYTHONPATH`` and working directory set to it).
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from gr_graph.provenance import git_state

__all__ = ["checkout_label", "run_alternating"]


def checkout_label(tree: Path) -> str:
    """``tree``'s short commit, with ", uncommitted changes" when its tracked files differ from it."""
    state = git_state(tree)
    if state["commit"] is None:
        return "not a git checkout"
    return state["commit"][:7] + (", uncommitted changes" if state["dirty"] else "")


def run_alternating(script: Path, trees: dict[str, Path], repeats: int, child_args: Callable[[str, int], list[str]],
                    report: Callable[[str, int, str], None] | None = None) -> dict[str, list[str]]:
    """Run ``python script *child_args(name, repeat)`` in every checkout of ``trees``, in turn, ``repeats`` times.

    Returns the last line of each run's standard output, per checkout name. ``report(name,
    repeat, line)`` is called after every run. A failing run raises ``SystemExit`` with its
    error output and the checkout it ran in.
    """
    out: dict[str, list[str]] = {name: [] for name in trees}
    for rep in range(repeats):
        for name, tree in trees.items():
            cmd = [sys.executable, str(script), *child_args(name, rep)]
            res = subprocess.run(cmd, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)}, capture_output=True,
                                 text=True)
            if res.returncode:
                raise SystemExit(f"the {name} checkout ({tree}) failed:\n{res.stderr[-2000:]}")
            lines = res.stdout.strip().splitlines()
            if not lines:
                raise SystemExit(f"the {name} checkout ({tree}) printed nothing (its last line is the result):\n"
                                 f"{res.stderr[-2000:]}")
            out[name].append(lines[-1])
            if report is not None:
                report(name, rep, out[name][-1])
    return out
