"""What a run leaves to look at: the map PLY (streamed voxel map), the trajectory plot with
readable covariance ellipses, the RPE-per-round figure, ``--viz`` without a display."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from gr_graph.map_export import VoxelMap, map_path, write_map
from gr_graph.plots import ellipse_axes, ellipse_scale, plot_rounds, plot_trajectory
from gr_graph.viewer import show_map


def _reference_voxel_map(points: np.ndarray, voxel: float) -> dict[tuple[int, int, int], tuple[np.ndarray, int]]:
    """Centroid and count per voxel, one point at a time in a dict."""
    acc: dict[tuple[int, int, int], list] = {}
    for p in points:
        key = tuple(int(v) for v in np.floor(p / voxel))
        e = acc.setdefault(key, [np.zeros(3), 0])
        e[0] += p
        e[1] += 1
    return {k: (s / n, n) for k, (s, n) in acc.items()}


def test_voxel_map_streams_to_the_same_centroids_as_a_dict() -> None:
    rng = np.random.default_rng(0)
    chunks = [rng.normal(0, 3, (500, 3)) + rng.normal(0, 5, 3) for _ in range(12)]
    chunks[3][:5] = np.nan  # dropped
    voxel = 0.7
    streamed = VoxelMap(voxel, flush_points=300)  # many merges
    for c in chunks:
        streamed.add(c)
    once = VoxelMap(voxel, flush_points=10**9)
    once.add(np.concatenate(chunks))
    ca, na = streamed.points()
    cb, nb = once.points()
    np.testing.assert_allclose(ca, cb, atol=1e-12)
    np.testing.assert_array_equal(na, nb)
    allp = np.concatenate(chunks)
    ref = _reference_voxel_map(allp[np.isfinite(allp).all(1)], voxel)
    assert len(ca) == len(ref) and na.sum() == len(allp) - 5
    keys = [tuple(int(v) for v in np.floor(p / voxel)) for p in allp[np.isfinite(allp).all(1)]]
    # every output centroid is the reference centroid of one voxel
    ref_c = np.array([ref[k][0] for k in sorted(ref)])
    np.testing.assert_allclose(np.array(sorted(map(tuple, ca))), np.array(sorted(map(tuple, ref_c))), atol=1e-12)
    assert len(set(keys)) == len(ca)
    with pytest.raises(ValueError, match="beyond"):
        VoxelMap(0.2, flush_points=1).add(np.array([[1e6, 0.0, 0.0]]))


def test_write_map_places_scans_with_their_poses(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    import open3d as o3d

    rng = np.random.default_rng(1)
    world = rng.uniform(-20, 20, (3000, 3))
    poses, scans = [], []
    for k in range(5):  # each scan sees the same world points from its own pose
        c, s = np.cos(0.3 * k), np.sin(0.3 * k)
        T = np.eye(4)
        T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        T[:3, 3] = [2.0 * k, -k, 0.1 * k]
        poses.append(T)
        scans.append(((world - T[:3, 3]) @ T[:3, :3]).astype(np.float64))
    counts = write_map(tmp_path / "map.ply", iter(scans), np.array(poses), voxel_size=0.01)
    cloud = o3d.t.io.read_point_cloud(str(tmp_path / "map.ply"))
    pts = cloud.point.positions.numpy()
    # a 1 cm grid separates the world points: the map is the world, each voxel seen 5 times
    assert counts == {"points": 15000, "voxels": 3000, "voxel_size": 0.01}
    np.testing.assert_allclose(np.array(sorted(map(tuple, pts))), np.array(sorted(map(tuple, world))), atol=1e-5)
    assert set(cloud.point["count"].numpy().ravel()) == {5}
    with pytest.raises(ValueError, match="4 scans for 5 poses"):
        write_map(tmp_path / "bad.ply", scans[:4], np.array(poses), 0.1)

    # a scan whose pose is not finite is left out, logged and counted (before: silently, point by point)
    broken = np.array(poses)
    broken[2, 0, 3] = np.nan
    with caplog.at_level(logging.WARNING, logger="gr_graph.map_export"):
        counts = write_map(tmp_path / "nan.ply", iter(scans), broken, voxel_size=0.01)
    assert counts == {"points": 12000, "voxels": 3000, "voxel_size": 0.01, "scans_left_out": 1}
    assert "1 scans left out of the map, their poses are not finite (scans 2)" in caplog.text


def test_ellipse_axes_and_scale_closed_form() -> None:
    th = np.radians(30.0)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    cov = R @ np.diag([0.2**2, 0.05**2]) @ R.T
    w, h, ang = ellipse_axes(cov[None])
    np.testing.assert_allclose([w[0], h[0]], [6 * 0.2, 6 * 0.05])
    assert np.isclose(ang[0] % 180, 30.0)
    assert ellipse_scale(np.array([0.1]), 600.0) == 50.0  # 0.015 * 600 / 0.1 = 90 -> 50
    assert ellipse_scale(np.array([0.1]), 20.0) == 2.0  # 3 -> 2
    assert ellipse_scale(np.array([1.0]), 20.0) == 1.0  # already visible: true size
    assert ellipse_scale(np.zeros(3), 600.0) == 1.0


def _captured_trajectory_plots(monkeypatch) -> dict:
    """What each trajectory plot drew, instead of saving it: its ellipses and legend texts."""
    import matplotlib.patches

    from gr_graph import plots

    captured: dict = {}

    def grab(fig, path, **kw):
        ax = fig.axes[0]
        captured["ellipses"] = [p for p in ax.patches if isinstance(p, matplotlib.patches.Ellipse)]
        captured["labels"] = [t.get_text() for t in ax.get_legend().get_texts()]
        Path(path).write_bytes(b"png")
        return Path(path)

    monkeypatch.setattr(plots, "atomic_savefig", grab)
    return captured


def test_trajectory_plot_draws_magnified_ellipses_and_says_so(tmp_path: Path, monkeypatch) -> None:
    captured = _captured_trajectory_plots(monkeypatch)
    K = 120
    poses = np.tile(np.eye(4), (K, 1, 1))
    poses[:, 0, 3] = np.linspace(0, 600, K)  # a 600 m drive
    cov = np.tile(np.diag([0.02**2, 0.01**2, 1e-4]), (K, 1, 1))  # 3-sigma major axis 0.12 m
    plot_trajectory(tmp_path / "t.png", poses, gt=poses, position_cov=cov)
    scale = ellipse_scale(np.full(K, 0.12), 600.0)
    assert scale == 50.0
    widths = sorted({round(e.width, 9) for e in captured["ellipses"]})
    assert widths == [round(50.0 * 0.12, 9)] and len(captured["ellipses"]) == 60
    assert any("magnified x50" in t and "3σ" in t for t in captured["labels"])


def test_trajectory_plot_leaves_out_poses_without_a_covariance_and_refuses_no_poses(tmp_path: Path,
                                                                                      monkeypatch) -> None:
    import matplotlib.pyplot as plt

    captured = _captured_trajectory_plots(monkeypatch)
    K = 10
    poses = np.tile(np.eye(4), (K, 1, 1))
    poses[:, 0, 3] = np.arange(K)
    cov = np.tile(np.diag([0.02**2, 0.01**2, 1e-4]), (K, 1, 1))
    cov[::2] = np.nan  # marginals that failed for half the poses
    plot_trajectory(tmp_path / "t.png", poses, position_cov=cov)
    assert len(captured["ellipses"]) == 5 and all(np.isfinite(e.width) for e in captured["ellipses"])
    label = next(t for t in captured["labels"] if "ellipses" in t)
    assert "median major axis 0.12 m" in label and "5 poses without a finite pose or covariance" in label
    plot_trajectory(tmp_path / "none.png", poses, position_cov=np.full((K, 3, 3), np.nan))
    assert not captured["ellipses"] and not any("ellipses" in t for t in captured["labels"])
    # a pose that is not finite (the map leaves such scans out): no ellipse there, the others at their scale
    captured["ellipses"].clear()
    poses[3, :3, 3] = np.nan
    cov[::2] = np.diag([0.02**2, 0.01**2, 1e-4])
    plot_trajectory(tmp_path / "nan_pose.png", poses, position_cov=cov)
    assert len(captured["ellipses"]) == K - 1 and all(np.isfinite(e.center).all() for e in captured["ellipses"])
    assert ellipse_scale(np.full(3, 0.1), float("nan")) == 1.0
    open_before = plt.get_fignums()
    with pytest.raises(ValueError, match="empty.png: no poses to plot"):
        plot_trajectory(tmp_path / "empty.png", np.zeros((0, 4, 4)))
    with pytest.raises(IndexError):  # drawing fails once the figure exists: the figure is closed all the same
        plot_trajectory(tmp_path / "bad_loop.png", poses, loops=np.array([[0, K + 5]]))
    assert plt.get_fignums() == open_before and not (tmp_path / "bad_loop.png").exists()


def test_rounds_figure_from_metrics(tmp_path: Path) -> None:
    metrics = {"rounds": {"0": {"slam": {"rpe300_consecutive_mean": 1.2, "ate_rmse": 3.0},
                                "odometry": {"rpe300_consecutive_mean": 2.0, "ate_rmse": 5.0}},
                          "1": {"slam": {"rpe300_consecutive_mean": 1.0, "ate_rmse": 2.5},
                                "odometry": {"rpe300_consecutive_mean": 1.9, "ate_rmse": 4.0}}}}
    png = plot_rounds(tmp_path / "rounds.png", metrics, title="t")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    plot_rounds(tmp_path / "empty.png", {"rounds": {"0": {}, "1": {}}})  # no ground truth: no crash
    plot_rounds(tmp_path / "none.png", {"rounds": {"0": {"slam": None, "odometry": None}}})  # another tool's file
    assert (tmp_path / "none.png").is_file()
    assert (tmp_path / "empty.png").is_file()


def test_revisit_run_writes_its_map_and_plot(revisit_run: Path) -> None:
    """The map is round 0's memory scans placed with the optimised poses (independent rebuild)."""
    import open3d as o3d

    from gr_graph.memory import load_memory

    rd = revisit_run / "round_0"
    summary = json.loads((rd / "round.json").read_text())
    cloud = o3d.t.io.read_point_cloud(str(map_path(rd)))
    pts = cloud.point.positions.numpy().astype(np.float64)
    assert summary["map"]["voxels"] == len(pts) and summary["map"]["voxel_size"] == 0.2
    assert summary["map"]["scans"] == "measured"
    with np.load(rd / "marginals.npz") as z:
        poses = z["poses"]
    mem = load_memory(rd / "memory")
    world = np.concatenate([np.asarray(mem.scan(k), np.float64) @ poses[k][:3, :3].T + poses[k][:3, 3]
                            for k in range(mem.n_scans)])
    assert summary["map"]["points"] == len(world)
    ref = VoxelMap(0.2, flush_points=10**9)
    ref.add(world)
    c, n = ref.points()
    np.testing.assert_allclose(pts, c, atol=1e-4)  # float32 in the PLY
    np.testing.assert_array_equal(cloud.point["count"].numpy().ravel(), n)
    assert (revisit_run / "trajectory.png").is_file()
    assert not (revisit_run / "rounds.png").exists()  # one round only


