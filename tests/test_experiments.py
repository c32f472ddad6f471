"""The experiment harness (gr_graph.experiments): cell definitions, resume, pruning, reuse,
aggregation math against hand computations, the ablation options, and a smoke cell end to end."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import statistics

import numpy as np
import pytest

from gr_graph.config import PreprocessConfig, TrainingConfig, load_config
from gr_graph.experiments import aggregate as agg
from gr_graph.experiments import report
from gr_graph.experiments import run_cell as rc
from gr_graph.experiments.cells import (
    ABLATION_WINDOW,
    ABLATIONS,
    BUDGETS,
    REVISIT_WINDOW,
    TABLE1_WINDOW,
    TABLES,
    cells_for,
)
from gr_graph.experiments.cli import main
from gr_graph.experiments.revisits import count_revisits, first_revisit_window, revisit_pairs

# ----------------------------------------------------------------------------- cell definitions


def test_estimates_follow_the_per_frame_costs_and_grow_with_the_work():
    from gr_graph.experiments.cells import _S_PER_FRAME, _S_TOWN, estimate_registration_minutes, estimate_slam_minutes

    c = _S_PER_FRAME[32]
    by_hand = (_S_TOWN + 1500 * (c["round0"] + 2 * (3 * c["epoch"] + c["round"])) + 1500 * c["kiss"]) / 60
    assert estimate_slam_minutes(1500, 32, 2, 3, True) == pytest.approx(by_hand, abs=0.05)
    for ch in (16, 32, 64):
        base = estimate_slam_minutes(600, ch, 1, 3, False)
        assert estimate_slam_minutes(1200, ch, 1, 3, False) > base  # frames, rounds, epochs, the baseline add time
        assert estimate_slam_minutes(600, ch, 2, 3, False) > base
        assert estimate_slam_minutes(600, ch, 1, 4, False) > base
        assert estimate_slam_minutes(600, ch, 1, 3, True) > base
        assert estimate_registration_minutes(200, ch) > estimate_registration_minutes(100, ch) > 0


def test_runtime_table_lists_each_slam_cell_stage_in_minutes():
    cells = cells_for("table1", "paper")
    reg = cells_for("table2", "paper")[0]
    rounds = {"0": {"runtime_s": {"total": 120.0}},
              "1": {"runtime_s": {"total": 300.0, "training": 600.0}},
              "2": {"runtime_s": {"total": 330.0, "training": 660.0}}}
    results = {cells[0].key: {"wall_s": 2400.0, "rounds": rounds, "kiss_icp": {"wall_s": 90.0}, "peak_rss_mb": 3072.0},
               reg.key: {"wall_s": 60.0, "rounds": rounds}}
    lines = report._runtime_md(cells + [reg], results)
    rows = [ln for ln in lines if ln.startswith("| ")][1:]
    assert rows == [f"| {cells[0].key} | 1500 | 40.0 | 2.0 | 10.0, 11.0 | 5.0, 5.5 | 1.5 | 3.0 |"]  # no registration cell
    assert report._runtime_md(cells, {}) == []
    abl = {c.params["reuse"]: c for c in cells_for("ablations", "paper") if c.seed == 0}
    rows = [ln for ln in report._runtime_md(list(abl.values()), {c.key: {"wall_s": 600.0, "rounds": rounds}
                                                                  for c in abl.values()}) if ln.startswith("| ")][1:]
    assert rows[0] == f"| {abl[None].key} | 600 | 10.0 | 2.0 | 10.0, 11.0 | 5.0, 5.5 |  |  |"
    assert f"| {abl['round0'].key} | 600 | 10.0 | reused | 10.0, 11.0 |" in rows[1]
    assert f"| {abl['round1_training'].key} | 600 | 10.0 | reused | reused, 11.0 |" in rows[2]
    # what the cell recorded it took counts: a source not ready, or its checkpoint pruned
    recorded = {abl["round0"].key: {"reuse": {"what": None, "copied": []}},
                abl["round1_training"].key: {"reuse": {"what": "round1_training", "copied": ["round_0"]}}}
    rows = [ln for ln in report._runtime_md([abl["round0"], abl["round1_training"]], {
        k: {"wall_s": 600.0, "rounds": rounds, **v} for k, v in recorded.items()}) if ln.startswith("| ")][1:]
    assert rows[0].startswith(f"| {abl['round0'].key} | 600 | 10.0 | 2.0 | 10.0, 11.0 |")
    assert rows[1].startswith(f"| {abl['round1_training'].key} | 600 | 10.0 | reused | 10.0, 11.0 |")


@pytest.mark.parametrize("budget", sorted(BUDGETS))
@pytest.mark.parametrize("table", TABLES)
def test_cells_have_unique_keys_and_paired_seeds(table, budget):
    cells = cells_for(table, budget)
    assert len({c.key for c in cells}) == len(cells)
    assert len({c.fingerprint() for c in cells}) == len(cells)
    for c in cells:
        assert c.table == table and c.est_minutes > 0
        if c.kind == "slam":
            cfg = load_config(None, c.overrides)  # a valid configuration
            assert cfg.seed == cfg.training.seed == c.seed  # world seed i with training seed i
            assert cfg.data.channels == c.channels and cfg.data.frames == c.frames
            assert cfg.data.synthetic_preset == "kitti"
            assert not cfg.training.stop_on_reject and cfg.training.convergence_delta == 0.0
        else:
            src = {s.key: s for s in cells_for("table1", budget)}[c.source.split("/")[1]]
            assert (src.seed, src.channels, src.frames) == (c.seed, c.channels, c.frames)


def test_paper_budget_follows_the_protocol():
    b = BUDGETS["paper"]
    assert len(b.seeds) >= 3
    t1 = {c.key: c for c in cells_for("table1", "paper")}
    for ch in (16, 32):
        assert [c.seed for c in t1.values() if c.group == f"{ch}ch"] == list(b.seeds)
        assert all(c.frames == TABLE1_WINDOW and c.params["rounds"] == 2 for c in t1.values() if c.group == f"{ch}ch")
    assert [(c.params["rounds"], c.seed) for c in t1.values() if c.group == "64ch"] == [(1, b.seeds[0])]
    # the defaults' budget runs 64 channels at every seed (the claim needs the spread), and their Table II cells
    adds = BUDGETS["student-t-adds"]
    t1_adds = cells_for("table1", "student-t-adds")
    assert [(c.params["rounds"], c.seed) for c in t1_adds if c.group == "64ch"] == [(1, s) for s in adds.seeds]
    assert len(adds.seeds) >= 3
    assert {c.key for c in cells_for("table2", "student-t-adds") if c.channels == 64} == {
        f"64ch-s{s}-r{r}" for s in adds.seeds for r in (0, 1)}
    with pytest.raises(ValueError, match="seeds_64ch"):
        dataclasses.replace(adds, seeds_64ch=4)
    full = t1[f"full-16ch-s{b.seeds[0]}"]
    assert full.frames == (0, 4541) and full.params["rounds"] == 2 and full.params["kiss_icp"]
    t2 = cells_for("table2", "paper")
    assert len(t2) == 3 * 3 * 2 + 2 and all(c.params["n_pairs"] == 100 for c in t2)
    ab = cells_for("ablations", "paper")
    assert {c.group for c in ab} == set(ABLATIONS) and len(ab) == len(ABLATIONS) * len(b.seeds)
    assert all(c.frames == ABLATION_WINDOW and c.channels == 16 for c in ab)
    for c in ab:  # the default cell of a seed comes before the cells reusing it
        if c.source:
            assert [x.key for x in ab].index(c.source.split("/")[1]) < [x.key for x in ab].index(c.key)


def test_ablation_overrides_reach_the_config():
    ab = {c.key: load_config(None, c.overrides).training for c in cells_for("ablations", "paper")}
    assert ab["untrained-s0"].epochs == 0 and ab["default-s0"].epochs == 3
    assert ab["pca-s0"].covariances == "pca" and ab["default-s0"].covariances == "network"
    assert ab["cholesky-s0"].trainer.net.head == "cholesky" and ab["default-s0"].trainer.net.head == "geometric"
    assert ab["edge-noise-off-s0"].edge_noise == "registration" and ab["default-s0"].edge_noise == "learned"
    assert ab["densify-off-s0"].densify is False and ab["default-s0"].densify is True
    assert ab["densify-adds-s0"].keep_original and ab["densify-adds-s0"].keep_dropped
    assert not (ab["default-s0"].keep_original or ab["default-s0"].keep_dropped)
    assert ab["student-t-s0"].trainer.corr_likelihood == "student_t" and ab["default-s0"].trainer.corr_likelihood == "gaussian"
    assert ab["student-t-8ep-s0"].epochs == 8 and ab["student-t-8ep-s0"].trainer.corr_likelihood == "student_t"
    t8 = {c.key: load_config(None, c.overrides).training for c in cells_for("table1", "student-t-8ep")}
    assert t8["16ch-s0"].epochs == 8 and t8["16ch-s0"].trainer.corr_likelihood == "student_t"
    assert not (t8["16ch-s0"].keep_original or t8["16ch-s0"].keep_dropped)
    t8a = {c.key: load_config(None, c.overrides).training for c in cells_for("ablations", "student-t-8ep-adds")}
    assert t8a["default-s0"].epochs == 8 and t8a["default-s0"].trainer.corr_likelihood == "student_t"
    assert t8a["default-s0"].keep_original and t8a["default-s0"].keep_dropped
    # a cell's own trainer settings merge with the budget's
    assert t8a["cholesky-s0"].trainer.net.head == "cholesky" and t8a["cholesky-s0"].trainer.corr_likelihood == "student_t"
    est = {c.key: c.est_minutes for c in cells_for("ablations", "paper")}
    assert est["student-t-8ep-s0"] > est["student-t-s0"] > est["untrained-s0"]  # the estimate counts the epochs
    smoke = {c.key: load_config(None, c.overrides).training for c in cells_for("ablations", "smoke")}
    assert smoke["cholesky-s0"].trainer.net.head == "cholesky" and smoke["cholesky-s0"].trainer.net.c0 == 8


def test_revisit_window_helpers_against_brute_force():
    rng = np.random.default_rng(0)
    P = np.cumsum(rng.normal(0, 1, (400, 3)), axis=0)
    P[350] = P[20] + 1.0  # one revisit 330 frames later
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    pairs = revisit_pairs(P, min_gap=100, radius=5.0)
    d = np.linalg.norm(P[:, None] - P[None], axis=2)
    path = travelled[None] - travelled[:, None]
    i, j = np.nonzero(np.triu(d <= 5.0) & (np.arange(400)[None] - np.arange(400)[:, None] >= 100) & (path >= 50.0))
    np.testing.assert_array_equal(pairs, np.stack([i, j], axis=1))
    assert count_revisits(P, (0, 400)) == len(pairs) >= 1
    a, b = first_revisit_window(P, 340, step=10)
    assert b - a == 340 and count_revisits(P, (a, b)) >= 1
    with pytest.raises(ValueError, match="no 50-frame window"):
        first_revisit_window(P, 50)


def test_a_stop_is_not_a_revisit():
    """Frames of a long stop are many frames apart and in one place, but no path lies between them."""
    drive = np.stack([np.linspace(0.0, 200.0, 200), np.zeros(200), np.zeros(200)], axis=1)
    stop = np.repeat(drive[-1:], 150, axis=0) + np.random.default_rng(1).normal(0.0, 0.01, (150, 3))
    P = np.concatenate([drive, stop, drive[-1] + drive[:100]])  # then drives on, never back
    assert len(revisit_pairs(P, min_gap=100, radius=5.0, min_path=0.0)) > 0  # the old rule: the stop counts
    assert len(revisit_pairs(P, min_gap=100, radius=5.0)) == 0
    with pytest.raises(ValueError, match="path between them"):
        first_revisit_window(P, 400)
    ret = np.stack([np.linspace(300.0, 0.0, 301), np.full(301, 3.0), np.zeros(301)], axis=1)
    back = np.concatenate([P, ret])  # 3 m across, then back along the road: a revisit of every place
    found = revisit_pairs(back, min_gap=100, radius=5.0)
    assert len(found) > 0 and np.all(found[:, 1] >= len(P))  # only the return's frames close a revisit
    assert np.any((found[:, 0] >= 200) & (found[:, 0] < 350))  # the stop's place too, when driven past again


@pytest.mark.slow
def test_chosen_windows_contain_a_revisit():
    """The published windows (0:1500, 0:600) hold only the stop at frame 346, no revisit; the revisit budget's
    window is the first 1,500-frame window that holds one (route ground truth)."""
    from gr_graph.experiments.revisits import route_positions

    P = route_positions(0)
    assert len(P) == 4541
    for w in (TABLE1_WINDOW, ABLATION_WINDOW):
        assert count_revisits(P, w, min_gap=100, radius=5.0, min_path=0.0) > 0  # the rule they were chosen by
        assert count_revisits(P, w) == 0
    assert count_revisits(P, REVISIT_WINDOW) > 0
    assert first_revisit_window(P, REVISIT_WINDOW[1] - REVISIT_WINDOW[0]) == REVISIT_WINDOW
    assert BUDGETS["student-t-adds-revisit"].window == REVISIT_WINDOW
    with pytest.raises(ValueError):
        first_revisit_window(P, ABLATION_WINDOW[1] - ABLATION_WINDOW[0])


def test_list_prints_index_key_estimate(capsys, tmp_path):
    assert main(["table1", "--list", "--root", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    cells = cells_for("table1", "paper")
    for i, c in enumerate(cells):
        line = next(ln for ln in out.splitlines() if ln.split()[:2] == [str(i), c.key])
        assert f"{c.est_minutes:.1f}" in line and c.what in line
    assert f"{len(cells)} cells, estimated {sum(c.est_minutes for c in cells):.0f} minutes" in out


def test_bad_cell_index_is_an_error(capsys, tmp_path):
    with pytest.raises(SystemExit, match="there are 8 cells"):
        main(["table1", "--root", str(tmp_path), "--cell", "99"])


@pytest.mark.parametrize("option", ["--list", "--report", "--publish", "--publish-records"])
def test_one_cell_with_a_whole_table_option_is_refused(capsys, tmp_path, option):
    """They used to be ignored silently (--cell --publish published nothing; --list listed every cell)."""
    with pytest.raises(SystemExit) as exc:
        main(["table1", "--root", str(tmp_path), "--cell", "0", option])
    assert exc.value.code == 2
    assert f"--cell runs one cell; {option} work(s) on the whole table" in capsys.readouterr().err
    assert not (tmp_path / "table1").exists()


# ----------------------------------------------------------------------------- resume and pruning


def _fake_slam_cell(calls: list[str]):
    """A stand-in for the SLAM run of a cell: writes a pipeline-like folder."""

    def run(root, d, cell, device):
        calls.append(cell.key)
        slam = d / "slam"
        for r in range(3):
            (slam / f"round_{r}" / "memory").mkdir(parents=True, exist_ok=True)
            (slam / f"round_{r}" / "memory" / "scans.npy").write_bytes(b"x" * 100)
            (slam / f"round_{r}" / "poses_kitti.txt").write_text("pose\n")
            if r:
                (slam / f"round_{r}" / "training").mkdir(exist_ok=True)
                (slam / f"round_{r}" / "training" / "model.pt").write_bytes(b"m")
                (slam / f"round_{r}" / "training" / "checkpoint.pt").write_bytes(b"c")
        (slam / "metrics.json").write_text("{}")
        return {"rounds": {}, "marker": len(calls)}

    return run


def test_finished_cell_is_skipped_and_changed_definition_recomputed(tmp_path, monkeypatch):
    calls: list[str] = []
    monkeypatch.setattr(rc, "_run_slam_cell", _fake_slam_cell(calls))
    cell = cells_for("table1", "smoke")[0]
    first = rc.run_cell(tmp_path, cell)
    assert calls == [cell.key] and rc.is_done(tmp_path, cell)
    assert rc.run_cell(tmp_path, cell) == first and calls == [cell.key]  # skipped
    d = rc.cell_dir(tmp_path, cell)
    (d / "stale.txt").write_text("from the old definition")
    changed = dataclasses.replace(cell, overrides={**cell.overrides, "loops": {"enabled": False}})
    assert changed.key == cell.key and changed.fingerprint() != cell.fingerprint()
    assert not rc.is_done(tmp_path, changed)
    doc = rc.run_cell(tmp_path, changed)
    assert calls == [cell.key, cell.key] and doc["fingerprint"] == changed.fingerprint()
    assert not (d / "stale.txt").exists()  # recomputed from scratch


def test_unfinished_cell_with_another_definition_is_cleared(tmp_path, monkeypatch):
    calls: list[str] = []
    cell = cells_for("table1", "smoke")[0]
    d = rc.cell_dir(tmp_path, cell)

    def crash(root, dd, c, device):
        (dd / "partial.txt").write_text("half done")
        raise KeyboardInterrupt

    monkeypatch.setattr(rc, "_run_slam_cell", crash)
    with pytest.raises(KeyboardInterrupt):
        rc.run_cell(tmp_path, cell)
    monkeypatch.setattr(rc, "_run_slam_cell", _fake_slam_cell(calls))
    rc.run_cell(tmp_path, cell)  # same definition: the partial run stays (the pipeline resumes it)
    assert (d / "partial.txt").exists()
    (d / "cell.json").unlink()
    changed = dataclasses.replace(cell, what="another definition")
    rc.run_cell(tmp_path, changed)
    assert not (d / "partial.txt").exists()

    # budgets in one root (keys repeat between them): a finished cell of another budget is never deleted,
    # nor one whose budget is unknown (a library call without one) when this run has one
    with pytest.raises(rc.CellConflictError, match="whose budget is not recorded"):
        rc.run_cell(tmp_path, cell, budget="smoke")
    assert json.loads((d / "cell.json").read_text())["fingerprint"] == changed.fingerprint()
    shutil.rmtree(d)  # what the error says to do
    rc.run_cell(tmp_path, cell, budget="smoke")
    finished = (d / "cell.json").read_text()
    assert json.loads(finished)["budget"] == "smoke"
    with pytest.raises(rc.CellConflictError, match="holds the finished cell .* of budget 'smoke'"):
        rc.run_cell(tmp_path, changed, budget="paper")
    assert (d / "cell.json").read_text() == finished
    rc.run_cell(tmp_path, changed, budget="smoke")  # the same budget's changed definition: recomputed
    assert json.loads((d / "cell.json").read_text())["fingerprint"] == changed.fingerprint()

    # a finished cell whose budget is not recorded (made before cell.json named it) is kept too
    legacy = json.loads((d / "cell.json").read_text())
    legacy.pop("budget")
    (d / "cell.json").write_text(json.dumps(legacy))
    with pytest.raises(rc.CellConflictError, match="whose budget is not recorded"):
        rc.run_cell(tmp_path, cell, budget="smoke")
    assert json.loads((d / "cell.json").read_text()) == legacy
    # an unfinished cell of another budget is kept; one of the same budget is cleared
    (d / "cell.json").unlink()
    (d / "definition.json").write_text(json.dumps({"fingerprint": "0" * 16, "budget": "paper"}))
    (d / "partial.txt").write_text("the paper budget's half-done work")
    with pytest.raises(rc.CellConflictError, match="holds the unfinished cell .* of budget 'paper'"):
        rc.run_cell(tmp_path, cell, budget="smoke")
    assert (d / "partial.txt").exists()
    rc.run_cell(tmp_path, cell, budget="paper")
    assert not (d / "partial.txt").exists()
    assert json.loads((d / "definition.json").read_text())["budget"] == "paper"


def test_pruning_keeps_models_and_poses_and_waits_for_reusing_cells(tmp_path, monkeypatch):
    calls: list[str] = []
    monkeypatch.setattr(rc, "_run_slam_cell", _fake_slam_cell(calls))
    cells = cells_for("ablations", "smoke")
    default, reusing = cells[0], [c for c in cells if c.source == f"ablations/{cells[0].key}"]
    assert default.group == "default" and len(reusing) == len(ABLATIONS) - 1
    rc.run_cell(tmp_path, default)
    assert rc.prune_finished(tmp_path, cells) == []  # its reusing cells are not finished
    for c in reusing:
        rc.run_cell(tmp_path, c)
    slam = rc.cell_dir(tmp_path, default) / "slam"
    (slam / "frames").mkdir()  # a frame cache left behind by an interrupted run
    gone = rc.prune_finished(tmp_path, cells)
    assert slam / "frames" in gone and not (slam / "frames").exists()
    assert slam / "round_0" / "memory" in gone
    assert not list(slam.glob("round_*/memory")) and not list(slam.glob("round_*/training/checkpoint.pt"))
    assert (slam / "round_1" / "training" / "model.pt").is_file() and (slam / "round_2" / "poses_kitti.txt").is_file()
    assert (slam / "metrics.json").is_file()
    unfinished = rc.cell_dir(tmp_path, cells[len(ABLATIONS)]) / "slam" / "round_0" / "memory"
    unfinished.mkdir(parents=True)
    rc.prune_finished(tmp_path, cells)
    assert unfinished.is_dir()  # an unfinished cell keeps its memory


def test_reuse_copies_round0_and_round1_training_from_a_finished_source(tmp_path, monkeypatch):
    calls: list[str] = []
    monkeypatch.setattr(rc, "_run_slam_cell", _fake_slam_cell(calls))
    cells = {c.group: c for c in cells_for("ablations", "smoke") if c.seed == 0}
    dst = rc.cell_dir(tmp_path, cells["edge-noise-off"])
    dst.mkdir(parents=True)
    assert rc._reuse(tmp_path, dst, cells["edge-noise-off"])["what"] is None  # source not finished
    rc.run_cell(tmp_path, cells["default"])
    (rc.cell_dir(tmp_path, cells["default"]) / "slam" / "round_0" / "round.json").write_text("{}")
    info = rc._reuse(tmp_path, dst, cells["edge-noise-off"])
    assert info["copied"] == ["round_0", "round_1/training"]
    assert (dst / "slam" / "round_0" / "memory" / "scans.npy").is_file()
    assert (dst / "slam" / "round_1" / "training" / "checkpoint.pt").is_file()
    dst2 = rc.cell_dir(tmp_path, cells["pca"])
    assert rc._reuse(tmp_path, dst2, cells["pca"])["copied"] == ["round_0"]
    assert not (dst2 / "slam" / "round_1").exists()
    # a resumed call reports what the first one did: here, round 0 computed by the cell itself
    dst3 = rc.cell_dir(tmp_path, cells["untrained"])
    (tmp_path / "table_moved").mkdir()
    src_cell = rc.cell_dir(tmp_path, cells["default"])
    (src_cell / "cell.json").rename(tmp_path / "table_moved" / "cell.json")  # the source not finished yet
    first = rc._reuse(tmp_path, dst3, cells["untrained"])
    assert first["what"] is None and first["copied"] == []
    (dst3 / "slam" / "round_0").mkdir(parents=True)
    (dst3 / "slam" / "round_0" / "round.json").write_text("{}")  # its own round 0 finished, then a kill
    (tmp_path / "table_moved" / "cell.json").rename(src_cell / "cell.json")  # the source finished meanwhile
    assert rc._reuse(tmp_path, dst3, cells["untrained"]) == first
    assert rc.reused_from_source(first) == set()
    # an interrupted copy leaves only a hidden sibling, which the next copy replaces
    shutil.rmtree(dst / "slam")
    half = dst / "slam" / "round_1" / ".copying-training"
    half.mkdir(parents=True)
    (half / "partial").write_text("x")
    assert rc._reuse(tmp_path, dst, cells["edge-noise-off"])["copied"] == ["round_0", "round_1/training"]
    assert not half.exists() and (dst / "slam" / "round_1" / "training" / "checkpoint.pt").is_file()
    # a source of another definition in a shared root (another budget's default cell) is not copied
    shutil.rmtree(dst / "slam")
    (dst / rc.REUSE_JSON).unlink()
    other = dataclasses.replace(cells["edge-noise-off"], reuse_fingerprint="0" * 16)
    verdict = rc._reuse(tmp_path, dst, other)
    assert verdict["what"] is None and verdict["copied"] == [] and "another definition" in verdict["note"]
    assert not (dst / "slam" / "round_0").exists()
    assert cells["edge-noise-off"].reuse_fingerprint == cells["default"].fingerprint()


def test_registration_cell_needs_its_table1_cell(tmp_path):
    cell = cells_for("table2", "smoke")[0]
    with pytest.raises(rc.CellDependencyError, match="--cell 16ch-s0"):
        rc.run_cell(tmp_path, cell)


# ----------------------------------------------------------------------------- aggregation math


def test_mean_std_and_reduction_by_hand():
    d = agg.mean_std([1.0, None, 2.0, 4.0])
    assert d["n"] == 3 and d["mean"] == pytest.approx(7 / 3)
    assert d["std"] == pytest.approx(statistics.stdev([1.0, 2.0, 4.0]))
    assert agg.mean_std([5.0])["std"] is None and agg.mean_std([None])["mean"] is None
    # a seed left out (None, or NaN: a diverged run) shows in the printed figure, not only in n
    assert d["n_given"] == 4 and agg.fmt_ms(d) == "2.333 ± 1.528 (n=3 of 4)"
    assert agg.fmt_ms(agg.mean_std([0.5, float("nan"), 0.7]), pct=True) == "0.600 ± 0.141 % (n=2 of 3)"
    assert agg.fmt_ms(agg.mean_std([0.5, 0.7])) == "0.600 ± 0.141" and agg.fmt_ms(agg.mean_std([5.0, None])) == \
        "5.000 (n=1 of 2)"
    assert agg.reduction_percent(0.2, 0.15) == pytest.approx(25.0)
    assert agg.reduction_percent(0.2, 0.3) == pytest.approx(-50.0)
    assert agg.reduction_percent(None, 1.0) is None and agg.reduction_percent(0.0, 1.0) is None


def _t1_result(seed: int, rpe: list[float], accepted: list[bool | None], group: str = "16ch", ch: int = 16):
    rounds = {}
    for r, v in enumerate(rpe):
        slam = {k: None for k in rc.METRIC_KEYS}
        slam.update(rpe300_consecutive_mean=v, rpe300_all_pairs_mean=v * 1.1, ate_rmse=v / 2)
        rounds[str(r)] = {"slam": slam, "accepted": None if r == 0 else accepted[r - 1]}
    return {"definition": {"group": group, "seed": seed, "channels": ch, "frames": [0, 1500],
                           "params": {"rounds": len(rpe) - 1}},
            "rounds": rounds, "kiss_icp": {k: (0.5 if k == "ate_rmse" else None) for k in rc.METRIC_KEYS}}


def test_table1_reductions_per_seed_then_mean_std():
    rpe = {0: [0.20, 0.15, 0.10], 1: [0.40, 0.20, 0.30], 2: [0.10, 0.09, 0.12]}
    acc = {0: [True, True], 1: [True, False], 2: [True, True]}
    res = [_t1_result(s, rpe[s], acc[s]) for s in rpe]
    s = agg.table1_summary(res)["16ch"]
    red1 = [100 * (v[0] - v[1]) / v[0] for v in rpe.values()]  # 25, 50, 10
    red2 = [100 * (v[0] - v[2]) / v[0] for v in rpe.values()]  # 50, 25, -20
    d = s["steps"]["1-step"]["reduction_rpe300_consecutive_mean"]
    assert d["mean"] == pytest.approx(np.mean(red1)) and d["std"] == pytest.approx(np.std(red1, ddof=1))
    d = s["steps"]["2-step"]["reduction_rpe300_consecutive_mean"]
    assert d["mean"] == pytest.approx(np.mean(red2)) and d["std"] == pytest.approx(np.std(red2, ddof=1))
    # guarded: seed 1 rejected round 2, so its guarded 2-step is round 1 (reduction 50 %)
    g = s["steps"]["2-step guarded"]
    assert [p["round"] for p in g["per_seed"]] == [2, 1, 2]
    assert g["reduction_rpe300_consecutive_mean"]["values"] == pytest.approx([50.0, 50.0, -20.0])
    assert s["steps"]["raw"]["rpe300_consecutive_mean"]["mean"] == pytest.approx(np.mean([0.2, 0.4, 0.1]))
    assert s["kiss_icp"]["ate_rmse"]["mean"] == 0.5 and s["kiss_icp"]["rpe300_consecutive_mean"]["n"] == 0
    assert s["paper_reduction"] == {1: 35.6, 2: 49.5}
    full = agg.table1_summary([_t1_result(0, rpe[0], acc[0], group="full-16ch")])["full-16ch"]
    assert full["paper_reduction"] == {1: 35.6, 2: 49.5}  # the paper's figures are of the whole sequence
    # 2x2 count by ground truth (all-pairs RPE vs the previous round)
    assert s["acceptance_2x2"] == {"accepted_better": 4, "accepted_worse": 1, "rejected_better": 0,
                                   "rejected_worse": 1}
    assert agg.acceptance_recorded(res)


def test_missing_acceptance_counts_every_round_as_accepted():
    res = [_t1_result(0, [0.2, 0.3, 0.1], [None, None])]
    assert not agg.acceptance_recorded(res)
    s = agg.table1_summary(res)["16ch"]
    assert s["steps"]["2-step guarded"]["per_seed"][0]["round"] == 2
    rounds = {"0": {}, "1": {"accepted": False}, "2": {"accepted": True}}
    assert agg.select_round(rounds, "2-step guarded") == (0, "round 1 rejected")
    assert agg.select_round({"0": {}, "2": {"accepted": True}}, "2-step guarded") == (0, "round 1 missing")
    r, note = agg.select_round({"0": {}, "1": {}}, "2-step")
    assert r == 1 and "round 2 not run" in note


def test_table2_success_mean_std_and_best_step():
    res = []
    rates = {(0, 0): 0.8, (0, 1): 0.9, (0, 2): 0.85, (1, 0): 0.7, (1, 1): 0.8, (1, 2): 0.9}
    for (seed, r), v in rates.items():
        res.append({"definition": {"channels": 32, "seed": seed, "params": {"round": r}},
                    "summary": {"fpfh_ransac": {"success_rate": v, "n_pairs": 100}}})
    s = agg.table2_summary(res)["32"]
    raw = s["steps"]["raw"]["fpfh_ransac"]
    assert raw["mean"] == pytest.approx(75.0) and raw["std"] == pytest.approx(np.std([80, 70], ddof=1))
    assert s["best_step"]["fpfh_ransac"]["step"] == "2-step"  # 87.5 > 85
    assert s["best_step"]["fpfh_ransac"]["mean"] == pytest.approx(87.5)
    assert s["paper"] == {"raw": 90.0, "best_step": 96.0}
    # a cell without a success rate (no pair evaluated) is missing, not 0 %
    res.append({"definition": {"channels": 32, "seed": 2, "params": {"round": 0}},
                "summary": {"fpfh_ransac": {"success_rate": None, "n_pairs": 0}}})
    raw = agg.table2_summary(res)["32"]["steps"]["raw"]["fpfh_ransac"]
    assert raw["mean"] == pytest.approx(75.0) and raw["n"] == 2 and raw["n_given"] == 3
    assert [p["success_percent"] for p in raw["per_seed"]] == [pytest.approx(80.0), pytest.approx(70.0), None]
    # a densified step with no success rate at all: no mean, and no best step from it
    only = [{"definition": {"channels": 16, "seed": 0, "params": {"round": r}},
             "summary": {"kiss_matcher": {"success_rate": 0.7 if r == 0 else None, "n_pairs": 100 if r == 0 else 0}}}
            for r in (0, 1)]
    s16 = agg.table2_summary(only)["16"]
    assert s16["steps"]["1-step"]["kiss_matcher"]["mean"] is None and s16["best_step"] == {}
    # the report labels every seed's rate and says when steps were measured on different seeds
    from gr_graph.experiments.report import _table2_md

    md = "\n".join(_table2_md(agg.table2_summary(res[:5])))
    assert "| 32 | raw | fpfh_ransac | 75.0 ± 7.1 | s0 80, s1 70 | raw 90 |" in md
    assert "| 32 | 2-step | fpfh_ransac | 85.0 (n=1) | s0 85 |" in md
    assert "Steps measured on different seeds (cells missing): 32 channels: raw (fpfh_ransac) seeds 0, 1; " \
           "1-step (fpfh_ransac) seeds 0, 1; 2-step (fpfh_ransac) seeds 0." in md
    assert "different seeds" not in "\n".join(_table2_md(agg.table2_summary(res[:6])))
    # per solver: a second solver's rows on all seeds do not hide the first one's missing seed
    both = [{**r, "summary": {**r["summary"], "kiss_matcher": {"success_rate": 0.5, "n_pairs": 100}}} for r in res[:6]]
    both[5] = {**both[5], "summary": {"fpfh_ransac": {"success_rate": None, "n_pairs": 0},
                                      "kiss_matcher": {"success_rate": 0.5, "n_pairs": 100}}}
    md = "\n".join(_table2_md(agg.table2_summary(both)))
    assert "2-step (fpfh_ransac) seeds 0; 2-step (kiss_matcher) seeds 0, 1" in md


def test_ablation_differences_and_the_consistency_rule():
    res = []
    vals = {"default": [0.10, 0.20, 0.30], "pca": [0.15, 0.26, 0.34], "untrained": [0.5, 0.1, 0.2],
            "rounding": [0.10 - 1e-10, 0.20 - 2e-10, 0.30 - 3e-10]}
    for name, v in vals.items():
        for seed, x in enumerate(v):
            r = _t1_result(seed, [0.4, x, x], [True, True], group=name)
            r["what"] = f"{name}, 16 channels"
            res.append(r)
    s = agg.ablation_summary(res)
    d = s["pca"]["steps"]["2-step"]["diff_rpe300_consecutive_mean"]
    diffs = [0.05, 0.06, 0.04]
    assert d["values"] == pytest.approx(diffs) and d["mean"] == pytest.approx(0.05)
    assert d["consistent"]  # all positive and the mean gap exceeds the spread
    assert not s["untrained"]["steps"]["2-step"]["diff_rpe300_consecutive_mean"]["consistent"]  # signs disagree
    assert s["default"]["steps"]["1-step"]["diff_rpe300_consecutive_mean"]["values"] == [0.0, 0.0, 0.0]
    # gaps of float noise agree in sign with |mean| > std, yet are no difference
    noise = s["rounding"]["steps"]["2-step"]["diff_rpe300_consecutive_mean"]
    assert all(v < 0 for v in noise["values"]) and abs(noise["mean"]) > noise["std"]
    assert not noise["consistent"]
    # an ablation finished for 2 of the baseline's 3 seeds cannot be called consistent, however they agree
    two = agg.ablation_summary([r for r in res if not (r["definition"]["group"] == "pca"
                                                       and r["definition"]["seed"] == 2)])
    d2 = two["pca"]["steps"]["2-step"]["diff_rpe300_consecutive_mean"]
    assert d2["values"] == pytest.approx([0.05, 0.06]) and not d2["consistent"]


def test_ablation_reductions_against_round0_guarded_step_and_acceptance(tmp_path, monkeypatch):
    # seed 0 helps in both rounds; seed 1's round 1 is worse and rejected, its round 2 better and accepted
    rpe = {0: [0.40, 0.30, 0.20], 1: [0.40, 0.60, 0.35]}
    acc = {0: [True, True], 1: [False, True]}
    res = []
    for seed in rpe:
        r = _t1_result(seed, rpe[seed], acc[seed], group="default")
        r["what"] = "default method, 16 channels"
        res.append(r)
    s = agg.ablation_summary(res)["default"]
    red1 = s["steps"]["1-step"]["reduction_rpe300_consecutive_mean"]
    assert red1["values"] == pytest.approx([25.0, -50.0])
    g = s["steps"]["2-step guarded"]
    assert [p["round"] for p in g["per_seed"]] == [2, 0]  # seed 1 stops at round 0: round 1 was rejected
    assert g["reduction_rpe300_consecutive_mean"]["values"] == pytest.approx([50.0, 0.0])
    assert s["acceptance_2x2"] == {"accepted_better": 3, "accepted_worse": 0, "rejected_better": 0,
                                   "rejected_worse": 1}
    monkeypatch.setattr(report, "_figures", lambda *a, **k: {})
    cells = [c for c in cells_for("ablations", "paper") if c.group == "default" and c.seed in (0, 1)]
    monkeypatch.setattr(report, "read_cell_result", lambda root, c: res[c.seed])
    md = report.write_report("ablations", tmp_path, BUDGETS["paper"], cells, "cmd").read_text()
    assert "| round 0 (all) | raw | 0.440 ± 0.000 | 0.400 ± 0.000 | 0.200 ± 0.000 | n/a | | |" in md
    assert "| default | 1-step | -12.5 ± 53.0 % |" in md
    assert "| default | 2-step guarded | 25.0 ± 35.4 % |" in md
    assert "3 / 0 | 0 / 1 |" in md


def test_error_plot_turns_logarithmic_only_when_a_round_is_ruined(tmp_path, monkeypatch):
    """A 100x worse round beside raw and KISS-ICP gets a log axis; values within 30x stay linear."""
    from gr_graph.experiments import figures as fig

    assert fig.needs_log_scale([2.7, 8.2, 102.0, 1.3]) and not fig.needs_log_scale([2.7, 8.2, 1.3])
    assert not fig.needs_log_scale([0.0, 100.0]) and not fig.needs_log_scale([])  # no log of zero
    kept = []
    monkeypatch.setattr(fig, "save_figure", lambda f, path, **k: kept.append(f) or path)

    def summary(two_step):
        val = {"mean": None, "std": None}
        steps = {s: {m: dict(val, mean=v, std=0.1 * v) for m in ("rpe300_consecutive_mean", "ate_rmse")}
                 for s, v in (("raw", 2.7), ("1-step", 8.2), ("2-step", two_step))}
        return {"16ch": {"seeds": [0, 1, 2], "steps": steps,
                         "kiss_icp": {"ate_rmse": {"mean": 0.9, "std": 0.0}}}}

    metrics = ("rpe300_consecutive_mean", "ate_rmse")
    fig.plot_rpe_over_rounds(summary(102.0), tmp_path / "a.png", metrics=metrics)
    fig.plot_rpe_over_rounds(summary(3.0), tmp_path / "b.png", metrics=metrics)
    assert [ax.get_yscale() for ax in kept[0].axes] == ["log", "log"]
    assert [ax.get_yscale() for ax in kept[1].axes] == ["linear", "linear"]
    assert "log scale" in kept[0].axes[1].get_ylabel()


def test_published_report_names_no_path_of_the_machine(tmp_path, monkeypatch):
    root = tmp_path / "my_machine_root"
    res = [_t1_result(seed, [0.40, 0.30, 0.20], [True, True], group="default") for seed in (0, 1)]
    for r in res:
        r["what"] = "default method, 16 channels"
    fig = tmp_path / "fig.png"
    fig.write_bytes(b"png")
    monkeypatch.setattr(report, "_figures", lambda *a, **k: {"rounds": fig})
    monkeypatch.setattr(report, "read_cell_result", lambda root, c: res[c.seed])
    monkeypatch.setattr(report, "RESULTS_DIR", tmp_path / "published")
    cells = [c for c in cells_for("ablations", "paper") if c.group == "default" and c.seed in (0, 1)]
    command = f"python -m gr_graph.experiments ablations --root {root}"
    local = report.write_report("ablations", root, BUDGETS["paper"], cells, command, publish=True)
    assert str(root) in local.read_text()  # the local report says where its cells are
    published = [tmp_path / "published" / n for n in ("ablations.md", "ablations.json")]
    for path in published:
        text = path.read_text()
        assert str(tmp_path) not in text, path
        assert "--root ROOT" in text
    assert json.loads(published[1].read_text())["figures"] == {"rounds": "figures/fig.png"}
    assert (tmp_path / "published" / "figures" / "fig.png").read_bytes() == b"png"
    # a short relative root: only the --root argument is replaced, the rest of the command stays
    monkeypatch.chdir(tmp_path)
    report.write_report("ablations", "exp", BUDGETS["paper"], cells,
                        "python -m gr_graph.experiments ablations --root exp", publish=True)
    doc = json.loads(published[1].read_text())
    assert doc["command"] == "python -m gr_graph.experiments ablations --root ROOT"
    # another budget publishes beside the paper's table, never over it
    before = published[0].read_bytes()
    t_cells = [c for c in cells_for("ablations", "student-t") if c.group == "default" and c.seed in (0, 1)]
    assert all(load_config(None, c.overrides).training.trainer.corr_likelihood == "student_t" for c in t_cells)
    report.write_report("ablations", "exp", BUDGETS["student-t"], t_cells,
                        "python -m gr_graph.experiments ablations --budget student-t --root exp", publish=True)
    assert published[0].read_bytes() == before
    assert "--budget student-t" in (tmp_path / "published" / "ablations_student-t.md").read_text()
    assert report.published_name("table1", BUDGETS["paper"]) == "table1"


def _write_round_marginals(round_dir, edge_error: float, position_error: float) -> None:
    """A 3-pose round along x whose two odometry edges are ``edge_error`` m long in x and whose poses
    are ``position_error`` m off in y: with information 100 I and marginals 0.01 I both NEES are
    ``100 edge_error^2`` and ``100 position_error^2`` by hand."""
    gt = np.stack([np.eye(4)] * 3)
    gt[:, 0, 3] = [0.0, 1.0, 2.0]
    poses = gt.copy()
    poses[1:, 1, 3] += position_error
    edge_T = np.stack([np.eye(4)] * 2)
    edge_T[:, 0, 3] = -1.0 - edge_error  # scan k into the frame of scan l = k + 1
    round_dir.mkdir(parents=True)
    np.savez(round_dir / "marginals.npz", poses=poses, gt_poses=gt, covariance=np.stack([np.eye(6)] * 3),
             position_cov_world=np.stack([0.01 * np.eye(3)] * 3), edges=np.array([[0, 1], [1, 2]]),
             edge_T=edge_T, edge_information=np.stack([100 * np.eye(6)] * 2), edge_kind=np.zeros(2, np.uint8),
             edge_ok=np.ones(2, bool))


def test_reports_carry_nees_of_every_round_from_the_marginals(tmp_path, monkeypatch):
    cells = [c for c in cells_for("ablations", "paper") if c.group == "default" and c.seed in (0, 1)]
    res = {}
    for c in cells:
        res[c.seed] = _t1_result(c.seed, [0.40, 0.30, 0.20], [True, True], group="default")
        res[c.seed]["what"] = "default method, 16 channels"
        slam = rc.cell_dir(tmp_path, c) / "slam"
        _write_round_marginals(slam / "round_0", 0.1, 0.1 * (1 + c.seed))  # NEES 1; 1 and 4
        _write_round_marginals(slam / "round_1", 0.3, 0.2)  # 9; 4
        # round 2 has no marginals: its NEES are missing, the report is still written
    got = rc.with_noise_consistency(tmp_path, cells[0], res[0])
    # path: the edges measure 1 + edge_error m of a 1 m step
    assert got["rounds"]["0"]["nees"] == pytest.approx(
        {"nees_odometry_mean": 1.0, "nees_loop_mean": None, "nees_position_mean": 1.0,
         "odometry_path_error_percent": 10.0})
    assert got["rounds"]["1"]["nees"]["nees_odometry_mean"] == pytest.approx(9.0)
    assert got["rounds"]["2"]["nees"] == dict.fromkeys(rc.NEES_KEYS)
    assert "nees" not in res[0]["rounds"]["0"]  # the cell's result is not changed
    # a round without ground truth in its marginals, and a damaged file: no NEES, no failure
    slam1 = rc.cell_dir(tmp_path, cells[1]) / "slam"
    with np.load(slam1 / "round_1" / "marginals.npz") as z:
        no_gt = {k: z[k] for k in z.files if k != "gt_poses"}
    np.savez(slam1 / "round_1" / "marginals.npz", **no_gt)
    (slam1 / "round_0" / "marginals.npz").write_bytes(b"PK\x03\x04 truncated")
    broken = rc.with_noise_consistency(tmp_path, cells[1], res[1])
    assert broken["rounds"]["0"]["nees"] == dict.fromkeys(rc.NEES_KEYS)
    assert broken["rounds"]["1"]["nees"] == dict.fromkeys(rc.NEES_KEYS)
    _write_round_marginals(tmp_path / "again" / "round_0", 0.1, 0.2)  # restore cell 1's rounds
    (slam1 / "round_0" / "marginals.npz").write_bytes((tmp_path / "again" / "round_0" / "marginals.npz").read_bytes())
    _write_round_marginals(tmp_path / "again" / "round_1", 0.3, 0.2)
    (slam1 / "round_1" / "marginals.npz").write_bytes((tmp_path / "again" / "round_1" / "marginals.npz").read_bytes())
    s = agg.ablation_summary([rc.with_noise_consistency(tmp_path, c, res[c.seed]) for c in cells])["default"]
    pos = s["steps"]["raw"]["nees_position_mean"]
    assert pos["values"] == pytest.approx([1.0, 4.0]) and pos["std"] == pytest.approx(np.std([1, 4], ddof=1))
    assert s["steps"]["1-step"]["nees_odometry_mean"]["mean"] == pytest.approx(9.0)
    assert s["steps"]["2-step"]["nees_odometry_mean"]["n"] == 0
    monkeypatch.setattr(report, "_figures", lambda *a, **k: {})
    monkeypatch.setattr(report, "read_cell_result", lambda root, c: res[c.seed])
    md = report.write_report("ablations", tmp_path, BUDGETS["paper"], cells, "cmd").read_text()
    assert "## Noise consistency (NEES against ground truth)" in md
    assert "| round 0 (all) | raw | 1 ± 0 | n/a | 2.5 ± 2.12 | 10 ± 0 |" in md
    assert "| default | 1-step | 9 ± 0 | n/a | 4 ± 0 | 30 ± 0 |" in md
    t1 = agg.table1_summary([rc.with_noise_consistency(tmp_path, c, res[c.seed]) for c in cells])
    assert t1["default"]["steps"]["1-step"]["nees_position_mean"]["mean"] == pytest.approx(4.0)


def _write_round_poses(path, y_offsets) -> None:
    """KITTI poses along x, 1 m a frame, moved by ``y_offsets`` [m] sideways."""
    from gr_graph.trajectory import write_kitti_poses

    T = np.stack([np.eye(4)] * len(y_offsets))
    T[:, 0, 3] = np.arange(len(y_offsets), dtype=float)
    T[:, 1, 3] = y_offsets
    path.parent.mkdir(parents=True, exist_ok=True)
    write_kitti_poses(path, T)


def test_reports_carry_short_range_rpe_of_every_round_from_the_poses(tmp_path, monkeypatch):
    # round 0 drifts 1 cm a frame sideways: RPE-1 0.01 m, RPE-10 0.10 m; round 1 jitters +-1 cm around
    # the truth: RPE-1 0.02 m (worse), RPE-10 0 (frames 10 apart share the sign: better); round 2 has no poses
    cells = [c for c in cells_for("ablations", "paper") if c.group == "default" and c.seed in (0, 1)]
    k = np.arange(14)
    res = {}
    for c in cells:
        res[c.seed] = _t1_result(c.seed, [0.40, 0.30, 0.20], [True, True], group="default")
        res[c.seed]["what"] = "default method, 16 channels"
        slam = rc.cell_dir(tmp_path, c) / "slam"
        _write_round_poses(slam / "gt_poses_kitti.txt", np.zeros(len(k)))
        _write_round_poses(slam / "round_0" / "poses_kitti.txt", 0.01 * k)
        _write_round_poses(slam / "round_1" / "poses_kitti.txt", 0.01 * (-1.0) ** k)
    got = rc.with_short_range_rpe(tmp_path, cells[0], res[0])
    assert got["rounds"]["0"]["short_range"] == pytest.approx({"rpe1_all_pairs_mean": 0.01, "rpe10_all_pairs_mean": 0.1})
    assert got["rounds"]["1"]["short_range"] == pytest.approx({"rpe1_all_pairs_mean": 0.02, "rpe10_all_pairs_mean": 0.0},
                                                              abs=1e-12)
    assert got["rounds"]["2"]["short_range"] == dict.fromkeys(rc.SHORT_RANGE_KEYS)  # no poses: None, no failure
    assert "short_range" not in res[0]["rounds"]["0"]  # the cell's result is not changed
    (rc.cell_dir(tmp_path, cells[1]) / "slam" / "gt_poses_kitti.txt").write_text("1 2 3\n")  # damaged truth
    broken = rc.with_short_range_rpe(tmp_path, cells[1], res[1])
    assert all(v["short_range"] == dict.fromkeys(rc.SHORT_RANGE_KEYS) for v in broken["rounds"].values())
    _write_round_poses(rc.cell_dir(tmp_path, cells[1]) / "slam" / "gt_poses_kitti.txt", np.zeros(len(k)))
    s = agg.ablation_summary([rc.with_short_range_rpe(tmp_path, c, res[c.seed]) for c in cells])["default"]
    one = s["steps"]["1-step"]
    assert one["reduction_rpe1_all_pairs_mean"]["values"] == pytest.approx([-100.0, -100.0])
    assert one["reduction_rpe10_all_pairs_mean"]["values"] == pytest.approx([100.0, 100.0])
    assert s["steps"]["2-step"]["rpe1_all_pairs_mean"]["n"] == 0
    t1 = agg.table1_summary([rc.with_short_range_rpe(tmp_path, c, res[c.seed]) for c in cells])["default"]
    assert t1["steps"]["1-step"]["rpe1_all_pairs_mean"]["mean"] == pytest.approx(0.02)
    monkeypatch.setattr(report, "_figures", lambda *a, **k: {})
    monkeypatch.setattr(report, "read_cell_result", lambda root, c: res[c.seed])
    md = report.write_report("ablations", tmp_path, BUDGETS["paper"], cells, "cmd").read_text()
    assert "## Short-range accuracy (RPE over 1 and 10 frames)" in md
    assert "| round 0 (all) | raw | 0.0100 ± 0.0000 | 0.1000 ± 0.0000 |  |  |" in md
    assert "| default | 1-step | 0.0200 ± 0.0000 | 0.0000 ± 0.0000 | -100.0 ± 0.0 % | 100.0 ± 0.0 % |" in md


def test_acceptance_count_judges_against_the_last_accepted_round():
    # round 1 rejected and worse than round 0; round 2 better than round 1 but still worse than
    # round 0 (the test's reference): worse; an equal round brings nothing: worse
    cells = [_t1_result(0, [0.40, 0.60, 0.50], [False, False]), _t1_result(1, [0.40, 0.40, 0.30], [False, True])]
    assert agg.acceptance_counts(cells) == {"accepted_better": 1, "accepted_worse": 0, "rejected_better": 0,
                                            "rejected_worse": 3}


# ----------------------------------------------------------------------------- the new options


def test_pca_covariances_against_numpy():
    from gr_graph.pca_covariances import pca_covariances

    rng = np.random.default_rng(1)
    P = rng.normal(0, 1, (60, 3)) * [3.0, 1.0, 0.1]
    C = pca_covariances(P, k=8, eps=1e-6)
    d = np.linalg.norm(P[:, None] - P[None], axis=2)
    for i in (0, 17, 59):
        nb = P[np.argsort(d[i])[:8]]
        np.testing.assert_allclose(C[i], np.cov(nb.T, bias=True) + 1e-6 * np.eye(3), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(C) >= 1e-6 - 1e-12)
    with pytest.raises(ValueError, match="k must be"):
        pca_covariances(P, 1)
    # eps 0 (valid with the geometric head): an exactly planar neighbourhood stays positive definite,
    # so a noise-free frame is densified, not sent whole to the non-PD fallback
    from gr_graph.densify import covariance_problem

    plane = np.c_[rng.uniform(-5, 5, (200, 2)), np.zeros(200)]
    C0 = pca_covariances(plane, k=10, eps=0.0)
    assert covariance_problem(C0) is None and np.all(np.linalg.eigvalsh(C0)[:, 0] > 0)
    lam = np.linalg.eigvalsh(C0)
    assert np.all(lam[:, 0] <= 1e-8 * lam.sum(axis=1))  # the floor is a trace fraction: the shape stays flat


def test_densify_off_returns_raw_frames_and_keeps_predictions():
    from gr_graph.densify import densified_sequence
    from gr_graph.pca_covariances import PcaCovariances
    from test_learning_rounds import PlaneScenes

    seq = PlaneScenes(n=2)
    cfg = TrainingConfig(densify=False, tau_ani=0.5)
    view = densified_sequence(seq, PcaCovariances(10, 1e-6), cfg, preprocess=PreprocessConfig())
    f = view[1]
    np.testing.assert_array_equal(f.points, seq[1].points)
    pts, C = view.predicted(1)
    assert C.shape == (len(pts), 3, 3) and len(pts) < len(f.points)
    assert view.stats()["fallbacks"] == {} and view.stats()["mean_kept_points"] > 0
    on = densified_sequence(seq, PcaCovariances(10, 1e-6), cfg.model_copy(update={"densify": True}),
                            preprocess=PreprocessConfig())
    assert len(on[1].points) != len(seq[1].points)


def test_round_fingerprints_of_the_defaults_stay_those_of_finished_runs():
    """An option added later must not change the fingerprint at its default (pipeline._ADDED_OPTIONS), or
    every finished round of every run is recomputed on resume. The values are those of 7cd09ab
    (2026-12-06), computed there; before sensor.frame_stamp was listed, round 0 hashed 5c176f6b483a7b31."""
    from gr_graph.pipeline import round_fingerprint

    cfg = load_config(None, {"training": {"rounds": 2}})
    assert [round_fingerprint(cfg, r) for r in (0, 1)] == ["6f7e390c5d4d8e78", "f93fc853f0eb14d0"]


def test_stop_on_reject_is_not_part_of_the_round_fingerprint():
    from gr_graph.pipeline import round_fingerprint

    # the training options at the defaults of the runs published before 2026-12-05 (the paper's Gaussian and
    # densification): the fingerprint those runs were written with
    legacy = {"keep_original": False, "keep_dropped": False, "trainer": {"corr_likelihood": "gaussian"}}
    a = load_config(None, {"training": {"rounds": 2, **legacy}})
    b = load_config(None, {"training": {"rounds": 2, "stop_on_reject": False, **legacy}})
    c = load_config(None, {"training": {"rounds": 2, "densify": False, **legacy}})
    # today's defaults (the t, densification that only adds) are other learning rounds, the same round 0
    now = load_config(None, {"training": {"rounds": 2}})
    assert round_fingerprint(now, 1) != round_fingerprint(a, 1) and round_fingerprint(now, 0) == round_fingerprint(a, 0)
    assert round_fingerprint(a, 1) == round_fingerprint(b, 1) != round_fingerprint(c, 1)
    assert round_fingerprint(a, 0) == round_fingerprint(c, 0)
    # graph.loop_variance: the default leaves the fingerprint as it was before the option existed
    # (the key is not hashed), the estimated variance changes every round's result
    e = load_config(None, {"training": {"rounds": 2}, "graph": {"loop_variance": "estimated"}})
    assert round_fingerprint(e, 0) != round_fingerprint(a, 0) and round_fingerprint(e, 1) != round_fingerprint(a, 1)
    import hashlib

    keyframes = {"map_keyframe_translation", "map_keyframe_rotation_deg"}
    loop_options = {"min_path_length", "sc_height_offset"}
    spin_options = {"rotation", "sweep_start_azimuth_deg", "frame_stamp"}
    d = a.model_dump(mode="json", exclude={"output": True, "data": {"prefetch", "frame_cache", "read_threads",
                                                                    "render_process"}, "training": True,
                                           "device": True, "graph": {"loop_variance", "registration_covariance",
                                                                      "cluster_size", "min_clusters",
                                                                      "ground_tilt_offset"},
                                           "odometry": keyframes, "loops": loop_options, "sensor": spin_options})
    # sensor.time_unit / time_reference became None (guessed): hashed as their former defaults
    d["sensor"].update(time_unit="s", time_reference="sweep_start")
    assert round_fingerprint(a, 0) == hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]
    # graph.registration_covariance likewise (its two options are hashed only away from their defaults)
    c = load_config(None, {"training": {"rounds": 2}, "graph": {"registration_covariance": "cluster_robust"}})
    assert round_fingerprint(c, 0) != round_fingerprint(a, 0)
    c16 = load_config(None, {"training": {"rounds": 2}, "graph": {"registration_covariance": "cluster_robust",
                                                                  "cluster_size": 16.0}})
    assert round_fingerprint(c16, 0) != round_fingerprint(c, 0)
    # odometry.map_keyframe_* likewise (every round registers with the odometry)
    m = load_config(None, {"training": {"rounds": 2}, "odometry": {"map_keyframe_translation": 0.1,
                                                                   "map_keyframe_rotation_deg": 1.0}})
    assert all(round_fingerprint(m, r) != round_fingerprint(a, r) for r in (0, 1))
    # loops.min_path_length and sc_height_offset likewise
    for section, options in (("loops", {"min_path_length": 20.0}), ("loops", {"sc_height_offset": 3.0}),
                             ("sensor", {"rotation": "counterclockwise"}), ("sensor", {"sweep_start_azimuth_deg": 0.0}),
                             ("sensor", {"frame_stamp": "sweep_start"})):
        lp = load_config(None, {"training": {"rounds": 2}, section: options})
        assert all(round_fingerprint(lp, r) != round_fingerprint(a, r) for r in (0, 1)), options
    g = load_config(None, {"training": {"rounds": 2}, "graph": {"ground_tilt_offset": True}})
    assert all(round_fingerprint(g, r) != round_fingerprint(now, r) for r in (0, 1))
    # training.keep_dropped likewise, for the learning rounds (round 0 never hashes the training section)
    k = load_config(None, {"training": {"rounds": 2, **legacy, "keep_dropped": True}})
    assert round_fingerprint(k, 1) != round_fingerprint(a, 1) and round_fingerprint(k, 0) == round_fingerprint(a, 0)
    d1 = a.model_dump(mode="json", exclude={"output": True, "data": {"prefetch", "frame_cache", "read_threads",
                                                                     "render_process"},
                                            "graph": {"loop_variance", "registration_covariance", "cluster_size",
                                                      "min_clusters", "ground_tilt_offset"}, "odometry": keyframes,
                                            "loops": loop_options,
                                            "sensor": spin_options,
                                            "training": {"rounds", "convergence_delta", "acceptance", "stop_on_reject",
                                                         "weights", "fine_tune", "keep_dropped", "prediction_passes",
                                                         "learned_noise_outlier_alpha", "learned_noise_covariance"}})
    d1["sensor"].update(time_unit="s", time_reference="sweep_start")
    for key in ("corr_likelihood", "corr_dof"):  # the trainer's options added later, likewise
        d1["training"]["trainer"].pop(key)
    assert round_fingerprint(a, 1) == hashlib.sha256(json.dumps(d1, sort_keys=True).encode()).hexdigest()[:16]
    t = load_config(None, {"training": {"rounds": 2, **legacy, "trainer": {"corr_likelihood": "student_t"}}})
    assert round_fingerprint(t, 1) != round_fingerprint(a, 1) and round_fingerprint(t, 0) == round_fingerprint(a, 0)
    t5 = load_config(None, {"training": {"rounds": 2, **legacy,
                                         "trainer": {"corr_likelihood": "student_t", "corr_dof": 5.0}}})
    assert round_fingerprint(t5, 1) != round_fingerprint(t, 1)
    # training.prediction_passes (2026-12-06) likewise: the learning rounds only, away from its default
    pp = load_config(None, {"training": {"rounds": 2, **legacy, "prediction_passes": "training_size"}})
    assert round_fingerprint(pp, 1) != round_fingerprint(a, 1) and round_fingerprint(pp, 0) == round_fingerprint(a, 0)
    # training.learned_noise_outlier_alpha (2026-12-06) likewise
    oa = load_config(None, {"training": {"rounds": 2, **legacy, "learned_noise_outlier_alpha": 1e-4}})
    assert round_fingerprint(oa, 1) != round_fingerprint(a, 1) and round_fingerprint(oa, 0) == round_fingerprint(a, 0)
    # training.learned_noise_covariance (2026-12-07) likewise
    lc = load_config(None, {"training": {"rounds": 2, **legacy, "learned_noise_covariance": "cluster_robust"}})
    assert round_fingerprint(lc, 1) != round_fingerprint(a, 1) and round_fingerprint(lc, 0) == round_fingerprint(a, 0)
    # ... but neither counts where the learned edge noise is off: the edges keep the registration's information
    reg = load_config(None, {"training": {"rounds": 2, **legacy, "edge_noise": "registration"}})
    reg_set = load_config(None, {"training": {"rounds": 2, **legacy, "edge_noise": "registration",
                                              "learned_noise_covariance": "cluster_robust_offset",
                                              "learned_noise_outlier_alpha": 1e-4}})
    assert round_fingerprint(reg, 1) != round_fingerprint(a, 1)
    assert round_fingerprint(reg_set, 1) == round_fingerprint(reg, 1)
    reg_older = load_config(None, {"training": {"rounds": 2, **legacy, "edge_noise": "registration",
                                                "learned_noise_scale": 2.0}})  # an older option: still counted
    assert round_fingerprint(reg_older, 1) != round_fingerprint(reg, 1)
    # how frames are read (data.read_threads, like prefetch) is in no fingerprint
    t = load_config(None, {"training": {"rounds": 2, **legacy}, "data": {"read_threads": 1, "prefetch": 2}})
    assert [round_fingerprint(t, r) for r in (0, 1)] == [round_fingerprint(a, r) for r in (0, 1)]


# ----------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_smoke_cell_end_to_end_through_the_cli(tmp_path, capsys):
    """table1 cell 0 of the smoke budget (60 frames, 16 channels, 1 epoch, tiny network)."""
    root = tmp_path / "exp"
    assert main(["table1", "--budget", "smoke", "--root", str(root), "--cell", "0", "--log-level", "WARNING"]) == 0
    cell = cells_for("table1", "smoke")[0]
    d = rc.cell_dir(root, cell)
    doc = json.loads((d / "cell.json").read_text())
    assert doc["fingerprint"] == cell.fingerprint() and doc["cpu_s"] > 0
    assert 100 < doc["peak_rss_mb"] < 24 * 1024  # this process's peak, in MiB (torch alone holds > 100)
    assert set(doc["git"]) == {"commit", "dirty"} and "cores" in doc["machine"]  # what a published record names
    assert set(doc["rounds"]) == {"0", "1", "2"}  # no convergence stop in a cell
    assert doc["rounds"]["1"]["slam"]["ate_rmse"] is not None
    assert doc["kiss_icp"]["system"].startswith("KISS-ICP 1.3.0") and doc["kiss_icp"]["ate_rmse"] < 1.0
    slam = d / "slam"
    assert not list(slam.glob("round_*/memory"))  # pruned
    assert (slam / "round_1" / "training" / "model.pt").is_file() and (slam / "metrics.json").is_file()
    assert (slam / "round_2" / "poses_kitti.txt").is_file()
    frames = json.loads((slam / "metrics.json").read_text())["frame_cache"]  # rounds 1, 2 read round 0's frames
    assert frames["misses"] == 60 and frames["hits"] >= 120 and frames["unreadable"] == 0
    assert not (slam / "frames").exists()  # removed once the KISS-ICP baseline had read the frames too
    mtime = (d / "cell.json").stat().st_mtime_ns
    assert main(["table1", "--budget", "smoke", "--root", str(root), "--cell", cell.key]) == 0
    assert (d / "cell.json").stat().st_mtime_ns == mtime  # finished: skipped
    capsys.readouterr()
    assert main(["table1", "--budget", "smoke", "--root", str(root), "--report", "--no-records"]) == 0
    md = (root / "table1" / "report.md").read_text()
    assert "budget `smoke`: 6 cells (1 finished)" in md and "missing cells" in md
    assert "| raw |" in md and "KISS-ICP 1.3.0" in md and "seeds 0" in md
    rep = json.loads((root / "table1" / "report.json").read_text())
    assert rep["summary"]["16ch"]["seeds"] == [0]
    assert (root / "table1" / "figures" / "table1_smoke_trajectories_16ch-s0.png").is_file()


def test_a_resumed_cell_counts_the_recorded_time_of_the_work_it_resumed(tmp_path):
    """A cell interrupted after round 1 (its record and round 2's summary missing) and run again:
    the second call resumes rounds 0 and 1 and the KISS-ICP baseline, and the cell's time adds
    their recorded times to the call's own (before, the call's time alone: a few seconds)."""
    cell = cells_for("table1", "smoke")[0]
    first = rc.run_cell(tmp_path, cell)
    assert first["resumed"] == {"rounds": [], "kiss_icp": False, "wall_s": 0.0, "not_counted": []}
    assert rc.cell_wall_s(first) == first["wall_s"]
    d = rc.cell_dir(tmp_path, cell)
    (d / "cell.json").unlink()
    (d / "slam" / "round_2" / "round.json").unlink()
    second = rc.run_cell(tmp_path, cell)
    rounds = first["rounds"]
    done_before = (rounds["0"]["runtime_s"]["total"] + rounds["1"]["runtime_s"]["total"]
                   + rounds["1"]["runtime_s"]["training"] + first["kiss_icp"]["wall_s"])
    assert second["resumed"]["rounds"] == [0, 1] and second["resumed"]["kiss_icp"]
    assert second["resumed"]["wall_s"] == pytest.approx(done_before, rel=1e-12)
    assert rc.cell_wall_s(second) == pytest.approx(second["wall_s"] + done_before, rel=1e-12)
    assert second["rounds"]["1"]["runtime_s"] == rounds["1"]["runtime_s"]  # resumed, not recomputed
    assert second["rounds"]["2"]["runtime_s"] != rounds["2"]["runtime_s"]  # recomputed in the second call
    assert second["rounds"]["2"]["slam"] == rounds["2"]["slam"]  # the same model (its training resumed), same poses
    results = {cell.key: second}
    row = [ln for ln in report._runtime_md([cell], results) if ln.startswith(f"| {cell.key} ")][0]
    assert row.split(" | ")[2] == f"{rc.cell_wall_s(second) / 60:.1f}"


def test_work_copied_from_a_source_cell_is_not_counted_again():
    """An ablation cell resumes the round 0 (and round-1 training) it copied from its seed's default
    cell: timed there, not added to the ablation cell's time."""
    metrics = {"rounds": {"0": {"runtime_s": {"total": 100.0}},
                          "1": {"runtime_s": {"total": 30.0, "training": 400.0}},
                          "2": {"runtime_s": {"total": 20.0, "training": 300.0}}}}
    assert rc.reused_from_source(None) == set() and rc.reused_from_source({"what": None}) == set()
    assert rc.reused_from_source({"what": "round0"}) == {"round_0"}
    both = rc.reused_from_source({"what": "round1_training", "note": "already in place"})
    assert both == {"round_0", "round_1/training"}
    assert rc.resumed_work(metrics, [0, 1, 2], None)["wall_s"] == 850.0
    assert rc.resumed_work(metrics, [0, 1], None, {"round_0"})["wall_s"] == 430.0
    done = rc.resumed_work(metrics, [0, 1, 2], {"wall_s": 5.0}, both)
    assert done["wall_s"] == 30.0 + 20.0 + 300.0 + 5.0 and done["not_counted"] == ["round_0", "round_1/training"]


