"""Pieces of the frame loop: the loop-corrected estimate and the prefetching reader."""

from __future__ import annotations

import numpy as np
import pytest

from factors.se3 import exp_se3
from gr_graph.frame_loop import LoopCorrectedEstimate, frame_readers, prefetch_frames


def test_estimate_is_optimised_prefix_then_corrected_odometry():
    rng = np.random.default_rng(1)
    odom = [np.eye(4)]
    for _ in range(5):
        odom.append(odom[-1] @ exp_se3(rng.normal(0, 0.2, 6)))
    est = LoopCorrectedEstimate(odom)
    np.testing.assert_array_equal(est.poses(6), np.stack(odom))  # nothing optimised yet
    opt = np.stack(odom[:3]) @ exp_se3(np.array([0, 0, 0.1, 1.0, 0, 0]))  # the graph moved poses 0..2
    est.optimised = opt
    P = est.poses(6)
    np.testing.assert_array_equal(P[:3], opt)
    # later poses keep their odometry motion relative to the last optimised pose
    for i in range(3, 6):
        np.testing.assert_allclose(np.linalg.inv(P[2]) @ P[i], np.linalg.inv(odom[2]) @ odom[i], atol=1e-12)
        np.testing.assert_allclose(est.pose(i), P[i], atol=1e-12)
    np.testing.assert_array_equal(est.poses(2), opt[:2])


class _Numbers:
    def __init__(self, n: int, bad: int = -1) -> None:
        self.n, self.bad = n, bad

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> int:
        if i == self.bad:
            raise OSError(f"frame {i} unreadable")
        return i


@pytest.mark.parametrize("ahead", [0, 1, 4, 20])
def test_prefetch_yields_in_order_and_raises_in_order(ahead):
    assert list(prefetch_frames(_Numbers(7), ahead)) == list(range(7))
    got = []
    with pytest.raises(OSError, match="frame 3"):
        for x in prefetch_frames(_Numbers(7, bad=3), ahead):
            got.append(x)
    assert got == [0, 1, 2]


class _ThreadRecordingNumbers(_Numbers):
    """Numbers that record which thread made each one (and take a moment, so reads overlap)."""

    concurrent_reads = True

    def __init__(self, n: int, bad: int = -1) -> None:
        super().__init__(n, bad)
        self.threads: set[str] = set()

    def __getitem__(self, i: int) -> int:
        import threading
        import time

        self.threads.add(threading.current_thread().name)
        time.sleep(0.01)
        return super().__getitem__(i)


def test_concurrent_reads_use_the_threads_and_keep_the_order():
    seq = _ThreadRecordingNumbers(12)
    assert list(prefetch_frames(seq, ahead=1, threads=2)) == list(range(12))  # ahead is raised to the workers
    assert len(seq.threads) == 2 and all(t.startswith("gr_graph-read") for t in seq.threads)
    bad = _ThreadRecordingNumbers(12, bad=5)
    got = []
    with pytest.raises(OSError, match="frame 5"):
        for x in prefetch_frames(bad, ahead=4, threads=2):
            got.append(x)
    assert got == [0, 1, 2, 3, 4]


def test_sequences_that_do_not_say_so_are_read_by_one_thread():
    seq = _ThreadRecordingNumbers(12)
    assert (frame_readers(seq, 4, 2), frame_readers(seq, 0, 2)) == (2, 0)  # prefetch 0: the caller reads
    seq.concurrent_reads = False
    assert frame_readers(seq, 4, 2) == 1
    assert list(prefetch_frames(seq, ahead=4, threads=2)) == list(range(12))
    assert len(seq.threads) == 1


def _blas_threads() -> set[int]:
    from threadpoolctl import threadpool_info

    return {int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"}


@pytest.mark.slow
def test_several_readers_run_numpy_blas_on_one_thread_without_changing_results(monkeypatch):
    """While several threads read a round's frames, numpy's BLAS runs one thread in them and in
    the SLAM thread (``frame_loop.SLAM_BLAS_THREADS``) and its team is set back afterwards; the
    poses and marginal covariances are the ones a team of two gives, bit for bit. A sequence
    read by one thread (round 0's renderer) keeps the team."""
    from threadpoolctl import threadpool_limits

    from gr_graph.config import load_config
    from gr_graph.datasets.synthetic import SyntheticSequence
    from gr_graph.frame_loop import run_slam
    from slam_support import FrameSubset

    class Recording(FrameSubset):
        """Frames made once, then read back from any thread; records the BLAS team of every read."""

        def __init__(self, parent, indices: np.ndarray) -> None:
            super().__init__(parent, indices, "blas")
            self.frames = [super(Recording, self).__getitem__(i) for i in range(len(indices))]
            self.teams: set[int] = set()

        def __getitem__(self, i: int):
            self.teams.update(_blas_threads())
            return self.frames[i]

    seq = Recording(SyntheticSequence(seed=0, preset="clean"), np.arange(100, 115))
    cfg = load_config(overrides={"loops": {"enabled": False}, "output": {"progress": False},
                                 "data": {"read_threads": 2}})
    results = {}
    with threadpool_limits(2, user_api="blas"):
        assert _blas_threads() == {2}
        for concurrent, team in ((True, 1), (True, 2), (False, 1)):
            seq.concurrent_reads, seq.teams = concurrent, set()
            monkeypatch.setattr("gr_graph.frame_loop.SLAM_BLAS_THREADS", team)
            results[concurrent, team] = run_slam(seq, cfg)
            assert seq.teams == ({team} if concurrent else {2}) and _blas_threads() == {2}  # the caller's team is back
    for other in ((True, 2), (False, 1)):
        np.testing.assert_array_equal(results[True, 1].poses, results[other].poses)
        np.testing.assert_array_equal(results[True, 1].covariances, results[other].covariances)
