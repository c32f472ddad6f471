"""The synthetic sequence rendered in a separate process (gr_graph.datasets.synthetic.render_process)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from gr_graph.datasets.base import DatasetError, LidarFrame, release_render_cache
from gr_graph.datasets.synthetic import SyntheticSequence
from gr_graph.datasets.synthetic.actors import ActorsConfig
from gr_graph.datasets.synthetic.render_process import RenderProcessSequence
from loader_support import assert_same_frame


class NumberedFrames:
    """A small picklable sequence: frame i holds i + 1 points; ``broken`` frames raise DatasetError."""

    def __init__(self, n: int = 12, broken: tuple[int, ...] = ()) -> None:
        self.name = "numbered"
        self.timestamps = 0.1 * np.arange(n)
        self.gt_poses = None
        self.T_cam_velo = np.eye(4)
        self.broken = broken
        self.released = 0

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> LidarFrame:
        if i in self.broken:
            raise DatasetError(f"{self.name}: frame {i} is broken")
        points = np.random.default_rng(i).normal(size=(i + 1, 3))
        return LidarFrame(index=i, timestamp=float(self.timestamps[i]), points=points,
                          intensity=np.full(i + 1, 0.5, np.float32))

    def release_cache(self) -> bool:
        self.released += 1
        return True


def test_the_synthetic_worlds_frames_from_the_render_process_are_bit_identical():
    # the clean town with moving actors: the actors are rebuilt in the child from their configuration
    seq = SyntheticSequence(seed=2, n_rings=16, preset="clean", actors=ActorsConfig())
    wrapped = RenderProcessSequence(seq, ahead=2)
    assert (wrapped.name, len(wrapped), wrapped.n_rings) == (seq.name, len(seq), 16)  # delegated
    order = [200, 201, 202, 203, 40]  # consecutive (rendered ahead), then a jump back
    got = [wrapped[i] for i in order]
    assert wrapped.stats()["frames_from_process"] == len(order) and wrapped.fallback is None
    assert seq._actors is None  # the actors were built in the child only
    for i, frame in zip(order, got):
        assert_same_frame(frame, seq[i])
    assert release_render_cache(wrapped) is True  # stops the child
    assert wrapped._process is None and wrapped.child_peak_rss_mb > 0
    assert_same_frame(wrapped[41], seq[41])  # a read after the release starts another child
    assert wrapped.stats()["frames_from_process"] == len(order) + 1
    wrapped.release_cache()


def test_errors_keep_their_type_and_the_child_serves_on():
    wrapped = RenderProcessSequence(NumberedFrames(broken=(3,)))
    assert len(wrapped[2]) == 3
    with pytest.raises(DatasetError, match="frame 3 is broken"):
        wrapped[3]
    with pytest.raises(IndexError, match="out of range"):
        wrapped[12]
    assert len(wrapped[4]) == 5 and wrapped.fallback is None
    assert wrapped.stats()["frames_from_process"] == 2
    wrapped.release_cache()


def test_a_child_that_dies_leaves_the_frames_to_this_process(caplog):
    wrapped = RenderProcessSequence(NumberedFrames())
    assert len(wrapped[0]) == 1
    wrapped._process.kill()  # e.g. the kernel's out-of-memory killer
    wrapped._process.join()
    with caplog.at_level(logging.WARNING):
        frame = wrapped[1]
    assert_same_frame(frame, NumberedFrames()[1])
    assert "exit code -9" in wrapped.fallback and "rendering in this process" in caplog.text
    assert wrapped.stats()["frames_in_this_process"] == 1 and wrapped.stats()["frames_from_process"] == 1
    assert_same_frame(wrapped[5], NumberedFrames()[5])  # no new child after a fallback
    assert wrapped._process is None


def test_a_sequence_that_cannot_be_pickled_is_rendered_here(caplog):
    seq = NumberedFrames()
    seq.transform = lambda f: f  # lambdas do not pickle
    wrapped = RenderProcessSequence(seq)
    with caplog.at_level(logging.WARNING):
        assert_same_frame(wrapped[7], NumberedFrames()[7])
    assert "cannot be sent to a render process" in wrapped.fallback and wrapped._process is None
    assert wrapped.stats()["frames_in_this_process"] == 1


def test_open_sequence_renders_in_a_process_for_long_reads(monkeypatch, tmp_path):
    from gr_graph.config import load_config
    from gr_graph.datasets.registry import KITTI_ROOT_ENV, RENDER_PROCESS_MIN_FRAMES, open_configured_sequence
    from gr_graph.pipeline import round_fingerprint

    monkeypatch.delenv(KITTI_ROOT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)

    def chain(view) -> list[type]:
        kinds = []
        while view is not None:
            kinds.append(type(view))
            view = view.__dict__.get("parent", view.__dict__.get("_sequence"))
        return kinds

    def opened(frames: list[int], **data):
        cfg = load_config(overrides={"data": {"frames": frames, "channels": 16, "synthetic_preset": "clean", **data}})
        return open_configured_sequence(cfg.data, sensor=cfg.sensor)[0], cfg

    long_read, _ = opened([0, RENDER_PROCESS_MIN_FRAMES], kitti_vertical_correction_deg=0.22)
    assert RenderProcessSequence in chain(long_read)  # under the vertical-angle correction's view too
    assert RenderProcessSequence not in chain(opened([0, RENDER_PROCESS_MIN_FRAMES - 1])[0])
    assert RenderProcessSequence not in chain(opened([0, 4000], render_process=False)[0])
    short, _ = opened([10, 13], render_process=True)
    assert RenderProcessSequence in chain(short)
    plain, _ = opened([10, 13], render_process=False)
    for k in range(3):
        assert_same_frame(short[k], plain[k])
    assert release_render_cache(short) is True
    # how frames are made is not what they are: no round's fingerprint changes
    base = load_config(overrides={"data": {"channels": 16}})
    for r in (0, 1):
        assert round_fingerprint(base, r) == round_fingerprint(
            load_config(overrides={"data": {"channels": 16, "render_process": True}}), r)


@pytest.mark.frees_render_cache  # the pipeline stops the child after the round: its peak is read then
def test_a_slam_run_with_the_render_process_equals_the_run_without(tmp_path):
    import json

    import yaml

    from gr_graph.slam import main

    runs = {}
    for name, on in (("process", True), ("here", False)):
        cfg = tmp_path / f"{name}.yaml"
        cfg.write_text(yaml.safe_dump({"data": {"render_process": on}, "output": {"plot": False}}))
        out = tmp_path / name
        assert main(["--frames", "740:760", "--channels", "16", "--rounds", "0", "--synthetic-preset", "clean",
                     "--out", str(out), "--config", str(cfg), "--quiet"]) == 0
        runs[name] = out
    stats = json.loads((runs["process"] / "metrics.json").read_text())["render_process"]
    assert stats["frames_from_process"] == 20 and stats["frames_in_this_process"] == 0 and stats["fallback"] is None
    assert stats["child_peak_rss_mb"] > 0
    assert "render_process" not in json.loads((runs["here"] / "metrics.json").read_text())
    with np.load(runs["process"] / "round_0" / "marginals.npz") as za, np.load(runs["here"] / "round_0" / "marginals.npz") as zb:
        for key in ("poses", "covariance", "edge_information"):
            np.testing.assert_array_equal(za[key], zb[key], err_msg=key)
