"""Re-run ``notebooks/marginal_covariances.ipynb`` and store it with its outputs (figures).

Usage (from the repository root)::

    python scripts/regenerate_notebook.py               # makes the run, executes, writes the notebook
    python scripts/regenerate_notebook.py --run DIR     # executes on an existing run of gr_graph.slam

Without ``--run`` the run is the short synthetic revisit run of the tests
(``tests/slam_support.run_revisit``: 160 frames of the generated route that pass the same street
twice, so the figures show loop closures), written to ``runs/notebook`` (about 2 minutes on one
core) and reused when it is already there. The notebook is executed with nbclient from the
repository root with ``GR_GRAPH_RUN_DIR`` set to the run (a path relative to the root, so the
stored outputs name no local directory) and written back atomically with its outputs; the
kernel's execution timestamps are removed so that a rerun on the same run changes only what
changed.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NOTEBOOK = REPO / "notebooks" / "marginal_covariances.ipynb"
DEFAULT_RUN = Path("runs") / "notebook"


def make_run(run_dir: Path) -> None:
    """The tests' short revisit run into ``run_dir`` (skipped when it is finished there)."""
    sys.path.insert(0, str(REPO / "tests"))
    from slam_support import run_revisit

    run_revisit(run_dir)


def execute(notebook: Path, run_dir: Path, timeout_s: int = 600) -> int:
    """Execute ``notebook`` on ``run_dir`` and write it back with its outputs; return the figure count."""
    import nbclient
    import nbformat

    from gr_graph.atomic import atomic_write_text

    nb = nbformat.read(notebook, as_version=4)
    os.environ["GR_GRAPH_RUN_DIR"] = str(run_dir)
    os.environ.setdefault("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    nbclient.NotebookClient(nb, timeout=timeout_s, kernel_name="python3",
                            resources={"metadata": {"path": str(REPO)}}).execute()
    for cell in nb.cells:
        cell.get("metadata", {}).pop("execution", None)
    nb.metadata.pop("widgets", None)
    atomic_write_text(notebook, nbformat.writes(nb) + "\n")
    return sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code" for o in c.outputs)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python scripts/regenerate_notebook.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", default=None, metavar="DIR",
                    help=f"an existing gr_graph.slam output directory (default: make {DEFAULT_RUN})")
    args = ap.parse_args(argv)
    os.chdir(REPO)
    if args.run is None:
        run_dir = DEFAULT_RUN
        make_run(REPO / run_dir)
    else:
        run_dir = Path(args.run)
    n = execute(NOTEBOOK, run_dir)
    print(f"{NOTEBOOK.relative_to(REPO)}: executed on {run_dir}, {n} figures stored")
    return 0


if __name__ == "__main__":
    sys.exit(main())
