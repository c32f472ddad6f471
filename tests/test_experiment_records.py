"""Published cell records: a report combines cells run in different roots (machines, sessions)."""

from __future__ import annotations

import dataclasses
import json

import pytest

from gr_graph.experiments import cli, report
from gr_graph.experiments import run_cell as rc
from gr_graph.experiments.cells import BUDGETS, cells_for
from gr_graph.experiments.records import read_records, record_path, write_records


def _result(cell, rpe: list[float], accepted: list[bool]) -> dict:
    rounds = {}
    for r, v in enumerate(rpe):
        slam = dict.fromkeys(rc.METRIC_KEYS)
        slam.update(rpe300_consecutive_mean=v, rpe300_all_pairs_mean=1.1 * v, ate_rmse=v / 2)
        rounds[str(r)] = {"slam": slam, "accepted": None if r == 0 else accepted[r - 1],
                          "nees": {"nees_odometry_mean": 6.0 + r, "nees_loop_mean": None,
                                   "nees_position_mean": 3.0, "odometry_path_error_percent": 0.1}}
    return {"table": cell.table, "key": cell.key, "what": cell.what, "fingerprint": cell.fingerprint(),
            "definition": cell.definition(),
            "command": f"python -m gr_graph.experiments ablations --root /my/machine --cell {cell.key}",
            "wall_s": 60.0, "cpu_s": 100.0, "git": {"commit": f"{cell.seed}" * 40, "dirty": False},
            "machine": "test machine", "rounds": rounds}


@pytest.fixture
def default_cells():
    return [c for c in cells_for("ablations", "paper") if c.group == "default"]


def _report(monkeypatch, tmp_path, root_results: dict, cells, records_dir=None, publish=False) -> str:
    monkeypatch.setattr(report, "_figures", lambda *a, **k: {})
    monkeypatch.setattr(report, "RESULTS_DIR", tmp_path / "published")
    monkeypatch.setattr(report, "read_cell_result", lambda root, c: root_results.get(c.key))
    monkeypatch.setattr(report, "with_noise_consistency", lambda root, c, r: r)  # the results carry it
    monkeypatch.setattr(report, "with_short_range_rpe", lambda root, c, r: r)
    return report.write_report("ablations", tmp_path / "root", BUDGETS["paper"], cells, "cmd", publish=publish,
                               records_dir=records_dir).read_text()


def test_cells_from_two_roots_give_the_report_of_all_cells_in_one(tmp_path, monkeypatch, default_cells):
    rpe = {0: [0.4, 0.3, 0.2], 1: [0.4, 0.6, 0.35], 2: [0.5, 0.45, 0.5]}
    res = {c.key: _result(c, rpe[c.seed], [c.seed != 1, True]) for c in default_cells}
    both = _report(monkeypatch, tmp_path / "a", res, default_cells)
    # session 1 ran seed 0 and published it; session 2 runs seeds 1 and 2 and reads the record
    first = {k: v for k, v in res.items() if k.endswith("s0")}
    _report(monkeypatch, tmp_path / "s1", first, default_cells, publish=True)
    records = tmp_path / "s1" / "published" / "cells"
    rec = json.loads(record_path(records, "paper", default_cells[0]).read_text())
    assert rec["record"] == {"commit": "0" * 40, "dirty": False, "machine": "test machine"}
    assert "command" not in rec  # names a path of the machine it ran on
    assert not record_path(records, "paper", default_cells[1]).exists()
    rest = {k: v for k, v in res.items() if not k.endswith("s0")}
    merged = _report(monkeypatch, tmp_path / "s2", rest, default_cells, records_dir=records)
    tables = [line for line in merged.splitlines() if line.startswith("|")]
    assert tables == [line for line in both.splitlines() if line.startswith("|")]
    assert "cells from published records" in merged
    assert "`default-s0` (commit 0000000000, test machine)" in merged
    assert str(tmp_path) not in record_path(records, "paper", default_cells[0]).read_text()
    assert "cells run in this report's root: `default-s1`, `default-s2`" in merged
    doc = json.loads((tmp_path / "s2" / "root" / "ablations" / "report.json").read_text())
    assert doc["cells"]["default-s0"]["from_record"] and not doc["cells"]["default-s1"]["from_record"]
    # without the records the seed-0 cell is missing
    alone = _report(monkeypatch, tmp_path / "s3", rest, default_cells)
    assert "**missing cells** (not finished): 0 `default-s0`" in alone