def test_viz_without_display_is_a_message_not_a_crash(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    write_map(tmp_path / "map.ply", [np.random.default_rng(0).normal(size=(100, 3))], np.eye(4)[None], 0.2)
    assert show_map(tmp_path / "map.ply") is False
    err = capsys.readouterr().err
    assert "no display" in err and str(tmp_path / "map.ply") in err
    assert show_map(tmp_path / "missing.ply") is False
    assert "no map at" in capsys.readouterr().err


def test_viz_with_a_display_that_does_not_open_is_a_message_not_a_hang(tmp_path: Path, monkeypatch, capsys) -> None:
    """DISPLAY set but no X server behind it (an ended SSH forwarding): open3d would block offscreen."""
    import ctypes.util

    if ctypes.util.find_library("X11") is None:
        pytest.skip("libX11 is not installed here: DISPLAY cannot be checked (and is trusted)")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setenv("DISPLAY", ":987")
    write_map(tmp_path / "map.ply", [np.random.default_rng(0).normal(size=(100, 3))], np.eye(4)[None], 0.2)
    assert show_map(tmp_path / "map.ply") is False
    err = capsys.readouterr().err
    assert "DISPLAY=:987 cannot be opened" in err and str(tmp_path / "map.ply") in err
    # a listener that never answers (a stalled forwarding): no answer within the timeout is no display
    import socket
    import threading
    import time

    import gr_graph.viewer as viewer

    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        port = silent.getsockname()[1]
        if port < 6000:
            pytest.skip(f"the free port {port} is below X's 6000 + display number")
        monkeypatch.setenv("DISPLAY", f"127.0.0.1:{port - 6000}")
        monkeypatch.setattr(viewer, "X_PROBE_TIMEOUT_S", 0.5)
        answer: list[tuple[bool, str]] = []
        t0 = time.perf_counter()
        probe = threading.Thread(target=lambda: answer.append(viewer.display_available()), daemon=True)
        probe.start()
        probe.join(10)  # a probe without its timeout fails here instead of hanging the suite
        assert not probe.is_alive() and answer[0][0] is False
        assert time.perf_counter() - t0 < 5


@pytest.mark.slow
def test_learning_run_outputs_and_slam_viz(learning_run, monkeypatch, capsys) -> None:
    """With rounds: a map per round and the RPE-per-round figure; ``--viz`` on the finished run
    (resumed, nothing recomputed) without a display prints the message and exits 0."""
    from gr_graph.slam import main

    run_dir, argv = learning_run
    assert (run_dir / "rounds.png").is_file()
    for r in (0, 1):
        assert map_path(run_dir / f"round_{r}").is_file()
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main([*argv, "--viz"]) == 0
    err = capsys.readouterr().err
    assert "--viz: no display" in err and str(map_path(run_dir / "round_1")) in err


def test_voxel_map_merge_memory_stays_near_the_map() -> None:
    """Merging a batch into a large map must not copy the map several times over: the peak
    (tracemalloc sees numpy's buffers) stays under 2.5x the map's own arrays plus a bounded
    cost per buffered point, however large the map has grown."""
    import tracemalloc

    rng = np.random.default_rng(1)
    vmap = VoxelMap(1.0, flush_points=20_000)
    tracemalloc.start()
    for i in range(60):  # 60 x 20,000 points, nearly all in new voxels: the map grows to ~1.2 M voxels
        vmap.add(rng.uniform(-1000, 1000, (20_000, 3)) + [0.0, 0.0, 4000.0 * (i % 2)])
    n_voxels = len(vmap)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    map_bytes = n_voxels * (8 + 24 + 8)  # key, sum, count per voxel
    assert n_voxels > 1_000_000
    assert peak < 2.5 * map_bytes + 200 * 20_000, (peak, map_bytes)


def test_a_figure_that_fails_never_fails_the_finished_run(kitti_root: Path, tmp_path: Path, monkeypatch,
                                                          capsys) -> None:
    """The poses and metrics are written before the figures: a plotting error is logged, named in
    metrics.json and the stale figure removed; the run ends with its summary. Figures turned off remove an
    earlier run's (they would be taken for this run's)."""
    import json

    import gr_graph.plots as plots
    from gr_graph import slam

    def broken(*args, **kwargs):
        raise ValueError("max() arg is an empty sequence")

    out = tmp_path / "run"
    out.mkdir()
    (out / "trajectory.png").write_bytes(b"an earlier run's figure")
    monkeypatch.setattr(plots, "plot_trajectory", broken)
    common = ["--data-root", str(kitti_root), "--frames", "0:4", "--no-loops", "--no-memory", "--no-progress",
              "--out", str(out)]
    assert slam.main(common) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["figures_failed"] == {"trajectory.png": "ValueError: max() arg is an empty sequence"}
    assert not (out / "trajectory.png").exists() and (out / "poses_kitti.txt").is_file()
    assert summary["final_round"] == 0
    (out / "trajectory.png").write_bytes(b"an earlier run's figure")
    cfg = tmp_path / "no_plot.yaml"
    cfg.write_text("output:\n  plot: false\n")
    assert slam.main(common + ["--config", str(cfg)]) == 0
    assert not (out / "trajectory.png").exists() and "figures_failed" not in json.loads((out / "metrics.json").read_text())
    assert summary["resumed_rounds"] == [] and json.loads(capsys.readouterr().out.strip().splitlines()[-1])[
        "resumed_rounds"] == [0]  # the second call took round 0 from --out


def test_options_of_learning_rounds_given_without_rounds_are_named_as_ignored(kitti_root: Path, tmp_path: Path,
                                                                               caplog) -> None:
    from gr_graph import slam

    common = ["--data-root", str(kitti_root), "--frames", "0:3", "--no-loops", "--no-memory", "--no-progress",
              "--out", str(tmp_path / "run")]
    with caplog.at_level("WARNING", logger="gr_graph.slam"):
        assert slam.main(common + ["--paper-method", "--device", "cpu", "--long-baseline-guard=0.05"]) == 0
    assert "--paper-method, --long-baseline-guard, --device cpu only act on learning rounds" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="gr_graph.slam"):
        assert slam.main(common) == 0
    assert "only act on learning rounds" not in caplog.text