def test_cell_cpu_time_counts_the_render_process():
    """Cells of 500 frames or more render in a child process: its CPU time counts in ``cpu_s``."""
    import subprocess
    import time

    before, own = rc.cpu_seconds(), time.process_time()
    subprocess.run([sys.executable, "-c", "t = __import__('time'); e = t.process_time() + 0.3\n"
                    "while t.process_time() < e: pass"], check=True)
    assert rc.cpu_seconds() - before >= 0.25 and time.process_time() - own < 0.2


def test_a_figure_that_cannot_be_drawn_is_left_out_not_the_report(tmp_path, monkeypatch, caplog):
    """One cell's damaged marginals.npz (the trajectory figure reads it) must not cost the report: the figure
    is logged and left out, the others are kept."""
    import zipfile

    from gr_graph.experiments import figures as fig

    cells = cells_for("table1", "smoke")
    results = {c.key: {} for c in cells}

    def damaged(cell_path, path, title):
        raise zipfile.BadZipFile("File is not a zip file")

    monkeypatch.setattr(fig, "plot_rpe_over_rounds", lambda summary, path: path)
    monkeypatch.setattr(fig, "plot_round_trajectories", damaged)
    monkeypatch.setattr(report, "_raw_vs_densified", lambda *a: tmp_path / "raw_vs_dense.png")
    with caplog.at_level("WARNING", logger="gr_graph.experiments.report"):
        out = report._figures("table1", tmp_path, cells, results, {}, "cpu", "smoke")
    assert "error over rounds (RPE-300, ATE)" in out and not any(k.startswith("trajectories") for k in out)
    assert ("raw vs densified 32-channel scan" in out) == any(c.channels == 32 for c in cells)
    assert "left out of the report: BadZipFile: File is not a zip file" in caplog.text


