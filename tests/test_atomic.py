"""Atomic output: complete files or the old ones, never a torn write, usual permissions."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from gr_graph.atomic import atomic_path, atomic_save_npz, atomic_write_json, atomic_write_text, read_json_or_none


def test_text_json_npz_round_trip(tmp_path: Path) -> None:
    atomic_write_text(tmp_path / "a" / "x.txt", "one\ntwo\n")
    assert (tmp_path / "a" / "x.txt").read_text() == "one\ntwo\n"
    atomic_write_json(tmp_path / "m.json", {"v": np.float64(1.5), "a": np.arange(3)})
    assert (tmp_path / "m.json").read_text().count("1.5") == 1
    atomic_save_npz(tmp_path / "z.npz", p=np.eye(3))
    with np.load(tmp_path / "z.npz") as z:
        np.testing.assert_array_equal(z["p"], np.eye(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "m.json", "z.npz"]


def test_error_keeps_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "poses.txt"
    atomic_write_text(target, "old\n")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed mid-write")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["poses.txt"]


def test_mode_follows_umask(tmp_path: Path) -> None:
    from gr_graph.atomic import _umask

    for umask, mode in ((0o022, 0o644), (0o027, 0o640), (0o077, 0o600)):  # not one fixed mode
        old = os.umask(umask)
        try:
            assert _umask() == umask  # read, not set
            atomic_write_text(tmp_path / f"r{umask:o}.txt", "x")
        finally:
            os.umask(old)
        assert stat.S_IMODE((tmp_path / f"r{umask:o}.txt").stat().st_mode) == mode


def test_read_json_or_none_takes_a_broken_file_as_missing(tmp_path: Path) -> None:
    """A resume reads round.json / cell.json with it: a file cut short or of binary garbage is no record."""
    atomic_write_json(tmp_path / "ok.json", {"a": 1})
    assert read_json_or_none(tmp_path / "ok.json") == {"a": 1}
    (tmp_path / "cut.json").write_text('{"a": ')
    (tmp_path / "binary.json").write_bytes(b"\x89PNG\r\n\xff\xfe")
    assert read_json_or_none(tmp_path / "cut.json") is None and read_json_or_none(tmp_path / "binary.json") is None
    assert read_json_or_none(tmp_path / "missing.json") is None


def test_a_file_that_cannot_be_written_is_named_not_its_temporary(tmp_path: Path) -> None:
    (tmp_path / "a_file").write_text("")
    target = tmp_path / "a_file" / "out.json"  # a folder that is a file
    with pytest.raises(OSError, match=f"cannot write {target}"):
        atomic_write_json(target, {"a": 1})


def test_errors_while_writing_name_the_file_and_keep_their_kind(tmp_path: Path) -> None:
    """A full disk or a refused write inside the block is raised as the same error type and errno, naming
    the file asked for (not its temporary sibling); an error about another file passes unchanged."""
    target = tmp_path / "out.ply"
    with pytest.raises(OSError, match=f"cannot write {target}: No space left") as err:
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert err.value.errno == errno.ENOSPC and type(err.value) is OSError
    with pytest.raises(PermissionError, match=f"cannot write {target}: Permission denied") as err:
        with atomic_path(target) as tmp:
            raise PermissionError(errno.EACCES, "Permission denied", str(tmp))
    assert err.value.errno == errno.EACCES
    with pytest.raises(OSError, match="cannot write .*out.ply: encoder error -2 when writing image file"):
        with atomic_path(target):  # a writer's own error, no errno (PIL raises so)
            raise OSError("encoder error -2 when writing image file")
    with pytest.raises(FileNotFoundError, match=r"^\[Errno 2\] calibration /data/calib.txt not found$"):
        with atomic_path(target):  # an input's error that names no file attribute: not the output's
            raise FileNotFoundError(errno.ENOENT, "calibration /data/calib.txt not found")
    from urllib.error import URLError

    with pytest.raises(URLError, match="timed out") as net:
        with atomic_path(target):  # a network's error (an OSError subclass without errno): unchanged
            raise URLError("timed out")
    assert "cannot write" not in str(net.value)
    with pytest.raises(ConnectionResetError, match=r"^\[Errno 104\] Connection reset by peer$"):
        with atomic_path(target):  # not about the file: unchanged
            raise ConnectionResetError(errno.ECONNRESET, "Connection reset by peer")
    with pytest.raises(OSError, match=f"^\\[Errno {errno.ENOSPC}\\] cannot write {tmp_path / 'inner.json'}: No space"):
        with atomic_path(target):  # nested: the inner file's name is kept
            with atomic_path(tmp_path / "inner.json"):
                raise OSError(errno.ENOSPC, "No space left on device")
    other = tmp_path / "input.pcd"
    with pytest.raises(FileNotFoundError) as err:
        with atomic_path(target):
            open(other)
    assert err.value.filename == str(other) and "cannot write" not in str(err.value)
    assert not list(tmp_path.iterdir())  # no target, no temporary left behind
