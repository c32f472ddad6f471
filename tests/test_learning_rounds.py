"""Learning rounds: densified scans S+_k (Algorithm 2) and ``--rounds 1`` end to end (Algorithm 3)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from gr_graph.config import PreprocessConfig, TrainingConfig
from gr_graph.datasets.base import LidarFrame
from gr_graph.densify import densified_sequence
from gr_graph.preprocess import preprocess_scan

from slam_support import LEARNING_RUN_CONFIG

GROUND_Z = -1.73
# a tilted planar covariance with correlations: eigenvalues 0.09, 0.04, 4e-4 -> a = 0.9956
_R = np.array([[np.cos(0.4), -np.sin(0.4), 0.0], [np.sin(0.4), np.cos(0.4), 0.0], [0.0, 0.0, 1.0]])
C_PLANE = _R @ np.diag([0.09, 0.04, 4e-4]) @ _R.T
C_ISO = 0.01 * np.eye(3)  # a = 0


class PlaneScenes:
    """A tiny LidarSequence: a noisy ground plane (known) plus isotropic clutter, per frame."""

    def __init__(self, n: int = 4, clutter_only: tuple[int, ...] = (), tiny: tuple[int, ...] = ()) -> None:
        self.n = n
        self.clutter_only = clutter_only
        self.tiny = tiny
        self.name = "planes"
        self.timestamps = np.arange(n) * 0.1
        self.gt_poses = np.stack([np.eye(4)] * n)
        self.T_cam_velo = np.eye(4)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> LidarFrame:
        rng = np.random.default_rng(100 + i)
        if i in self.tiny:
            pts = rng.uniform(5, 6, (10, 3))
        else:
            xy = rng.uniform(-25, 25, (20000, 2))
            xy = xy[np.linalg.norm(xy, axis=1) > 4.0]
            ground = np.column_stack([xy, GROUND_Z + rng.normal(0, 0.01, len(xy))])
            clutter = rng.uniform([-20, -20, 0.5], [20, 20, 6.0], (6000, 3))
            pts = clutter if i in self.clutter_only else np.vstack([ground, clutter])
        return LidarFrame(index=i, timestamp=0.1 * i, points=pts, intensity=np.abs(pts[:, 2]).astype(np.float32),
                          n_rings=16)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]


def plane_predictor(points: np.ndarray) -> np.ndarray:
    """Stand-in for f_theta: planar covariance on the ground, isotropic elsewhere."""
    on_ground = np.abs(points[:, 2] - GROUND_Z) < 0.1
    return np.where(on_ground[:, None, None], C_PLANE, C_ISO)


PRE = PreprocessConfig()


def _cfg(**kw) -> TrainingConfig:
    """The paper's densification (samples replace the anisotropic points, the rest dropped) unless ``kw`` says
    otherwise; the default keeps every point (``keep_original``, ``keep_dropped``)."""
    return TrainingConfig(**{"tau_ani": 0.9, "samples_per_point": 8, "seed": 3, "keep_original": False,
                             "keep_dropped": False, **kw})


def test_view_metadata_and_lazy():
    seq = PlaneScenes()
    view = densified_sequence(seq, plane_predictor, _cfg(), preprocess=PRE)
    assert len(view) == len(seq)
    np.testing.assert_array_equal(view.timestamps, seq.timestamps)
    np.testing.assert_array_equal(view.gt_poses, seq.gt_poses)
    np.testing.assert_array_equal(view.T_cam_velo, seq.T_cam_velo)
    assert view.stats()["frames"] == 0  # nothing computed before a frame is read


def test_stats_count_the_horizontal_share_of_kept_points():
    from gr_graph.densify import horizontal_surfaces

    # a wall (normal along x), a floor tilted 20 deg and one tilted 40 deg, an isotropic blob (no normal)
    def tilted(deg):
        c, s_ = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        R = np.array([[c, 0.0, s_], [0.0, 1.0, 0.0], [-s_, 0.0, c]])
        return R @ np.diag([0.09, 0.04, 4e-4]) @ R.T

    wall = np.diag([4e-4, 0.09, 0.04])
    assert horizontal_surfaces(np.stack([wall, tilted(20), tilted(40), C_ISO, C_PLANE])).tolist() == [
        False, True, False, False, True]
    from gr_graph.densify import HORIZONTAL, NO_NORMAL, OBLIQUE, VERTICAL, surface_orientation

    # the normal tilted 20 / 40 / 70 / 85 deg from z: horizontal, oblique, vertical (within 30 deg of the x-y plane)
    assert surface_orientation(np.stack([wall, tilted(20), tilted(40), tilted(70), tilted(85), C_ISO,
                                         np.diag([0.05, 0.04, 0.03])])).tolist() == [
        VERTICAL, HORIZONTAL, OBLIQUE, VERTICAL, VERTICAL, NO_NORMAL, NO_NORMAL]
    def ground_and_walls(points):  # the plane predictor, plus a wall covariance on clutter above 3 m
        return np.where((points[:, 2] > 3.0)[:, None, None], wall, plane_predictor(points))

    seq = PlaneScenes(n=3)
    view = densified_sequence(seq, ground_and_walls, _cfg(), preprocess=PRE)
    on_plane = high = n_pre = 0
    for i in range(3):
        view[i]
        s = preprocess_scan(seq[i].points, PRE, index=i).points
        on_plane += int((np.abs(s[:, 2] - GROUND_Z) < 0.1).sum())
        high += int((s[:, 2] > 3.0).sum())
        n_pre += len(s)
    st = view.stats()
    assert st["kept_fraction"] == pytest.approx((on_plane + high) / n_pre)  # ground and walls are kept
    assert st["horizontal_fraction_kept"] == pytest.approx(on_plane / (on_plane + high))
    assert st["horizontal_fraction_input"] == pytest.approx(on_plane / n_pre)
    assert 0.0 < st["horizontal_fraction_kept"] < 1.0


def test_kept_points_are_the_anisotropic_ones_and_samples_follow_C():
    M = 64
    seq = PlaneScenes()
    view = densified_sequence(seq, plane_predictor, _cfg(samples_per_point=M), preprocess=PRE)
    f = view[1]
    # independent reference: SLAM's preprocessing of the raw frame, and which points are on the plane
    s = preprocess_scan(seq[1].points, PRE, index=1).points
    on_plane = np.abs(s[:, 2] - GROUND_Z) < 0.1
    assert 100 < on_plane.sum() < len(s)  # both kinds are present
    assert len(f.points) == on_plane.sum() * M and f.ring is None
    # samples are grouped by source point: residuals from their own source point ~ N(0, C_PLANE)
    d = f.points.reshape(-1, M, 3) - s[on_plane][:, None, :]
    d = d.reshape(-1, 3)
    n = len(d)
    np.testing.assert_allclose(d.mean(0), 0.0, atol=4 * np.sqrt(np.diag(C_PLANE) / n).max())
    emp = np.cov(d.T)
    sd = np.sqrt(np.outer(np.diag(C_PLANE), np.diag(C_PLANE)))
    assert np.all(np.abs(emp - C_PLANE) < 5 * sd * np.sqrt(2.0 / n) + 1e-12), (emp, C_PLANE)
    # the thin axis of C is vertical: samples stay within ~5 sigma (0.1 m) of the plane; no clutter survives
    assert np.abs(f.points[:, 2] - GROUND_Z).max() < 0.02 + 5 * 0.02
    # intensity is inherited from the nearest raw point (= |z| of that point, ~1.73 on the ground)
    assert f.intensity.shape == (len(f.points),)
    np.testing.assert_allclose(f.intensity, -GROUND_Z, atol=0.05)
    st = view.stats()
    assert st["frames"] == 1 and st["fallbacks"] == {}
    assert st["mean_kept_points"] == on_plane.sum() and st["mean_output_points"] == on_plane.sum() * M


def test_keep_original_prepends_kept_points():
    seq = PlaneScenes()
    f = densified_sequence(seq, plane_predictor, _cfg(keep_original=True, samples_per_point=2), preprocess=PRE)[0]
    s = preprocess_scan(seq[0].points, PRE, index=0).points
    kept = s[np.abs(s[:, 2] - GROUND_Z) < 0.1]
    assert len(f.points) == 3 * len(kept)
    np.testing.assert_allclose(f.points[: len(kept)], kept)

def test_keep_dropped_appends_the_filtered_out_points_unchanged():
    """``keep_dropped``: the clutter the filter drops comes back unchanged after the samples;
    with ``keep_original`` too the scan holds every preprocessed point plus the samples."""
    seq = PlaneScenes()
    s = preprocess_scan(seq[0].points, PRE, index=0).points
    on_plane = np.abs(s[:, 2] - GROUND_Z) < 0.1
    M = 2
    f = densified_sequence(seq, plane_predictor, _cfg(keep_dropped=True, samples_per_point=M), preprocess=PRE)[0]
    n_samples = M * on_plane.sum()
    assert len(f.points) == n_samples + (~on_plane).sum()
    np.testing.assert_allclose(f.points[n_samples:], s[~on_plane])  # the dropped points, in scan order
    plain = densified_sequence(seq, plane_predictor, _cfg(samples_per_point=M), preprocess=PRE)[0]
    np.testing.assert_array_equal(f.points[:n_samples], plain.points)  # the same samples as without the option
    # intensity of the returned points is their own raw point's (|z| > 0.5 for the clutter)
    assert (f.intensity[n_samples:] > 0.4).all()

    both = densified_sequence(seq, plane_predictor, _cfg(keep_dropped=True, keep_original=True, samples_per_point=M),
                              preprocess=PRE)[0]
    assert len(both.points) == len(s) + n_samples
    every_point = np.vstack([both.points[: on_plane.sum()], both.points[on_plane.sum() + n_samples:]])
    np.testing.assert_allclose(np.sort(every_point, axis=0), np.sort(s, axis=0))



def test_deterministic_per_seed_and_frame():
    seq = PlaneScenes()
    a = densified_sequence(seq, plane_predictor, _cfg(), preprocess=PRE)
    b = densified_sequence(seq, plane_predictor, _cfg(), preprocess=PRE)
    f2 = a[2].points
    _ = b[3]  # reading order does not matter
    np.testing.assert_array_equal(b[2].points, f2)
    np.testing.assert_array_equal(a[2].points, f2)
    c = densified_sequence(seq, plane_predictor, _cfg(seed=4), preprocess=PRE)
    assert c[2].points.shape == f2.shape and not np.allclose(c[2].points, f2)
    assert not np.allclose(a[1].points[: 100], a[2].points[: 100])  # frames get different streams


class _OneReadAtATime(PlaneScenes):
    """PlaneScenes that fails if two of its frames are ever read at the same time (the view must
    read its parent under its lock)."""

    def __init__(self, n: int) -> None:
        super().__init__(n=n)
        self.reading = 0

    def __getitem__(self, i: int) -> LidarFrame:
        import time

        self.reading += 1
        try:
            assert self.reading == 1, "two parent reads overlapped"
            time.sleep(0.002)
            return super().__getitem__(i)
        finally:
            self.reading -= 1


def test_frames_read_by_two_threads_equal_frames_read_in_order():
    """The SLAM reader's ``data.read_threads``: a real network (random weights) and the
    sampling give every frame bit for bit whatever thread reads it, in whatever order, while the
    calling thread recomputes an evicted frame's covariances (as the learned edge noise does)."""
    import torch

    from gr_graph.frame_loop import prefetch_frames
    from training.config import NetConfig
    from training.network import CovarianceNet

    torch.manual_seed(0)
    net = CovarianceNet(NetConfig(n_points=512, k0=8, k1=8, k2=8, c0=16, c1=32, c2=32, kw=8))
    seq = _OneReadAtATime(n=6)
    serial = densified_sequence(seq, net, _cfg(), preprocess=PRE)
    expected = {i: serial[i] for i in reversed(range(len(seq)))}  # read last to first
    assert serial.stats()["fallbacks"] == {} and serial.stats()["mean_kept_points"] > 0  # frames were sampled
    view = densified_sequence(seq, net, _cfg(), preprocess=PRE, keep_predictions=1)
    assert view.concurrent_reads
    got = []
    for frame in prefetch_frames(view, ahead=4, threads=2):
        got.append(frame)
        if frame.index >= 2:  # frame 0 is no longer kept: predicted again beside the readers
            np.testing.assert_array_equal(view.prediction(0)[1], serial.predicted(0)[1])
    assert [f.index for f in got] == list(range(len(seq)))
    for f in got:
        np.testing.assert_array_equal(f.points, expected[f.index].points)
        np.testing.assert_array_equal(f.intensity, expected[f.index].intensity)
    assert view.stats() == serial.stats() and view.n_recomputed >= 4 and view.recomputed_failures == 0


