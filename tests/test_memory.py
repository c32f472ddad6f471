"""The on-disk memory: round trip, memory mapping, validation and atomic replacement."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gr_graph.memory import (
    EDGE_LOOP,
    EDGE_ODOMETRY,
    Memory,
    MemoryFormatError,
    load_memory,
    save_memory_from_scans,
)


def _memory_parts(rng: np.random.Generator, n_scans: int = 4, n_points: tuple[int, int] = (50, 80)) -> dict:
    scans = [rng.normal(size=(int(rng.integers(*n_points)), 3)).astype(np.float32) for _ in range(n_scans)]
    poses = np.tile(np.eye(4), (n_scans, 1, 1))
    poses[:, 0, 3] = np.arange(n_scans)
    edges = [(k, k + 1) for k in range(n_scans - 1)] + [(n_scans - 1, 0)]
    kinds = [EDGE_ODOMETRY] * (n_scans - 1) + [EDGE_LOOP]
    edge_T = [np.linalg.inv(poses[l]) @ poses[k] for k, l in edges]
    edge_H = [np.eye(6) * (e + 1) for e in range(len(edges))]
    corr = [
        np.stack([rng.integers(0, len(scans[k]), 30), rng.integers(0, len(scans[l]), 30)], 1)
        for k, l in edges
    ]
    return {"scans": scans, "poses": poses, "edges": edges, "edge_kind": kinds, "edge_T": edge_T,
            "edge_H": edge_H, "corr": corr, "info": {"round": 0}}


def _memory(rng: np.random.Generator, n_scans: int = 4) -> Memory:
    return Memory.from_scans(**_memory_parts(rng, n_scans))


def test_round_trip_memory_mapped(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    mem = _memory(rng)
    mem.save(tmp_path / "m")
    back = load_memory(tmp_path / "m")
    assert isinstance(back.points, np.memmap)
    assert back.n_scans == 4 and back.n_edges == 4 and back.info == {"round": 0}
    for k in range(4):
        np.testing.assert_array_equal(back.scan(k), mem.scan(k))
    e = back.edge(3)
    assert (e.k, e.l, e.kind) == (3, 0, EDGE_LOOP)
    np.testing.assert_array_equal(e.corr, mem.edge(3).corr)
    np.testing.assert_array_equal(e.H, np.eye(6) * 4)


def test_save_replaces_atomically(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    _memory(rng, 3).save(tmp_path / "m")
    _memory(rng, 5).save(tmp_path / "m")
    assert load_memory(tmp_path / "m").n_scans == 5
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no temporary leftovers


def test_failed_save_keeps_previous(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    _memory(rng, 3).save(tmp_path / "m")
    bad = _memory(rng, 3)
    bad.edge_T[0, 0, 0] = np.nan
    with pytest.raises(MemoryFormatError, match="non-finite"):
        bad.save(tmp_path / "m")
    assert load_memory(tmp_path / "m").n_scans == 3


def test_out_of_range_correspondence(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    mem = _memory(rng)
    mem.corr[0, 0] = 10_000
    with pytest.raises(MemoryFormatError, match="correspondence index out of range"):
        mem.validate()


def test_wrong_format_and_missing_parts(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    with pytest.raises(MemoryFormatError, match="no meta.json"):
        load_memory(tmp_path)
    _memory(rng).save(tmp_path / "m")
    (tmp_path / "m" / "corr.npy").unlink()
    with pytest.raises(MemoryFormatError, match="missing corr.npy"):
        load_memory(tmp_path / "m")
    _memory(rng).save(tmp_path / "m")
    meta = json.loads((tmp_path / "m" / "meta.json").read_text())
    meta["version"] = 99
    (tmp_path / "m" / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(MemoryFormatError, match="v99"):
        load_memory(tmp_path / "m")


def test_saved_memory_has_usual_permissions(tmp_path: Path) -> None:
    import os
    import stat

    old = os.umask(0o022)
    try:
        _memory(np.random.default_rng(5)).save(tmp_path / "m")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "m").stat().st_mode) == 0o755


def test_streaming_write_gives_the_same_files(tmp_path: Path) -> None:
    parts = _memory_parts(np.random.default_rng(6), 5)
    parts["corr"][1] = np.zeros((0, 2), np.int64)  # an edge without correspondences
    Memory.from_scans(**parts).save(tmp_path / "a")
    mem = save_memory_from_scans(tmp_path / "b", **parts)
    assert isinstance(mem.points, np.memmap) and mem.n_scans == 5 and mem.info == {"round": 0}
    for f in sorted((tmp_path / "a").iterdir()):
        assert (tmp_path / "b" / f.name).read_bytes() == f.read_bytes(), f.name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]  # no temporary leftovers


def test_streaming_write_holds_no_concatenated_copy(tmp_path: Path) -> None:
    """tracemalloc sees numpy's allocations: assembling in RAM needs a second copy of every
    point and correspondence, the streaming writer (memory-mapped files) does not."""
    import tracemalloc

    parts = _memory_parts(np.random.default_rng(7), 40, (20_000, 20_001))
    parts["corr"] = [np.stack([np.arange(20_000), np.arange(20_000)], 1).astype(np.int32) for _ in parts["edges"]]
    payload = sum(s.nbytes for s in parts["scans"]) + sum(c.nbytes for c in parts["corr"])
    peaks = {}
    for name, write in (("ram", lambda d: Memory.from_scans(**parts).save(d)),
                        ("stream", lambda d: save_memory_from_scans(d, **parts))):
        tracemalloc.start()
        write(tmp_path / name)
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peaks["ram"] > payload  # the control: the in-RAM assembly holds the concatenation
    assert peaks["stream"] < 0.1 * payload, peaks
    np.testing.assert_array_equal(load_memory(tmp_path / "stream").points, load_memory(tmp_path / "ram").points)


def test_failed_streaming_write_keeps_previous(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    save_memory_from_scans(tmp_path / "m", **_memory_parts(rng, 3))
    bad = _memory_parts(rng, 4)
    bad["corr"][0][0, 0] = 10_000
    with pytest.raises(MemoryFormatError, match="correspondence index out of range"):
        save_memory_from_scans(tmp_path / "m", **bad)
    assert load_memory(tmp_path / "m").n_scans == 3
    assert [p.name for p in tmp_path.iterdir()] == ["m"]


def test_streaming_write_maps_no_file_and_survives_a_stale_old_folder(tmp_path: Path, monkeypatch) -> None:
    """Written, not memory-mapped (a full disk is an OSError, not a SIGBUS killing the process);
    a ``.m.old-<pid>`` folder left by a killed process with this pid does not make the save fail."""
    import os

    rng = np.random.default_rng(9)
    save_memory_from_scans(tmp_path / "m", **_memory_parts(rng, 3))
    stale = tmp_path / f".m.old-{os.getpid()}"
    stale.mkdir()
    (stale / "points.npy").write_bytes(b"left by a killed process")

    mapping = np.lib.format.open_memmap

    def no_mapping(*args, **kwargs):  # reading the saved memory back maps it ("r"): that is fine
        if kwargs.get("mode", args[1] if len(args) > 1 else "r+") != "r":
            raise AssertionError("the memory files are written through a memory map")
        return mapping(*args, **kwargs)

    monkeypatch.setattr(np.lib.format, "open_memmap", no_mapping)
    parts = _memory_parts(rng, 4)
    save_memory_from_scans(tmp_path / "m", **parts)
    monkeypatch.undo()
    back = load_memory(tmp_path / "m")
    assert back.n_scans == 4
    np.testing.assert_array_equal(back.scan(2), parts["scans"][2])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["m", stale.name])  # the stale one is not ours


def test_streaming_write_refuses_scans_of_another_width(tmp_path: Path) -> None:
    rng = np.random.default_rng(10)
    parts = _memory_parts(rng, 2)
    parts["scans"] = [np.arange(24, dtype=np.float32).reshape(6, 4), np.ones((3, 3), np.float32)]
    with pytest.raises(ValueError, match=r"points.npy: part 0 has shape \(6, 4\), expected \(n, 3\)"):
        save_memory_from_scans(tmp_path / "m", **parts)
    assert list(tmp_path.iterdir()) == []  # nothing half-written left


def test_empty_array_file_is_a_format_error(tmp_path: Path) -> None:
    save_memory_from_scans(tmp_path / "m", **_memory_parts(np.random.default_rng(11), 3))
    (tmp_path / "m" / "edge_T.npy").write_bytes(b"")  # e.g. a power loss before the data reached the disk
    with pytest.raises(MemoryFormatError, match="edge_T.npy: unreadable"):
        load_memory(tmp_path / "m")


def test_stale_siblings_of_killed_writes_are_removed_but_never_the_only_copy(tmp_path: Path, caplog) -> None:
    import os

    from gr_graph.memory import STALE_SIBLING_S

    rng = np.random.default_rng(12)
    old_time = __import__("time").time() - 2 * STALE_SIBLING_S
    left = {}
    for name in (".m.tmp-abc", ".m.old-def", ".m.tmp-new"):
        left[name] = tmp_path / name
        left[name].mkdir()
        (left[name] / "points.npy").write_bytes(b"x")
        if name != ".m.tmp-new":
            os.utime(left[name], (old_time, old_time))
    save_memory_from_scans(tmp_path / "m", **_memory_parts(rng, 3))  # no memory yet: the old one is the only copy
    assert not left[".m.tmp-abc"].exists() and left[".m.old-def"].is_dir() and left[".m.tmp-new"].is_dir()
    with caplog.at_level("WARNING", logger="gr_graph.memory"):
        save_memory_from_scans(tmp_path / "m", **_memory_parts(rng, 4))
    assert not left[".m.old-def"].exists() and "left by an interrupted write" in caplog.text
    assert left[".m.tmp-new"].is_dir()  # young: perhaps being written


def test_failed_rename_puts_the_earlier_memory_back(tmp_path: Path, monkeypatch) -> None:
    import os

    rng = np.random.default_rng(13)
    save_memory_from_scans(tmp_path / "m", **_memory_parts(rng, 3))
    real = os.replace
    calls = []

    def second_fails(src, dst):
        calls.append(dst)
        if len(calls) == 2:  # the new memory onto its place
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(os, "replace", second_fails)
    with pytest.raises(OSError, match="No space"):
        save_memory_from_scans(tmp_path / "m", **_memory_parts(rng, 4))
    monkeypatch.undo()
    assert load_memory(tmp_path / "m").n_scans == 3
    assert [p.name for p in tmp_path.iterdir()] == ["m"]
