"""Command line of the experiment harness: ``python -m gr_graph.experiments TABLE [options]``.

Without ``--cell``/``--list``/``--report`` every unfinished cell runs in order (a cell that
fails is reported and the next one runs; the exit status is 1 if any failed), finished
memories are pruned, then the report is written; cells with a current published record
(:mod:`gr_graph.experiments.records`) count as finished unless ``--no-records``. ``--cell K``
runs one cell (index or key) and prunes, without the report. ``--report`` only writes the
report of the finished cells.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from gr_graph.cli_common import add_device, add_log_level, make_parser, setup_logging
from gr_graph.experiments.cells import BUDGETS, TABLES, Cell, cells_for
from gr_graph.experiments.records import RECORDS_DIR, read_records
from gr_graph.experiments.run_cell import CellBusyError, CellDependencyError, is_done, prune_finished, run_cell

log = logging.getLogger(__name__)

__all__ = ["main", "build_parser", "list_cells", "default_root"]

EXAMPLES = (
    "python -m gr_graph.experiments table1 --list",
    "python -m gr_graph.experiments table1 --root runs/experiments",
    "python -m gr_graph.experiments table2 --root runs/experiments --cell 0",
    "python -m gr_graph.experiments ablations --budget smoke --root /tmp/exp-smoke",
    "python -m gr_graph.experiments table1 --root runs/experiments --report --publish",
)


def default_root(budget: str) -> Path:
    """``runs/experiments`` (paper budget) or ``runs/experiments-<budget>``."""
    return Path("runs/experiments" if budget == "paper" else f"runs/experiments-{budget}")


def build_parser():  # noqa: ANN201 (argparse.ArgumentParser)
    """The argument parser of ``python -m gr_graph.experiments``."""
    ap = make_parser("python -m gr_graph.experiments", __doc__.split("\n\n")[0] + " " + __doc__.split("\n\n")[1],
                     EXAMPLES)
    ap.add_argument("table", choices=TABLES, help="which table's cells")
    ap.add_argument("--root", default=None, metavar="DIR",
                    help="results root; cells go to DIR/<table>/<key> (default: runs/experiments[-<budget>])")
    ap.add_argument("--budget", choices=tuple(BUDGETS), default="paper",
                    help="; ".join(f"{name}: {b.description}" for name, b in BUDGETS.items()))
    ap.add_argument("--list", action="store_true", help="print the cells (index, key, estimated wall minutes on 2 cores, what)")
    ap.add_argument("--cell", default=None, metavar="K", help="run only cell K (index or key)")
    ap.add_argument("--report", action="store_true", help="only write the report of the finished cells")
    ap.add_argument("--publish", action="store_true",
                    help="also write benchmarks/results/<table>.md (+ .json, figures/) and a record of each cell "
                         "finished in the root (benchmarks/results/cells/<budget>/<table>/<key>.json)")
    ap.add_argument("--publish-records", action="store_true",
                    help="only write the records of the cells finished in the root (benchmarks/results/cells/), "
                         "not the table: for a root that holds part of a table whose published report stays")
    ap.add_argument("--no-records", action="store_true",
                    help="report only the cells in the root (default: cells missing there are taken from the "
                         "published records whose definition is current, named in the report)")
    add_device(ap, "torch device of training and densification")
    add_log_level(ap)
    return ap


def list_cells(cells: list[Cell], root: Path | None = None, records_dir: Path | None = None,
               budget: str = "paper") -> str:
    """One line per cell: index, key, estimated wall minutes (2 cores), done, what; then the total.

    done: ``yes`` (finished in ``root``), ``rec`` (a current published record in ``records_dir``), ``-``.
    """
    recorded = read_records(records_dir, budget, cells).results if records_dir is not None else {}
    rows = [f"{'#':>3}  {'key':<24} {'est. min':>12}  {'done':<4}  what"]
    for i, c in enumerate(cells):
        done = "yes" if root is not None and is_done(root, c) else ("rec" if c.key in recorded else "-")
        rows.append(f"{i:>3}  {c.key:<24} {c.est_minutes:>12.1f}  {done:<4}  {c.what}")
    total = sum(c.est_minutes for c in cells)
    rows.append(f"{len(cells)} cells, estimated {total:.0f} minutes ({total / 60:.1f} h) on 2 cores")
    return "\n".join(rows)


def _pick(cells: list[Cell], k: str) -> Cell:
    if k.isdigit():
        i = int(k)
        if not 0 <= i < len(cells):
            raise SystemExit(f"error: --cell {k}: there are {len(cells)} cells (0-{len(cells) - 1}); see --list")
        return cells[i]
    for c in cells:
        if c.key == k:
            return c
    raise SystemExit(f"error: --cell {k}: no such cell key; see --list")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring); returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.cell is not None:  # one cell: the whole-table options would be silently ignored
        whole = [o for o, on in (("--list", args.list), ("--report", args.report), ("--publish", args.publish),
                                 ("--publish-records", args.publish_records)) if on]
        if whole:
            parser.error(f"--cell runs one cell; {', '.join(whole)} work(s) on the whole table: run it without "
                         "--cell once the cells are done")
    setup_logging(args.log_level)
    root = Path(args.root) if args.root else default_root(args.budget)
    budget = BUDGETS[args.budget]
    cells = cells_for(args.table, budget)
    command = f"python -m gr_graph.experiments {args.table} --budget {args.budget} --root {root}"
    if args.device != "cpu":
        command += f" --device {args.device}"
    records = None if args.no_records else RECORDS_DIR
    if args.list:
        print(list_cells(cells, root, records, budget.name))
        return 0
    if args.publish_records:
        from gr_graph.experiments.report import publish_records

        for p in publish_records(root, budget, cells):
            print(p)
        return 0
    if args.report:
        from gr_graph.experiments.report import write_report

        print(write_report(args.table, root, budget, cells, command, args.publish, args.device, records))
        return 0
    todo = [_pick(cells, args.cell)] if args.cell is not None else cells
    if args.cell is None and records is not None:
        recorded = read_records(records, budget.name, cells).results
        skip = [c.key for c in cells if c.key in recorded and not is_done(root, c)]
        if skip:
            log.info("skipping %d cell(s) with a current published record (--no-records runs them): %s",
                     len(skip), ", ".join(skip))
            todo = [c for c in cells if c.key not in skip]
    failed = []
    for c in todo:
        try:
            run_cell(root, c, args.device, command + (f" --cell {c.key}" if args.cell is not None else ""),
                     budget=budget.name)
        except (CellDependencyError, CellBusyError) as exc:  # not this process's to run now
            log.error("%s", exc)
            failed.append(c.key)
        except Exception:  # one failing cell must not lose the others' runs; reported and counted
            if args.cell is not None:
                raise
            log.exception("%s/%s failed", c.table, c.key)
            failed.append(c.key)
        for p in prune_finished(root, cells):
            log.info("pruned %s", p)
    if args.cell is None:
        from gr_graph.experiments.report import write_report

        print(write_report(args.table, root, budget, cells, command, args.publish, args.device, records))
    if failed:
        print(f"{len(failed)} cell(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0