def test_fallbacks_are_counted():
    seq = PlaneScenes(n=5, clutter_only=(2,), tiny=(4,))
    state = {"nan": False}

    def predictor(points):
        C = plane_predictor(points)
        if state["nan"]:
            C[0] = np.nan
        return C

    view = densified_sequence(seq, predictor, _cfg(), preprocess=PRE)
    for i in range(5):
        state["nan"] = i == 3
        f = view[i]
        raw = seq[i]
        if i == 2:  # only isotropic clutter: nothing kept -> the unfiltered preprocessed points
            np.testing.assert_allclose(f.points, preprocess_scan(raw.points, PRE, index=2).points)
        elif i in (3, 4):  # non-finite covariances / unusable scan -> the raw frame
            np.testing.assert_array_equal(f.points, raw.points)
        else:
            assert len(f.points) % 8 == 0 and np.abs(f.points[:, 2] - GROUND_Z).max() < 0.2
    st = view.stats()
    assert view.fallbacks == {2: "few_kept", 3: "nonfinite_covariance", 4: "unusable_scan"}
    assert st["fallbacks"] == {"few_kept": 1, "nonfinite_covariance": 1, "unusable_scan": 1}
    state["nan"] = False
    _ = view[2]  # re-reading a frame does not count it twice
    assert view.stats()["fallbacks"]["few_kept"] == 1


