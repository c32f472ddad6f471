"""Published benchmark reports are what their scripts make of their stored results: rebuilding one from the
JSON beside it changes nothing (a script edited since, or a report edited by hand, would show here)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from benchmark_support import BENCHMARKS, benchmark_script


@pytest.mark.parametrize("name, report, inputs", [
    ("bench_slam", "slam.md", "slam_*.json"),
    ("bench_drift", "drift.md", "drift_*.json"),
])
def test_a_rebuilt_report_equals_the_published_one(tmp_path: Path, monkeypatch, name: str, report: str,
                                                   inputs: str) -> None:
    results = BENCHMARKS / "results"
    for f in [results / report, *results.glob(inputs)]:
        shutil.copy(f, tmp_path / f.name)
    module = benchmark_script(name)
    monkeypatch.setattr(module, "RESULTS", tmp_path)
    published_machine = re.search(r"Machine: (.*?Python \d+\.\d+\.\d+)", (results / report).read_text())
    monkeypatch.setattr(module, "machine", lambda: published_machine.group(1))  # where it ran, not this machine
    module.write_markdown()
    assert (tmp_path / report).read_text() == (results / report).read_text()


def test_table2_nontrivial_rebuilds_from_its_json(tmp_path: Path, monkeypatch, capsys) -> None:
    module = benchmark_script("table2_nontrivial")
    published = BENCHMARKS / "results" / "table2_nontrivial.md"
    monkeypatch.setattr(module, "print_and_write", lambda name, text, document, write: print(text))
    argv = ["benchmarks/results/table2_nontrivial.json", "--from-json", "--write", "table2_nontrivial"]
    monkeypatch.chdir(BENCHMARKS.parent)
    assert module.main(argv) == 0
    assert capsys.readouterr().out == published.read_text()


def test_a_checkout_run_that_prints_nothing_is_named(tmp_path: Path) -> None:
    """``checkouts.run_alternating`` takes a run's last output line as its result: a run that prints none is an
    error naming the checkout, not an IndexError."""
    module = benchmark_script("checkouts")
    silent = tmp_path / "silent.py"
    silent.write_text("import sys\nprint('the cause', file=sys.stderr)\n")
    with pytest.raises(SystemExit, match=r"(?s)the a checkout \(.*\) printed nothing.*the cause"):
        module.run_alternating(silent, {"a": tmp_path}, 1, lambda name, rep: [])
    talker = tmp_path / "talker.py"
    talker.write_text("print('progress')\nprint('{\"result\": 1}')\n")
    assert module.run_alternating(talker, {"a": tmp_path}, 2, lambda name, rep: []) == {"a": ['{"result": 1}'] * 2}