def test_root_results_win_over_records_and_stale_records_are_ignored(tmp_path, monkeypatch, default_cells):
    c0 = default_cells[0]
    old = _result(c0, [0.4, 9.0, 9.0], [False, False])
    records = tmp_path / "records"
    write_records(records, "paper", [c0], {c0.key: old})
    new = _result(c0, [0.4, 0.3, 0.2], [True, True])
    md = _report(monkeypatch, tmp_path, {c0.key: new}, [c0], records_dir=records)
    assert "cells from published records" not in md  # the root's own cell is used
    s = json.loads((tmp_path / "root" / "ablations" / "report.json").read_text())["summary"]["default"]
    assert s["steps"]["1-step"]["per_seed"][0]["ate_rmse"] == pytest.approx(0.15)
    # a record made with another definition of the cell: ignored, named in the report
    changed = dataclasses.replace(c0, frames=(0, 700))
    got = read_records(records, "paper", [changed])
    assert got.results == {} and got.stale == [c0.key]
    md = _report(monkeypatch, tmp_path / "b", {}, [changed], records_dir=records)
    assert f"records ignored because the cell's definition changed since: {c0.key}" in md
    assert "**missing cells**" in md
    # a record of a cell that no longer exists: listed, ignored
    (records / "paper" / "ablations" / "gone-s0.json").write_text("{}")
    md = _report(monkeypatch, tmp_path / "o", {}, [c0], records_dir=records)
    assert "records of cells that no longer exist, ignored: ablations/gone-s0" in md
    # a damaged record: ignored and named, never a failed report
    record_path(records, "paper", c0).write_text("{cut short")
    md = _report(monkeypatch, tmp_path / "c", {}, [c0], records_dir=records)
    assert f"unreadable records ignored: {c0.key}" in md
    # valid JSON of another shape (hand-edited, an older layout): the same, not a KeyError of the report
    for i, text in enumerate(("[]", json.dumps({"fingerprint": c0.fingerprint()}))):
        record_path(records, "paper", c0).write_text(text)
        md = _report(monkeypatch, tmp_path / f"shape{i}", {}, [c0], records_dir=records)
        assert f"unreadable records ignored: {c0.key}" in md


def test_a_damaged_cell_json_is_an_unfinished_cell_named_in_the_log(tmp_path, caplog, default_cells):
    """cell.json cut short or of another shape: the cell counts as unfinished (recomputed, logged naming
    the file), never an AttributeError of the harness."""
    from gr_graph.experiments.run_cell import CELL_JSON, _start, cell_dir, read_cell_result

    c0 = default_cells[0]
    path = cell_dir(tmp_path, c0) / CELL_JSON
    path.parent.mkdir(parents=True)
    for text in ("[]", "{cut", json.dumps({"fingerprint": c0.fingerprint(), "definition": {}})):
        path.write_text(text)
        caplog.clear()
        with caplog.at_level("WARNING", logger="gr_graph.experiments.records"):
            assert read_cell_result(tmp_path, c0) is None
        assert f"{path}: not" in caplog.text
        _start(tmp_path, c0, "paper")  # no crash: the cell is started again
    whole = _result(c0, [0.4, 0.3, 0.2], [True, True])
    path.write_text(json.dumps(whole))
    assert read_cell_result(tmp_path, c0) == whole