def test_few_kept_points_need_no_fallback_when_every_point_is_kept():
    """With ``keep_original`` and ``keep_dropped`` (the defaults) a frame where nothing passes the filter
    keeps all its preprocessed points: no ``few_kept`` fallback, and a frame with a plane gains samples."""
    seq = PlaneScenes(n=2, clutter_only=(1,))
    adds = _cfg(keep_original=True, keep_dropped=True)
    view = densified_sequence(seq, plane_predictor, adds, preprocess=PRE)
    for i in range(2):
        s = preprocess_scan(seq[i].points, PRE, index=i).points
        f = view[i]
        on_ground = np.abs(s[:, 2] - GROUND_Z) < 0.1  # the planar points: the ones the filter keeps
        n_kept, n_dropped = int(on_ground.sum()), int((~on_ground).sum())
        assert len(f.points) == len(s) + adds.samples_per_point * n_kept  # every point, plus M samples per kept one
        np.testing.assert_array_equal(f.points[:n_kept], s[on_ground])  # the kept points first
        np.testing.assert_array_equal(f.points[len(f.points) - n_dropped:], s[~on_ground])  # the dropped ones last
    assert view.fallbacks == {} and view.stats()["fallbacks"] == {}
    paper = densified_sequence(seq, plane_predictor, _cfg(), preprocess=PRE)
    _ = paper[1]
    assert paper.fallbacks == {1: "few_kept"}  # the paper's densification would leave no points: fallback


