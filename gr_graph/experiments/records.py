"""Published cell records: the figures of finished cells, kept in the repository.

A table's cells may run on different machines, or in sessions whose experiment root does not
outlive them, so a report cannot rely on one ``ROOT`` holding every cell. ``--publish`` writes
each finished cell of ``ROOT`` as ``benchmarks/results/cells/<budget>/<table>/<key>.json``: its
``cell.json`` figures with the noise consistency already computed (the marginals it comes from
stay behind in ``ROOT``), the commit and machine it ran on. A later report fills the cells
missing in its ``ROOT`` from these records, but only where the record's fingerprint equals the
cell's current definition (a changed definition makes a record stale: ignored, logged and
listed in the report). The report names every cell taken from a record and its commit; figures
that need files (trajectories, scans) are drawn only for the cells in ``ROOT``.

A record holds figures, never data that came from elsewhere: no scans, poses or models.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from gr_graph.atomic import atomic_write_json, read_json_or_none
from gr_graph.experiments.cells import Cell, source_mismatch
from gr_graph.provenance import format_machine

log = logging.getLogger(__name__)

__all__ = ["RECORDS_DIR", "read_result", "record_path", "write_records", "read_records", "RecordSet"]

RECORDS_DIR = Path(__file__).resolve().parents[2] / "benchmarks" / "results" / "cells"
#: keys of a cell result that name files or paths of the machine it ran on; left out of a record
_LOCAL_KEYS = ("command",)


#: what every cell result (``cell.json``) and record holds; besides, ``rounds`` (SLAM cells) or ``summary``
#: (registration cells)
_RESULT_KEYS = ("fingerprint", "definition")


def read_result(path: str | Path) -> dict[str, Any] | None:
    """The cell result (``cell.json``) or record in ``path``; None when there is none.

    A file that is not one (cut short, binary, hand-edited or of an older layout: not a mapping with a
    fingerprint, a definition and rounds or a summary) is logged naming it and taken as no result, so
    the cell counts as unfinished (recomputed in a root, missing from a report), never as a crash of
    the report or of the cells after it."""
    p = Path(path)
    doc = read_json_or_none(p)
    if doc is None:
        if p.exists():
            log.warning("%s: not valid JSON: not a cell result; ignored", p)
        return None
    missing = [k for k in _RESULT_KEYS if not isinstance(doc, dict) or k not in doc]
    if missing or not ("rounds" in doc or "summary" in doc):
        log.warning("%s: not a cell result (a mapping with %s and rounds or summary); ignored", p, ", ".join(_RESULT_KEYS))
        return None
    return doc


def record_path(records_dir: str | Path, budget: str, cell: Cell) -> Path:
    """``records_dir/<budget>/<table>/<key>.json`` (keys repeat between budgets)."""
    return Path(records_dir) / budget / cell.table / f"{cell.key}.json"


def _git_of(result: dict[str, Any], slam_metrics: dict[str, Any] | None) -> dict[str, Any]:
    """The commit a cell ran with (``{"commit", "dirty"}``): its own ``git`` entry (cells since
    records exist), else the pipeline's provenance kept in the result or in ``slam/metrics.json``."""
    return (result.get("git") or (result.get("provenance") or {}).get("git")
            or ((slam_metrics or {}).get("provenance") or {}).get("git") or {})


def _machine_of(result: dict[str, Any]) -> str | None:
    """The machine a cell ran on: its own ``machine`` line, else one made of the pipeline's provenance."""
    if result.get("machine"):
        return result["machine"]
    prov = result.get("provenance") or {}
    if not prov:
        return None
    return format_machine(prov.get("cpu") or {}, prov.get("cpu_count"), prov.get("platform"), prov.get("python"))


def write_records(records_dir: str | Path, budget: str, cells: list[Cell], results: dict[str, dict[str, Any]],
                  slam_metrics: dict[str, dict[str, Any] | None] | None = None) -> list[Path]:
    """Write one record per finished cell in ``results`` (key -> result with noise consistency).

    ``slam_metrics`` (key -> the cell's ``slam/metrics.json`` or None) supplies the commit of
    cells whose result does not name it. Returns the written paths.
    """
    written = []
    for c in cells:
        if c.key not in results:
            continue
        res = {k: v for k, v in results[c.key].items() if k not in _LOCAL_KEYS}
        git = _git_of(results[c.key], (slam_metrics or {}).get(c.key))
        res["record"] = {"commit": git.get("commit"), "dirty": git.get("dirty"), "machine": _machine_of(results[c.key])}
        written.append(atomic_write_json(record_path(records_dir, budget, c), res))
    return written