def test_a_cell_shared_by_two_budgets_takes_the_other_budgets_record(tmp_path):
    """The full-route cell is the same definition in student-t-adds and its revisit variant: one
    record serves both, named as the other budget's; a different definition is not taken."""
    full = next(c for c in cells_for("table1", "student-t-adds") if c.key == "full-16ch-s0")
    twin = next(c for c in cells_for("table1", "student-t-adds-revisit") if c.key == "full-16ch-s0")
    window = next(c for c in cells_for("table1", "student-t-adds-revisit") if c.key == "16ch-s0")
    window_0_1500 = next(c for c in cells_for("table1", "student-t-adds") if c.key == "16ch-s0")
    assert twin.fingerprint() == full.fingerprint() and window.fingerprint() != window_0_1500.fingerprint()
    records = tmp_path / "records"
    write_records(records, "student-t-adds", [full, window_0_1500],
                  {c.key: _result(c, [3.0, 2.5], [True]) for c in (full, window_0_1500)})
    got = read_records(records, "student-t-adds-revisit", [twin, window])
    assert set(got.results) == {twin.key} and got.shared == {twin.key: "student-t-adds"}
    assert "record of budget `student-t-adds`" in got.provenance_of(twin.key)
    assert got.stale == [] and got.orphans == []
    # the budget's own record wins
    write_records(records, "student-t-adds-revisit", [twin], {twin.key: _result(twin, [3.0, 2.0], [True])})
    own = read_records(records, "student-t-adds-revisit", [twin])
    assert own.shared == {} and own.results[twin.key]["rounds"]["1"]["slam"]["rpe300_consecutive_mean"] == 2.0


def test_table2_densified_cells_take_only_results_made_from_their_own_table1_models(tmp_path):
    """Table II's cell definitions are equal across budgets, but the densified cells use that budget's Table I
    models: another budget's record is shared only for the raw scans, or when it names the same Table I cell
    definition; in a root, a result or a source of another definition is not this budget's."""
    paper = {c.key: c for c in cells_for("table2", "paper")}
    t = {c.key: c for c in cells_for("table2", "student-t")}
    src_paper = next(c for c in cells_for("table1", "paper") if c.key == "16ch-s0")
    src_t = next(c for c in cells_for("table1", "student-t") if c.key == "16ch-s0")
    r0, r1 = "16ch-s0-r0", "16ch-s0-r1"
    assert paper[r1].fingerprint() == t[r1].fingerprint() and src_paper.fingerprint() != src_t.fingerprint()
    assert t[r1].source_fingerprint == src_t.fingerprint() and t[r0].source_fingerprint is None
    records = tmp_path / "records"
    figures = {"summary": {"kiss_matcher": {"success_rate": 0.35}}}
    for cell in (src_paper, paper[r0], paper[r1]):
        atomic = record_path(records, "paper", cell)
        atomic.parent.mkdir(parents=True, exist_ok=True)
        atomic.write_text(json.dumps({"fingerprint": cell.fingerprint(), "definition": cell.definition(), **figures}))
    got = read_records(records, "student-t", [t[r0], t[r1]])
    assert got.shared == {r0: "paper"} and r1 not in got.results  # the paper's models are not the t's
    assert set(read_records(records, "paper", [paper[r0], paper[r1]]).results) == {r0, r1}  # its own: kept
    # a record that names the t's Table I cell is shared; one of the budget itself naming another is stale
    record_path(records, "paper", paper[r1]).write_text(json.dumps(
        {"fingerprint": paper[r1].fingerprint(), "definition": paper[r1].definition(),
         "source_fingerprint": src_t.fingerprint(), **figures}))
    assert read_records(records, "student-t", [t[r1]]).shared == {r1: "paper"}
    mine = record_path(records, "student-t", t[r1])
    mine.parent.mkdir(parents=True)
    mine.write_text(json.dumps({"fingerprint": t[r1].fingerprint(), "definition": t[r1].definition(),
                                "source_fingerprint": "0" * 16, **figures}))
    assert read_records(records, "student-t", [t[r1]]).stale == [r1]
    # in a root: a finished result made from the paper's Table I cell is not done for the t, and running it
    # on that source is refused naming both definitions
    root = tmp_path / "root"
    for cell in (src_paper, paper[r1]):
        d = rc.cell_dir(root, cell)
        d.mkdir(parents=True)
        (d / rc.CELL_JSON).write_text(json.dumps({"fingerprint": cell.fingerprint(), "definition": cell.definition(),
                                                  "rounds": {}}))
    assert rc.is_done(root, paper[r1]) and not rc.is_done(root, t[r1])
    with pytest.raises(rc.CellDependencyError, match=f"this root's was made with another definition "
                                                     f"\\({src_paper.fingerprint()}"):
        rc._run_registration_cell(root, rc.cell_dir(root, t[r1]), t[r1], "cpu")


