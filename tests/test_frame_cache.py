"""The on-disk frame cache (gr_graph.datasets.frame_cache): frames read back are the frames
made, a learning run with the cache gives the same result as without it, and bad cache files
are made again, counted."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from gr_graph.datasets.base import LidarFrame, release_render_cache
from gr_graph.datasets.frame_cache import CachedFrames, makes_frames
from gr_graph.datasets.registry import SequenceView
from gr_graph.datasets.synthetic import SyntheticSequence
from loader_support import assert_same_frame


class CountingSequence:
    """A small in-memory sequence that counts how often each frame is made."""

    name = "counting"

    def __init__(self, n: int = 4, with_time: bool = True) -> None:
        rng = np.random.default_rng(7)
        self.frames = [LidarFrame(index=10 + i, timestamp=0.1 * i + 1e-12 * np.pi, points=rng.normal(size=(50 + i, 3)),
                                  intensity=rng.random(50 + i).astype(np.float32),
                                  ring=rng.integers(0, 16, 50 + i).astype(np.int16), n_rings=16, dropped_nonfinite=i,
                                  time=rng.random(50 + i) if with_time else None) for i in range(n)]
        self.timestamps = np.array([f.timestamp for f in self.frames])
        self.gt_poses = None
        self.T_cam_velo = np.eye(4)
        self.made = [0] * n

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> LidarFrame:
        self.made[i] += 1
        return self.frames[i]


def test_frames_read_back_are_bit_identical_and_made_once(tmp_path):
    seq = CountingSequence()
    cache = CachedFrames(seq, tmp_path / "frames", key="k1")
    first = [cache[i] for i in range(len(seq))]
    again = [cache[i] for i in range(len(seq))]
    assert seq.made == [1, 1, 1, 1]
    for f, a, orig in zip(first, again, seq.frames):
        assert_same_frame(a, orig)
        assert_same_frame(f, orig)
    assert cache.stats()["hits"] == 4 and cache.stats()["misses"] == 4
    # a new view on the same directory and key reads the files (a resumed run)
    reopened = CachedFrames(seq, tmp_path / "frames", key="k1")
    assert_same_frame(reopened[-1], seq.frames[-1])
    assert seq.made == [1, 1, 1, 1] and reopened.hits == 1


def test_frames_without_ring_or_time(tmp_path):
    seq = CountingSequence(with_time=False)
    seq.frames = [LidarFrame(index=f.index, timestamp=f.timestamp, points=f.points, intensity=f.intensity)
                  for f in seq.frames]
    cache = CachedFrames(seq, tmp_path / "frames", key="k")
    cache[1]
    assert_same_frame(cache[1], seq.frames[1])
    assert cache[1].ring is None and cache[1].time is None


def test_another_key_empties_the_directory(tmp_path):
    seq = CountingSequence()
    CachedFrames(seq, tmp_path / "frames", key="k1")[0]
    cache = CachedFrames(seq, tmp_path / "frames", key="k2")
    assert not cache.path(0).exists()
    cache[0]
    assert seq.made[0] == 2
    assert json.loads((tmp_path / "frames" / "cache.json").read_text())["key"] == "k2"


def test_a_cache_opened_later_touches_nothing_until_then(tmp_path):
    seq = CountingSequence()
    CachedFrames(seq, tmp_path / "frames", key="k1")[0]
    later = CachedFrames(seq, tmp_path / "frames", key="k2", open_now=False)  # the pipeline's, before its checks
    assert json.loads((tmp_path / "frames" / "cache.json").read_text())["key"] == "k1" and later.path(0).exists()
    later[0]  # the first read opens it
    assert json.loads((tmp_path / "frames" / "cache.json").read_text())["key"] == "k2"
    fresh = CachedFrames(seq, tmp_path / "new", key="k", open_now=False)
    assert not (tmp_path / "new").exists()
    fresh.open()
    assert (tmp_path / "new" / "cache.json").is_file()


def test_a_folder_of_the_users_own_is_never_emptied(tmp_path, caplog):
    from gr_graph.datasets.base import DatasetError

    seq = CountingSequence()
    own = tmp_path / "frames"
    own.mkdir()
    (own / "000000.pcd").write_text("the user's scan")
    with pytest.raises(DatasetError, match=r"frames: the frame cache's folder holds 000000.pcd, not a cached frame"):
        CachedFrames(seq, own, key="k")
    assert (own / "000000.pcd").read_text() == "the user's scan"
    cache = CachedFrames(seq, tmp_path / "cache", key="k")
    cache[0]
    (tmp_path / "cache" / "notes.txt").write_text("added later")
    with caplog.at_level("WARNING"):
        cache.remove()
    assert (tmp_path / "cache" / "notes.txt").is_file() and "frame cache not removed" in caplog.text
    (tmp_path / "file").write_text("x")
    with pytest.raises(DatasetError, match="holds a file"):
        CachedFrames(seq, tmp_path / "file", key="k")


@pytest.mark.parametrize("damage", ["truncate", "other_position"])
def test_unreadable_file_is_made_again_and_counted(tmp_path, damage):
    seq = CountingSequence()
    cache = CachedFrames(seq, tmp_path / "frames", key="k")
    cache[0], cache[1]
    if damage == "truncate":
        data = cache.path(1).read_bytes()
        cache.path(1).write_bytes(data[: len(data) // 2])
    else:  # frame 0's file where frame 1's should be
        cache.path(1).write_bytes(cache.path(0).read_bytes())
    assert_same_frame(cache[1], seq.frames[1])
    assert cache.unreadable == 1 and seq.made[1] == 2
    assert_same_frame(cache[1], seq.frames[1])  # rewritten: read back now
    assert cache.unreadable == 1 and seq.made[1] == 2


def test_a_frame_that_cannot_be_stored_is_returned_and_counted(tmp_path, monkeypatch, caplog):
    seq = CountingSequence()
    cache = CachedFrames(seq, tmp_path / "frames", key="k")

    def full_disk(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cache, "_store", full_disk)
    with caplog.at_level("WARNING", logger="gr_graph.datasets.frame_cache"):
        assert_same_frame(cache[2], seq.frames[2])
        assert_same_frame(cache[2], seq.frames[2])
    assert cache.stats()["write_errors"] == 2 and seq.made[2] == 2 and not cache.path(2).exists()
    assert sum("not stored" in r.message for r in caplog.records) == 1  # warned once, then counted


def test_the_cache_leaves_room_for_the_results(tmp_path, monkeypatch, caplog):
    """Below DISK_RESERVE free, frames are no longer stored (said once, counted), still returned;
    with room again they are stored."""
    import collections

    import gr_graph.datasets.frame_cache as fc

    seq = CountingSequence()
    cache = CachedFrames(seq, tmp_path / "frames", key="k")
    free = {"bytes": fc.DISK_RESERVE - 1}
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(fc.shutil, "disk_usage", lambda path: usage(10 * fc.DISK_RESERVE, 0, free["bytes"]))
    with caplog.at_level("WARNING", logger="gr_graph.datasets.frame_cache"):
        assert_same_frame(cache[1], seq.frames[1])
        assert_same_frame(cache[2], seq.frames[2])
    assert not cache.path(1).exists() and not cache.path(2).exists()
    assert cache.stats()["not_stored_low_disk"] == 2 and cache.stats()["write_errors"] == 0
    assert sum("no longer stored" in r.message for r in caplog.records) == 1
    free["bytes"] = fc.DISK_RESERVE
    assert_same_frame(cache[1], seq.frames[1])
    assert cache.path(1).exists()


def test_remove_deletes_the_files_and_the_view_still_reads(tmp_path):
    seq = CountingSequence()
    cache = CachedFrames(seq, tmp_path / "frames", key="k")
    cache[0]
    cache.remove()
    assert not (tmp_path / "frames").exists()
    assert_same_frame(cache[0], seq.frames[0])


def test_synthetic_views_make_frames_and_release_through_the_cache(tmp_path):
    seq = SequenceView(SyntheticSequence(seed=0, preset="clean"), 740, 742)
    assert makes_frames(seq) and not makes_frames(CountingSequence())
    cache = CachedFrames(seq, tmp_path / "frames", key="k")
    made = cache[0]
    assert release_render_cache(cache)  # the town goes, the cached frame stays
    assert cache.path(0).is_file()
    assert_same_frame(cache[0], made)
    assert cache.hits == 1
    assert cache.motion_compensated == seq.motion_compensated


@pytest.mark.slow
def test_learning_run_with_the_cache_equals_the_run_without(tmp_path):
    """Round 0 fills the cache, round 1 reads every frame back; the results are identical to a
    run that makes every frame again and to one whose densified frames one thread reads
    (``data.read_threads``), and the cache is gone at the end."""
    from gr_graph.slam import main

    config = {"training": {"epochs": 1, "trainer": {
        "max_corr": 300, "lr": 3e-3, "num_threads": 1,
        "net": {"n_points": 512, "k0": 8, "k1": 8, "k2": 8, "c0": 16, "c1": 32, "c2": 32, "kw": 8}}},
        "output": {"plot": False}}
    runs = {}
    for name, data in (("cached", {}), ("uncached", {"frame_cache": False}), ("one_reader", {"read_threads": 1})):
        cfg = tmp_path / f"{name}.yaml"
        cfg.write_text(yaml.safe_dump({**config, "data": data}))
        out = tmp_path / name
        assert main(["--frames", "740:750", "--channels", "16", "--rounds", "1", "--synthetic-preset", "clean",
                     "--out", str(out), "--config", str(cfg), "--quiet"]) == 0
        runs[name] = out
    a, b = runs["cached"], runs["uncached"]
    stats = json.loads((a / "metrics.json").read_text())["frame_cache"]
    assert stats["misses"] == 10 and stats["hits"] >= 10 and stats["unreadable"] == stats["write_errors"] == 0
    assert "frame_cache" not in json.loads((b / "metrics.json").read_text())
    assert not (a / "frames").exists()
    for other in (b, runs["one_reader"]):  # the densified frames read by two threads (the default) or one
        for r in ("round_0", "round_1"):
            with np.load(a / r / "marginals.npz") as za, np.load(other / r / "marginals.npz") as zb:
                for key in ("poses", "covariance", "edge_information"):
                    np.testing.assert_array_equal(za[key], zb[key], err_msg=f"{other.name} {r}: {key}")