class RecordSet:
    """The usable records of a table's cells (``results``: key -> record), and the keys of stale
    (``stale``), unreadable (``unreadable``) and orphaned records (``orphans``: files of the table
    that name no current cell).

    A cell without a record of its own budget takes another budget's record of the same table and
    key when its fingerprint equals the cell's (budgets that share a cell's definition share its
    result, e.g. a full-route cell of budgets that differ only in the 1,500-frame window);
    ``shared`` maps such keys to the budget the record came from.

    Parameters
    ----------
    records_dir : path
        ``benchmarks/results/cells`` or another folder of the same layout.
    budget : str
        The budget the cells belong to.
    cells : list of Cell
        The table's current cells; a record counts only when its fingerprint equals the cell's.
    """

    def __init__(self, records_dir: str | Path, budget: str, cells: list[Cell]):
        self.results: dict[str, dict[str, Any]] = {}
        self.stale: list[str] = []
        self.unreadable: list[str] = []
        self.shared: dict[str, str] = {}
        keys = {c.key for c in cells}
        tables = {c.table for c in cells}
        self.orphans = sorted(f"{t}/{p.stem}" for t in tables
                              for p in (Path(records_dir) / budget / t).glob("*.json") if p.stem not in keys)
        for c in cells:
            p = record_path(records_dir, budget, c)
            if not p.exists():
                self._share(records_dir, budget, c)
                continue
            rec = read_result(p)
            if rec is None:  # logged
                self.unreadable.append(c.key)
            elif rec.get("fingerprint") != c.fingerprint():
                log.warning("%s: made with another definition of cell %s (stale); ignored", p, c.key)
                self.stale.append(c.key)
            elif (why := source_mismatch(c, rec, _source_record(records_dir, budget, c))) is not None:
                log.warning("%s: %s (stale); ignored", p, why)
                self.stale.append(c.key)
            else:
                self.results[c.key] = rec

    def _share(self, records_dir: str | Path, budget: str, cell: Cell) -> None:
        """Take another budget's record of ``cell`` whose fingerprint equals the cell's, if one exists
        (Table II's densified cells: only one made from the same Table I cell definition, the models
        of that budget's Table I being another budget's otherwise)."""
        for other in sorted(Path(records_dir).glob(f"*/{cell.table}/{cell.key}.json")):
            name = other.parent.parent.name
            rec = read_result(other) if name != budget else None
            if (rec is not None and rec.get("fingerprint") == cell.fingerprint()
                    and source_mismatch(cell, rec, _source_record(records_dir, name, cell)) is None):
                self.results[cell.key] = rec
                self.shared[cell.key] = name
                return

    def provenance_of(self, key: str) -> str:
        """``commit <10 hex>[, uncommitted changes], <machine>[, record of budget <b>]`` of a recorded cell."""
        rec = self.results[key].get("record") or {}
        return (f"commit {(rec.get('commit') or 'unknown')[:10]}{', uncommitted changes' if rec.get('dirty') else ''}, "
                f"{rec.get('machine') or 'machine not recorded'}"
                + (f", record of budget `{self.shared[key]}` (same definition)" if key in self.shared else ""))


def _source_record(records_dir: str | Path, budget: str, cell: Cell) -> dict[str, Any] | None:
    """The record of ``budget`` of the cell ``cell`` uses (``cell.source``, e.g. ``table1/16ch-s0``), or None."""
    if cell.source is None:
        return None
    return read_result(Path(records_dir) / budget / f"{cell.source}.json")


def read_records(records_dir: str | Path, budget: str, cells: list[Cell]) -> RecordSet:
    """The records of ``cells`` of ``budget`` in ``records_dir`` (:class:`RecordSet`)."""
    return RecordSet(records_dir, budget, cells)
