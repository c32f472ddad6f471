"""Pieces of the frame loop: the loop-corrected estimate and the prefetching reader."""

from __future__ import annotations

import numpy as np
import pytest

from factors.se3 import exp_se3
from gr_graph.frame_loop import LoopCorrectedEstimate, prefetch_frames


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
    seq.concurrent_reads = False
    assert list(prefetch_frames(seq, ahead=4, threads=2)) == list(range(12))
    assert len(seq.threads) == 1