def test_real_network_checkpoint_is_accepted(tmp_path):
    """A trainer model.pt path goes through training.predict (same points -> same C -> same frame)."""
    import torch

    from training.network import CovarianceNet, NetConfig
    from training.predict import predict_covariances
    from training.trainer import save_atomic

    torch.manual_seed(0)
    net = CovarianceNet(NetConfig(n_points=512, k0=8, k1=8, k2=8, c0=16, c1=16, c2=16, kw=8))
    path = tmp_path / "model.pt"
    save_atomic({"model_state": net.state_dict(), "net_config": net.config.to_dict()}, path)
    seq = PlaneScenes(n=1)
    cfg = _cfg(tau_ani=0.0, samples_per_point=1, min_kept_points=1)
    f = densified_sequence(seq, path, cfg, preprocess=PRE)[0]
    s = preprocess_scan(seq[0].points, PRE, index=0).points
    C = predict_covariances(net, s, seed=cfg.seed)
    from training.densify import densify

    ref, kept = densify(s, C, 0.0, 1, seed=[cfg.seed, 0])
    np.testing.assert_allclose(f.points, ref, atol=1e-9)


def test_trainer_keys_checked_before_round_zero(tmp_path):
    """The trainer section is validated when the configuration is loaded, before any round."""
    from gr_graph.config import load_config

    with pytest.raises(ValueError, match="set by the pipeline"):
        TrainingConfig(trainer={"epochs": 3})
    with pytest.raises(ValueError, match="unknown key 'training.trainer.lrr'"):
        load_config(overrides={"output": {"out_dir": str(tmp_path)}, "training": {"rounds": 1, "trainer": {"lrr": 1}}})
    cfg = load_config(overrides={"training": {"rounds": 1, "trainer": {"lr": 2e-3, "net": {"n_points": 256}}}})
    tc = cfg.training.trainer_config("cpu", progress=False)
    assert (tc.lr, tc.net.n_points, tc.epochs, tc.seed) == (2e-3, 256, cfg.training.epochs, cfg.training.seed)
    with pytest.raises(ValueError, match="lr"):
        cfg.training.trainer.lr = -1.0  # validated on assignment too


