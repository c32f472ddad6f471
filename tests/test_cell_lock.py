"""One process at a time in a cell: gr_graph.experiments.cell_lock and run_cell / the CLI with it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gr_graph.experiments import run_cell as rc
from gr_graph.experiments.cell_lock import CellBusyError, cell_lock, lock_path
from gr_graph.experiments.cells import cells_for
from gr_graph.experiments.cli import main

HOLD_LOCK = textwrap.dedent("""
    import sys, time
    from gr_graph.experiments.cell_lock import cell_lock
    with cell_lock(sys.argv[1]):
        print("held", flush=True)
        time.sleep(120)
""")


def _holder(folder: Path) -> subprocess.Popen:
    """A separate process holding the lock of ``folder`` until it is killed."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_lock_is_exclusive_and_released(tmp_path: Path) -> None:
    folder = tmp_path / "table1" / "c16-s0"
    assert lock_path(folder) == tmp_path / "table1" / ".c16-s0.lock"
    with cell_lock(folder) as path:
        owner = json.loads(path.read_text())
        assert owner["pid"] == os.getpid() and owner["host"] and owner["started_utc"]
        with pytest.raises(CellBusyError, match=rf"c16-s0 is being run by process {os.getpid()} on .*lock"):
            with cell_lock(folder):  # another open file of the same process: refused too
                pass
    with cell_lock(folder):  # released at the end of the block
        pass
    with pytest.raises(ZeroDivisionError):
        with cell_lock(folder):
            1 / 0
    with cell_lock(folder):  # and when the block fails
        pass


def test_lock_of_a_killed_process_is_not_stale(tmp_path: Path) -> None:
    folder = tmp_path / "table1" / "c16-s1"
    proc = _holder(folder)
    try:
        with pytest.raises(CellBusyError, match=f"process {proc.pid} on "):
            with cell_lock(folder):
                pass
    finally:
        proc.send_signal(signal.SIGKILL)  # no cleanup code runs
        proc.wait()
    with cell_lock(folder) as path:  # the operating system released it
        assert json.loads(path.read_text())["pid"] == os.getpid()


def test_busy_cell_is_not_touched_and_the_cli_goes_on(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture) -> None:
    calls: list[str] = []

    def fake_slam_cell(root, d, cell, device):
        calls.append(cell.key)
        return {"rounds": {}}

    monkeypatch.setattr(rc, "_run_slam_cell", fake_slam_cell)
    monkeypatch.setattr("gr_graph.experiments.cli.prune_finished", lambda root, cells: [])
    monkeypatch.setattr("gr_graph.experiments.report.write_report", lambda *a, **k: "report")
    cells = cells_for("table1", "smoke")
    busy = rc.cell_dir(tmp_path, cells[0])
    proc = _holder(busy)
    try:
        with pytest.raises(CellBusyError):
            rc.run_cell(tmp_path, cells[0])
        assert calls == [] and not busy.exists()  # nothing started or cleared in the busy cell
        assert main(["table1", "--budget", "smoke", "--root", str(tmp_path), "--no-records"]) == 1
        assert calls == [c.key for c in cells[1:]]  # the other cells ran
        assert f"1 cell(s) failed: {cells[0].key}" in capsys.readouterr().err
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    rc.run_cell(tmp_path, cells[0])
    assert calls[-1] == cells[0].key and rc.is_done(tmp_path, cells[0])


def test_cell_finished_by_another_process_meanwhile_is_taken(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cell = cells_for("table1", "smoke")[0]
    calls: list[str] = []
    monkeypatch.setattr(rc, "_run_slam_cell", lambda root, d, c, device: calls.append(c.key) or {"rounds": {}})
    first = rc.run_cell(tmp_path, cell)
    looks: list[int] = []
    real = rc.read_cell_result

    def late(root, c):  # the first look misses it, as if it finished between the look and the lock
        looks.append(1)
        return None if len(looks) == 1 else real(root, c)

    monkeypatch.setattr(rc, "read_cell_result", late)
    assert rc.run_cell(tmp_path, cell) == first and calls == [cell.key] and len(looks) == 2


def test_a_file_system_without_locks_runs_the_cell_unlocked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    import errno

    import gr_graph.folder_lock as cl

    def no_locks(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(cl.fcntl, "flock", no_locks)
    with caplog.at_level("WARNING", logger="gr_graph.folder_lock"):
        with cell_lock(tmp_path / "table1" / "c") as path:
            assert json.loads(path.read_text())["pid"] == os.getpid()
    assert "takes no locks" in caplog.text

    def broken(fd, op):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(cl.fcntl, "flock", broken)
    with pytest.raises(OSError, match="Input/output"):  # other errors are not hidden
        with cell_lock(tmp_path / "table1" / "c"):
            pass
