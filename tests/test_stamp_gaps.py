"""Frame stamps displaced off the sensor's beat (gr_graph.datasets.stamp_gaps): found, moved back
for the motion model, and a run with one such stamp against the same run with regular stamps."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from gr_graph.datasets.stamp_gaps import MotionTimes, motion_times


def _ms(t) -> np.ndarray:
    return np.asarray(t, np.float64) / 1000.0


TAIL = [700, 800, 900, 1000, 1100]  # regular frames after the first seven


@pytest.mark.parametrize("stamps, moved, on_beat", [
    ([0, 100, 102, 300, 400, 500, 600] + TAIL, 2, 200),   # 2 ms after its predecessor (received early)
    ([0, 100, 298, 300, 400, 500, 600] + TAIL, 2, 200),   # 98 ms late, 2 ms before its successor
    ([0, 2, 200, 300, 400, 500, 600] + TAIL, 1, 100),     # the second frame
    ([-500, -400, -300, -200, -100, 0, 100, 200, 300, 400, 500, 502], 11, 600),  # the last frame
    ([0, 100, 200, 300, 400, 460, 600] + TAIL, 5, 500),   # 40 ms early
    ([0, 100, 200, 260, 500, 600, 700, 800, 900, 1000, 1100], 3, 300),  # 40 ms early before two dropped frames
])
def test_one_displaced_stamp_goes_back_on_the_beat(stamps, moved, on_beat, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="gr_graph.datasets.stamp_gaps"):
        out = motion_times(_ms(stamps), "bag.mcap")
    expected = _ms(stamps)
    expected[moved] = on_beat / 1000.0
    np.testing.assert_allclose(out.times, expected, rtol=0, atol=1e-12)
    assert out.moved == [moved] and out.unresolved == [] and out.period == pytest.approx(0.1)
    assert "bag.mcap: 1 frame stamp off the sensor's 0.1 s beat" in caplog.text
    assert out.summary()["n_moved"] == 1


@pytest.mark.parametrize("stamps", [
    [0, 100, 200, 300, 400, 500, 600] + TAIL,   # regular
    [0, 100, 200, 500, 600, 700, 800] + TAIL,   # two frames dropped
    [0, 103, 201, 302, 399, 503, 600, 701],     # jitter of a few ms
    [0, 100, 200, 300],                         # too few gaps to judge a beat
])
def test_stamps_on_the_beat_are_kept_as_they_are(stamps, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="gr_graph.datasets.stamp_gaps"):
        out = motion_times(_ms(stamps))
    np.testing.assert_array_equal(out.times, _ms(stamps))
    assert out.moved == [] and out.unresolved == [] and caplog.text == ""


def test_sequences_without_a_beat_and_unexplained_gaps_are_left_alone() -> None:
    irregular = np.cumsum(np.random.default_rng(0).uniform(0.05, 0.15, 30))  # frames cut at irregular times
    out = motion_times(irregular)
    assert out.period is None and out.moved == []
    np.testing.assert_array_equal(out.times, irregular)
    # every stamp from frame 3 on 42 ms later (a driver restarted): no moved stamp explains it
    stamps = _ms([0, 100, 200, 342, 442, 542, 642, 742, 842, 942, 1042, 1142])
    out = motion_times(stamps)
    assert out.moved == [] and out.unresolved == [3]
    np.testing.assert_array_equal(out.times, stamps)


def test_a_burst_of_stamps_delivered_together_is_spread_back_over_the_beat() -> None:
    """After a stall, queued sweeps arrive together: frames 4 and 5 stamped 1 ms before frame 6."""
    out = motion_times(_ms([0, 100, 200, 300, 598, 599, 600] + TAIL))
    np.testing.assert_allclose(out.times, _ms([0, 100, 200, 300, 400, 500, 600] + TAIL), rtol=0, atol=1e-12)
    assert out.moved == [4, 5] and out.unresolved == []
    # more frames than the time between their neighbours holds: nothing explains it, nothing moves
    crowded = _ms([0, 100, 200, 298, 299, 300, 400, 500, 600, 700, 800, 900])
    out = motion_times(crowded)
    assert out.moved == [] and out.unresolved == [4, 5]
    np.testing.assert_array_equal(out.times, crowded)


def test_a_topic_throttled_to_every_other_sweep_keeps_its_true_stamps() -> None:
    """Gaps of mostly 0.2 s with some 0.1 and 0.3 s are whole sweeps of a 10 Hz sensor, not stamps
    displaced off a 0.2 s beat."""
    stamps = _ms([0, 200, 300, 600, 800, 1000, 1200, 1300, 1600, 1800, 2000, 2200])
    out = motion_times(stamps)
    assert out.period == pytest.approx(0.1) and out.moved == [] and out.unresolved == []
    np.testing.assert_array_equal(out.times, stamps)


def test_the_input_is_not_modified() -> None:
    stamps = _ms([0, 100, 102, 300, 400, 500, 600])
    keep = stamps.copy()
    motion_times(stamps)
    np.testing.assert_array_equal(stamps, keep)


@pytest.mark.slow
def test_a_run_with_one_displaced_stamp_matches_the_run_with_regular_stamps(monkeypatch) -> None:
    """30 raw (motion-distorted) synthetic sweeps at ~12.7 m/s, deskewed: frame 12 stamped 2 ms after
    frame 11 gives the regular stamps' trajectory; with the stamps used as they are (the code before
    stamp_gaps), the odometry's guess and the deskewing scale by the displaced gaps and the
    trajectory drifts."""
    from gr_graph.config import load_config
    from gr_graph.datasets.distortion import MotionDistortedSequence
    from gr_graph.datasets.registry import open_sequence
    from gr_graph.frame_loop import run_slam
    from gr_graph.metrics import ate
    from tests.test_deskew_odometry import _Cached

    seq, _ = open_sequence("00", frames=(4200, 4230), synthetic_preset="clean", channels=16)
    regular = _Cached(MotionDistortedSequence(_Cached(seq), scan_period=0.1))
    displaced = _Cached(regular)
    displaced.timestamps = regular.timestamps.copy()
    displaced.timestamps[12] = displaced.timestamps[11] + 0.002
    cfg = load_config(overrides={"loops": {"enabled": False}, "graph": {"marginals": False},
                                 "output": {"progress": False}})
    gt = np.linalg.inv(regular.gt_poses[0]) @ regular.gt_poses

    def error(s) -> tuple[float, dict]:
        res = run_slam(s, cfg)
        return ate(res.odometry_poses, gt).rmse, res.info["stamp_gaps"]

    ate_regular, gaps_regular = error(regular)
    ate_fixed, gaps_fixed = error(displaced)
    monkeypatch.setattr("gr_graph.frame_loop.motion_times", lambda stamps, source: MotionTimes(
        np.asarray(stamps, np.float64), None))
    ate_as_stamped, _ = error(displaced)
    assert gaps_regular["n_moved"] == 0 and gaps_fixed["moved"] == [12]
    assert ate_fixed < 1.5 * ate_regular + 0.005
    assert ate_as_stamped > 5 * ate_regular + 0.05