# ----------------------------------------------------------------------------- end to end

# Bounds for the shared run (session fixture learning_run, tests/conftest.py); a densified
# scan that lost its walls (only ground kept) drifts by metres, far above these.
RPE10_BOUND_M = 0.1  # translation error over 10 frames (~8 m driven)
ATE_BOUND_M = 0.1


@pytest.mark.slow
def test_rounds_end_to_end(learning_run):
    out, _ = learning_run
    for r in (0, 1):
        for name in ("poses_kitti.txt", "poses_tum.txt", "marginals.npz", "round.json", "memory"):
            assert (out / f"round_{r}" / name).exists(), (r, name)
    assert (out / "round_1" / "training" / "model.pt").is_file()
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["rounds"]) == {"0", "1"}
    from gr_graph.metrics import rpe_translation
    from gr_graph.trajectory import read_kitti_poses

    gt = read_kitti_poses(out / "gt_poses_kitti.txt")
    for r in ("0", "1"):
        s = m["rounds"][r]["slam"]
        assert s["ate_rmse"] is not None and np.isfinite(s["ate_rmse"])
        assert s["ate_rmse"] < ATE_BOUND_M, (r, s["ate_rmse"])
        # RPE over 300 frames needs a longer run (None here); RPE over 10 frames from the written poses
        rpe = rpe_translation(read_kitti_poses(out / f"round_{r}" / "poses_kitti.txt"), gt, delta=10)
        assert np.isfinite(rpe.rmse) and rpe.rmse < RPE10_BOUND_M, (r, rpe.rmse)
    r1 = m["rounds"]["1"]
    assert np.isfinite(r1["trajectory_change"]) and r1["trajectory_change"] < ATE_BOUND_M
    assert r1["densify"]["frames"] == 30 and r1["runtime_s"]["training"] > 0
    assert r1["map"]["scans"].startswith("densified") and m["rounds"]["0"]["map"]["scans"] == "measured"
    assert r1["densify"]["mean_output_points"] > 0
    # no frame or training pair met non-finite / indefinite network covariances (issue 10: < 0.1 %)
    cf = r1["covariance_failures"]
    assert cf["frames"] == 30 and cf["frames_nonfinite"] == 0 and cf["frames_non_pd"] == 0
    assert cf["training_pairs"] == 29 * 4 and cf["training_pairs_skipped"] == 0
    assert cf["edges_without_covariances"] == {"odometry": 0, "loop": 0}
    # the memory of round 1 stores the raw downsampled scans of round 0 with round 1's trajectory
    from gr_graph.memory import load_memory

    m0, m1 = load_memory(out / "round_0" / "memory"), load_memory(out / "round_1" / "memory")
    for k in (0, 15, 29):
        np.testing.assert_array_equal(np.asarray(m1.scan(k)), np.asarray(m0.scan(k)))
    with np.load(out / "round_1" / "marginals.npz") as z:
        np.testing.assert_allclose(m1.poses, z["poses"], atol=1e-6)