def test_run_all_skips_recorded_cells_and_list_marks_them(tmp_path, monkeypatch, capsys):
    cells = cells_for("ablations", "smoke")
    records = tmp_path / "records"
    write_records(records, "smoke", [cells[1]], {cells[1].key: _result(cells[1], [0.4, 0.3], [True])})
    # the same key of the paper budget (a different cell) is no record of the smoke one
    paper = cells_for("ablations", "paper")
    write_records(records, "paper", [paper[2]], {paper[2].key: _result(paper[2], [0.4, 0.3], [True])})
    monkeypatch.setattr(cli, "RECORDS_DIR", records)
    ran: list[str] = []
    monkeypatch.setattr(cli, "run_cell", lambda root, c, device, command, budget=None: ran.append(c.key))
    monkeypatch.setattr(cli, "prune_finished", lambda root, cells: [])
    monkeypatch.setattr(report, "write_report", lambda *a, **k: tmp_path / "report.md")
    root = str(tmp_path / "exp")
    assert cli.main(["ablations", "--budget", "smoke", "--root", root]) == 0
    assert ran == [c.key for c in cells if c.key != cells[1].key]
    ran.clear()
    assert cli.main(["ablations", "--budget", "smoke", "--root", root, "--no-records"]) == 0
    assert ran == [c.key for c in cells]
    ran.clear()
    assert cli.main(["ablations", "--budget", "smoke", "--root", root, "--cell", cells[1].key]) == 0
    assert ran == [cells[1].key]  # asked for by name: run
    capsys.readouterr()
    assert cli.main(["ablations", "--budget", "smoke", "--root", root, "--list"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows[2].split()[3] == "rec" and rows[1].split()[3] == "-"


def test_publish_records_writes_records_and_leaves_the_table(tmp_path, monkeypatch, default_cells, capsys):
    c0 = default_cells[0]
    res = _result(c0, [0.4, 0.3, 0.2], [True, True])
    res.pop("git")  # a cell finished before cell.json named its commit and machine: the pipeline's provenance does
    res.pop("machine")
    res["provenance"] = {"cpu": {"model": "Some CPU"}, "cpu_count": 2, "platform": "Linux-x", "python": "3.11.7"}
    root = tmp_path / "exp"
    (rc.cell_dir(root, c0) / "slam").mkdir(parents=True)
    (rc.cell_dir(root, c0) / "slam" / "metrics.json").write_text(json.dumps({"provenance": {"git": {"commit": "ab" * 20}}}))
    monkeypatch.setattr(report, "RESULTS_DIR", tmp_path / "published")
    monkeypatch.setattr(report, "read_cell_result", lambda r, c: res if c.key == c0.key else None)
    monkeypatch.setattr(report, "with_noise_consistency", lambda r, c, x: x)
    monkeypatch.setattr(report, "with_short_range_rpe", lambda r, c, x: x)
    assert cli.main(["ablations", "--root", str(root), "--publish-records"]) == 0
    assert capsys.readouterr().out.strip() == str(record_path(tmp_path / "published" / "cells", "paper", c0))
    rec = json.loads(record_path(tmp_path / "published" / "cells", "paper", c0).read_text())
    assert rec["record"]["commit"] == "ab" * 20 and rec["rounds"] == res["rounds"]
    assert rec["record"]["machine"] == "Some CPU, 2 cores, Linux-x, Python 3.11.7"
    assert not (tmp_path / "published" / "ablations.md").exists()


def test_cells_refuse_to_run_on_a_kitti_root_found_on_the_machine(tmp_path, monkeypatch):
    """A cell's fingerprint says synthetic world; a KITTI root in the environment must not swap in
    real scans under it (records would mix them)."""
    cell = cells_for("ablations", "smoke")[0]
    (tmp_path / "kitti" / "sequences" / "00" / "velodyne").mkdir(parents=True)
    cfg = rc._slam_config(tmp_path / "cell", cell, "cpu")
    monkeypatch.delenv("GR_GRAPH_KITTI_ROOT", raising=False)
    from gr_graph.datasets import registry

    monkeypatch.setattr(registry, "_DEFAULT_ROOTS", (tmp_path / "no-kitti-here",))
    rc._require_synthetic(cfg, cell)
    monkeypatch.setenv("GR_GRAPH_KITTI_ROOT", str(tmp_path / "kitti"))
    with pytest.raises(RuntimeError, match="run on the synthetic world"):
        rc._require_synthetic(cfg, cell)
    # Table II's cells and the report reopen a finished cell's scans: the synthetic world, never the root found
    with pytest.raises(registry.DatasetError, match="kitti/sequences/00/velodyne: no .bin scans"):  # auto reads it
        registry.open_configured_sequence(cfg.data, synthetic_seed=cfg.seed)
    seq, desc = rc.open_cell_sequence(cfg)
    assert "synthetic world" in desc and len(seq) == len(range(*cell.frames))


def test_every_published_record_matches_its_cell_and_the_cells_pin_the_training_they_were_run_with():
    """The records in ``benchmarks/results/cells`` count only while their fingerprints equal the cells'
    (a changed library default must not silently change what a published cell means, nor orphan it)."""
    from pathlib import Path

    from gr_graph.experiments.cells import CELL_TRAINING_PINS, TABLES

    root = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "cells"
    records = sorted(root.glob("*/*/*.json"))
    if not records:
        pytest.skip(f"no published records under {root}")
    stale = []
    for path in records:
        budget, table = path.parent.parent.name, path.parent.name
        assert budget in BUDGETS and table in TABLES, path
        cells = {c.key: c for c in cells_for(table, budget)}
        doc = json.loads(path.read_text())
        if cells[doc["key"]].fingerprint() != doc["fingerprint"]:
            stale.append(str(path.relative_to(root)))
    assert not stale, f"records whose cell changed: {stale}"
    # every SLAM cell states the pinned training explicitly, the paper budget's at the pinned (paper) values
    paper = [c for t in ("table1", "ablations") for c in cells_for(t, "paper")]
    default = next(c for c in paper if c.key == "default-s0")
    tr = default.overrides["training"]
    assert tr["trainer"]["corr_likelihood"] == CELL_TRAINING_PINS["trainer"]["corr_likelihood"] == "gaussian"
    assert tr["keep_original"] is tr["keep_dropped"] is False
    adds = next(c for c in cells_for("table1", "student-t-8ep-adds") if c.key == "16ch-s0")
    assert adds.overrides["training"]["keep_original"] is True
    # a pin that differs from the pinned value changes the fingerprint
    changed = dataclasses.replace(default, overrides={**default.overrides, "training": {**tr, "keep_dropped": True}})
    assert changed.fingerprint() != default.fingerprint()


def test_table2_raw_cells_refuse_a_table1_run_of_other_scans(tmp_path, monkeypatch):
    """A raw-scan Table II cell has no source fingerprint (no model): it renders the scans the Table I
    run in the root was configured with, so those must be its own frames, channels and seed."""
    from gr_graph.config import SlamConfig, dump_config
    from gr_graph.datasets import registry

    def never(*a, **k):
        raise AssertionError("the sequence must not be opened")

    monkeypatch.setattr(registry, "open_configured_sequence", never)
    smoke = next(c for c in cells_for("table2", "smoke") if c.key.endswith("-r0"))
    root = tmp_path / "root"
    src = root / str(smoke.source)
    (src / "slam").mkdir(parents=True)
    (src / rc.CELL_JSON).write_text(json.dumps({"fingerprint": "another budget's", "definition": {}, "rounds": {}}))
    other = SlamConfig.model_validate({"seed": smoke.seed, "data": {"frames": [400, 1900], "channels": smoke.channels}})
    dump_config(other, src / "slam" / "config.yaml")
    with pytest.raises(rc.CellDependencyError, match=r"frames \(400, 1900\) \(the cell: \(\d+, \d+\)\)"):
        rc._run_registration_cell(root, rc.cell_dir(root, smoke), smoke, "cpu")
    assert rc._scans_mismatch(smoke, SlamConfig.model_validate(
        {"seed": smoke.seed, "data": {"frames": list(smoke.frames), "channels": smoke.channels}})) is None