def test_no_ablation_cell_reruns_its_budgets_default_cell():
    """An ablation whose settings the budget already has would rerun the default cell under a misleading
    name: it has no cell there; the paper's budget keeps every ablation."""
    for name in BUDGETS:
        cells = cells_for("ablations", name)
        default = {c.seed: c.overrides for c in cells if c.key.startswith("default-")}
        assert all(c.overrides != default[c.seed] for c in cells if not c.key.startswith("default-")), name
    assert {c.key.rsplit("-s", 1)[0] for c in cells_for("ablations", "paper")} == set(ABLATIONS)
    assert {c.key.rsplit("-s", 1)[0] for c in cells_for("ablations", "student-t-8ep-adds")} == \
        set(ABLATIONS) - {"student-t", "student-t-8ep", "densify-adds"}


def test_budget_help_describes_every_budget():
    from gr_graph.experiments.cli import build_parser

    text = next(a.help for a in build_parser()._actions if a.dest == "budget")
    assert all(b.description and f"{name}: {b.description}" in text for name, b in BUDGETS.items())
    assert BUDGETS["student-t-adds-revisit"].description != BUDGETS["student-t-adds"].description


def test_a_killed_delete_of_a_cell_folder_leaves_no_results_to_resume(tmp_path, monkeypatch):
    """A delete killed midway (a time limit) must not leave old round.json files without cell.json behind:
    the folder is renamed away first, and the next delete removes what is left of it."""
    d = tmp_path / "ablations" / "default-s0"
    (d / "slam" / "round_0").mkdir(parents=True)
    (d / "slam" / "round_0" / "round.json").write_text("{}")
    (d / "cell.json").write_text("{}")
    real_rmtree = shutil.rmtree

    def killed(path, *a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(shutil, "rmtree", killed)
    with pytest.raises(KeyboardInterrupt):
        rc.remove_tree(d)
    assert not d.exists() and len(list(d.parent.glob(".trash-default-s0-*"))) == 1
    monkeypatch.setattr(shutil, "rmtree", real_rmtree)
    d.mkdir()
    (d / "new").write_text("x")
    rc.remove_tree(d)
    assert list(d.parent.iterdir()) == []
    # the next start of the cell sweeps what a killed delete left, though nothing is deleted then
    (d.parent / ".trash-default-s0-1-2" / "slam").mkdir(parents=True)
    cell = next(c for c in cells_for("ablations", "smoke") if c.key == "default-s0")
    rc._start(tmp_path, cell, "smoke")
    assert not list(d.parent.glob(".trash-*")) and (d / rc.DEFINITION_JSON).is_file()