@pytest.mark.slow
def test_rounds_resume_skips_finished(learning_run, caplog):
    import logging

    from gr_graph.slam import main

    out, argv = learning_run
    stamp = {p: p.stat().st_mtime_ns for p in (out / "round_0" / "round.json", out / "round_1" / "round.json",
                                              out / "round_1" / "training" / "model.pt")}
    with caplog.at_level(logging.INFO):
        assert main(argv) == 0
    assert "round 0: already finished" in caplog.text and "round 1: already finished" in caplog.text
    assert {p: p.stat().st_mtime_ns for p in stamp} == stamp
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["rounds"]) == {"0", "1"} and "trajectory_change" in m["rounds"]["1"]


def test_a_convergence_stop_is_recorded(learning_run, tmp_path):
    """Rounds that stop because the trajectory moved less than training.convergence_delta say so in
    metrics.json (``stopped``), as a rejection does (the run's rounds resume: nothing is trained)."""
    import shutil

    from gr_graph.config import load_config
    from gr_graph.pipeline import SlamPipeline

    out, _ = learning_run
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    cfg = load_config(copy / "config.yaml", {"output": {"out_dir": str(copy)}, "training": {"convergence_delta": 1e6}})
    metrics = SlamPipeline(cfg).run()
    assert metrics["stopped"].startswith("round 1 converged: the trajectory moved ")
    assert "training.convergence_delta 1e+06 m" in metrics["stopped"]
    assert json.loads((copy / "metrics.json").read_text())["stopped"] == metrics["stopped"]
    cfg = load_config(copy / "config.yaml", {"output": {"out_dir": str(copy)}, "training": {"convergence_delta": 0.0}})
    assert "converged" not in SlamPipeline(cfg).run().get("stopped", "")  # a delta of 0 never stops the rounds


@pytest.mark.slow
def test_unfinished_round_resumes_its_training(learning_run, caplog):
    """Round 1 interrupted after training (no round.json): the rerun skips round 0, resumes the
    finished training from its checkpoint (no new training steps) and redoes round 1's SLAM."""
    import logging

    from gr_graph.slam import main

    out, argv = learning_run
    log_path = out / "round_1" / "training" / "train_log.jsonl"
    n_log = len(log_path.read_text().splitlines())
    r0 = (out / "round_0" / "round.json").stat().st_mtime_ns
    before = json.loads((out / "round_1" / "round.json").read_text())
    (out / "round_1" / "round.json").unlink()
    with caplog.at_level(logging.INFO):
        assert main(argv) == 0
    assert "round 0: already finished" in caplog.text and "resumed from" in caplog.text
    assert (out / "round_0" / "round.json").stat().st_mtime_ns == r0
    assert len(log_path.read_text().splitlines()) == n_log  # no step was trained again
    after = json.loads((out / "round_1" / "round.json").read_text())
    assert after["slam"]["ate_rmse"] == pytest.approx(before["slam"]["ate_rmse"], abs=1e-9)  # same model, same seeds


@pytest.mark.slow
def test_changed_training_config_retrains(learning_run, caplog, tmp_path):
    """Another trainer setting: round 0 is kept (it does not depend on training), round 1 is
    recomputed and its stale checkpoint is not resumed but replaced (logged)."""
    import logging

    from gr_graph.slam import main

    import shutil

    shared, argv = learning_run
    argv = list(argv)
    out = tmp_path / "run"  # a copy: the shared run stays as it was made
    shutil.copytree(shared, out)
    argv[argv.index("--out") + 1] = str(out)
    r0 = (out / "round_0" / "round.json").stat().st_mtime_ns
    cfg = json.loads(json.dumps(LEARNING_RUN_CONFIG))
    cfg["training"]["trainer"]["lr"] = 2e-3
    y = tmp_path / "other.yaml"
    y.write_text(yaml.safe_dump(cfg))
    argv = [a if a != argv[argv.index("--config") + 1] else str(y) for a in argv]
    with caplog.at_level(logging.INFO):
        assert main(argv) == 0
    assert "round 0: already finished" in caplog.text
    assert "training restarts from scratch" in caplog.text
    assert (out / "round_0" / "round.json").stat().st_mtime_ns == r0
    summary = json.loads((out / "round_1" / "training" / "summary.json").read_text())
    assert summary["config"]["lr"] == 2e-3 and summary["epochs_done"] == 4
    m = json.loads((out / "metrics.json").read_text())
    assert m["rounds"]["1"]["slam"]["ate_rmse"] < ATE_BOUND_M
