"""The main command and the pipeline end to end: real KITTI frames, synthetic runs, resume."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gr_graph.config import load_config
from gr_graph.memory import EDGE_LOOP, EDGE_ODOMETRY, load_memory
from gr_graph.round_output import MARGINALS_KEYS
from gr_graph.slam import main
from gr_graph.trajectory import read_kitti_poses, read_tum_poses


@pytest.fixture(scope="module")
def kitti_run(kitti_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("kitti_run")
    rc = main(["--seq", "00", "--data-root", str(kitti_root), "--out", str(out), "--quiet"])
    assert rc == 0
    return out


@pytest.mark.slow
def test_cli_real_kitti_outputs(kitti_run, kitti_root):
    out = kitti_run
    P = read_kitti_poses(out / "round_0" / "poses_kitti.txt")
    assert P.shape == (6, 4, 4)
    np.testing.assert_allclose(P[0], np.eye(4), atol=1e-9)
    # camera frame: forward is +z; the real car moves ~0.69 m/frame (GT wrongly says 0.86)
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.6) & (steps < 0.8))
    assert P[-1, 2, 3] > 3.0 and abs(P[-1, 0, 3]) < 0.5
    # TUM file: LiDAR frame, same trajectory (forward is +x)
    ts, Pt = read_tum_poses(out / "round_0" / "poses_tum.txt")
    assert len(ts) == 6 and np.all(np.diff(ts) > 0)
    assert Pt[-1, 0, 3] > 3.0  # LiDAR frame: forward is +x
    # same trajectory: camera-frame poses are Tr T Tr^-1 of the LiDAR ones
    Tr = np.loadtxt(kitti_root / "sequences" / "00" / "calib.txt", usecols=range(1, 13), max_rows=5)[-1]
    Tr = np.vstack([Tr.reshape(3, 4), [0, 0, 0, 1]])
    np.testing.assert_allclose(Tr @ Pt @ np.linalg.inv(Tr), P, atol=1e-6)
    # marginals: documented keys, SPD covariances growing along the chain
    with np.load(out / "round_0" / "marginals.npz") as z:
        assert set(z.files) <= set(MARGINALS_KEYS) and {"covariance", "poses", "frame_index"} <= set(z.files)
        C = z["covariance"]
        assert C.shape == (6, 6, 6) and np.all(np.linalg.eigvalsh(C[1:]) > 0)
        tr = np.trace(z["position_cov_world"], axis1=1, axis2=2)
        assert np.all(np.diff(tr) > 0)
        np.testing.assert_array_equal(z["frame_index"], np.arange(6))
    # resolved config round-trips
    cfg = load_config(out / "config.yaml")
    assert cfg.data.data_root == str(kitti_root) and cfg.output.out_dir == str(out)
    m = json.loads((out / "metrics.json").read_text())
    r0 = m["rounds"]["0"]
    assert r0["n_frames"] == 6 and r0["n_flagged_odometry_edges"] == 0
    # the real pairs' registrations converge within the iteration limit (each 2-4 iterations)
    assert r0["n_odometry_edges_not_converged"] == 0 and r0["n_loop_edges_not_converged"] == 0
    assert "KITTI" in m["source"] and "synthetic" not in m["source"]
    assert {"preprocess", "odometry", "graph", "total"} <= set(r0["runtime_s"])
    assert r0["slam"]["rpe300_consecutive_mean"] is None  # too short, reported as None
    assert (out / "trajectory.png").stat().st_size > 1000


@pytest.mark.slow
def test_cli_real_kitti_memory(kitti_run):
    mem = load_memory(kitti_run / "round_0" / "memory")
    assert isinstance(mem.points, np.memmap)
    assert mem.n_scans == 6 and mem.n_edges == 5
    assert mem.edges.tolist() == [[k + 1, k] for k in range(5)]
    assert np.all(mem.edge_kind == EDGE_ODOMETRY)
    for e in range(mem.n_edges):
        ed = mem.edge(e)
        np.testing.assert_allclose(ed.T, np.linalg.inv(mem.poses[ed.l]) @ mem.poses[ed.k], atol=1e-9)
        assert len(ed.corr) > 0.5 * len(mem.scan(ed.k))
        p = mem.scan(ed.k)[ed.corr[:, 0]].astype(float) @ ed.T[:3, :3].T + ed.T[:3, 3]
        q = mem.scan(ed.l)[ed.corr[:, 1]].astype(float)
        d = np.linalg.norm(p - q, axis=1)
        assert d.max() <= 1.0 + 1e-5 and np.median(d) < 0.3
        # j is the nearest stored target point
        i0 = len(ed.corr) // 2
        all_d = np.linalg.norm(mem.scan(ed.l).astype(float) - p[i0], axis=1)
        assert np.isclose(all_d.min(), d[i0], atol=1e-5)
        assert np.all(np.linalg.eigvalsh(ed.H) > 0)


@pytest.mark.slow
def test_resume_skips_finished_round(kitti_run, kitti_root, caplog, tmp_path):
    rj = kitti_run / "round_0" / "round.json"
    before = rj.read_text()
    mtime = rj.stat().st_mtime_ns
    with caplog.at_level("INFO"):
        assert main(["--seq", "00", "--data-root", str(kitti_root), "--out", str(kitti_run), "--quiet"]) == 0
    assert rj.stat().st_mtime_ns == mtime and rj.read_text() == before
    assert "skipped (resume)" in caplog.text
    # another SLAM setting -> recomputed
    y = tmp_path / "c.yaml"
    y.write_text("odometry:\n  max_iterations: 25\n")
    assert main(["--seq", "00", "--data-root", str(kitti_root), "--out", str(kitti_run), "--quiet",
                 "--config", str(y)]) == 0
    assert rj.stat().st_mtime_ns != mtime
    assert json.loads(rj.read_text())["config_fingerprint"] != json.loads(before)["config_fingerprint"]


def test_bad_cli_input_is_a_clear_error(tmp_path, capsys):
    assert main(["--frames", "10:5", "--out", str(tmp_path)]) == 2
    assert "frames" in capsys.readouterr().err
    assert main(["--data-root", str(tmp_path / "nope"), "--out", str(tmp_path)]) == 2
    assert "sequences/00/velodyne" in capsys.readouterr().err
    y = tmp_path / "typo.yaml"
    y.write_text("odometry:\n  max_iteratons: 5\n")
    assert main(["--config", str(y), "--out", str(tmp_path)]) == 2
    assert "max_iteratons" in capsys.readouterr().err
    latin = tmp_path / "latin.yaml"
    latin.write_bytes("# caf\xe9\nseed: 1\n".encode("latin-1"))
    assert main(["--config", str(latin), "--out", str(tmp_path)]) == 2
    assert f"{latin}: not a UTF-8 text file" in capsys.readouterr().err


def test_a_damaged_memory_or_failed_training_is_one_line_not_a_traceback(tmp_path, capsys, monkeypatch):
    from gr_graph.memory import MemoryFormatError
    from gr_graph.pipeline import SlamPipeline
    from training.trainer import TrainingError

    for exc in (MemoryFormatError("/x/round_0/memory: missing points.npy"), TrainingError("3 of 4 pairs skipped")):
        def fail(self, exc=exc):
            raise exc

        monkeypatch.setattr(SlamPipeline, "run", fail)
        assert main(["--frames", "0:5", "--out", str(tmp_path / "o"), "--no-progress"]) == 1
        assert capsys.readouterr().err.strip() == f"error: {type(exc).__name__}: {exc}"
    def full_disk(self):
        raise OSError(28, "No space left on device", str(tmp_path / "o" / "round_0"))

    monkeypatch.setattr(SlamPipeline, "run", full_disk)
    assert main(["--frames", "0:5", "--out", str(tmp_path / "o"), "--no-progress"]) == 1
    assert "No space left on device" in capsys.readouterr().err  # the OSError's own line, as before
    monkeypatch.setattr(SlamPipeline, "run", lambda self: 1 / 0)
    with pytest.raises(ZeroDivisionError):  # anything else is a bug: its traceback stays
        main(["--frames", "0:5", "--out", str(tmp_path / "o"), "--no-progress"])


@pytest.mark.slow
def test_synthetic_fallback_without_kitti_root(tmp_path, monkeypatch, caplog):
    monkeypatch.delenv("GR_GRAPH_KITTI_ROOT", raising=False)
    monkeypatch.chdir(tmp_path)  # no ./data/kitti here
    out = tmp_path / "synth"
    with caplog.at_level("INFO"):
        assert main(["--seq", "00", "--frames", "100:115", "--out", str(out), "--quiet", "--no-memory"]) == 0
    said = [r for r in caplog.records if "no KITTI root given or found" in r.getMessage()]
    assert len(said) == 1 and said[0].levelname == "WARNING"  # says so, in one line
    assert "'kitti' preset of the synthetic world" in said[0].getMessage()  # the default world, by name
    m = json.loads((out / "metrics.json").read_text())
    assert "synthetic" in m["source"]
    assert load_config(out / "config.yaml").data.frames == (100, 115)
    r0 = m["rounds"]["0"]
    assert r0["n_frames"] == 15 and r0["slam"]["ate_rmse"] < 0.05
    est = read_kitti_poses(out / "round_0" / "poses_kitti.txt")
    gt = read_kitti_poses(out / "gt_poses_kitti.txt")
    assert np.linalg.norm(est[-1, :3, 3] - gt[-1, :3, 3]) < 0.1  # common camera frame


@pytest.mark.frees_render_cache
def test_pipeline_frees_the_town_of_the_sequence_it_opened(tmp_path, caplog):
    from loader_support import write_short_trajectory

    from gr_graph.datasets.synthetic import SyntheticSequence
    from gr_graph.datasets.synthetic import sequence as synthetic_sequence
    from gr_graph.pipeline import SlamPipeline

    traj = write_short_trajectory(tmp_path / "t.tum", 8)
    data = {"dataset": "synthetic", "trajectory": str(traj), "channels": 16, "synthetic_preset": "clean"}

    def config(out: str):
        return load_config(overrides={"data": data, "output": {"out_dir": str(tmp_path / out), "progress": False,
                                                               "write_memory": False}})

    given = SyntheticSequence(preset="clean", n_rings=16, trajectory=traj)
    key = synthetic_sequence._scene_key(given.town_seed, given.path, given.town_config)
    with caplog.at_level("INFO", logger="gr_graph.pipeline"):
        SlamPipeline(config("own")).run()
    assert key not in synthetic_sequence._CACHE  # opened by the pipeline: freed after the round
    assert any("synthetic town is freed" in r.getMessage() for r in caplog.records)
    SlamPipeline(config("given"), given).run()
    assert key in synthetic_sequence._CACHE  # the caller's sequence keeps its town
    own = read_kitti_poses(tmp_path / "own" / "poses_kitti.txt")
    np.testing.assert_array_equal(own, read_kitti_poses(tmp_path / "given" / "poses_kitti.txt"))
    given.release_cache()


# ----------------------------------------------------------------------------- revisit run


@pytest.mark.slow
def test_revisit_loops_found_and_correct(revisit_run):
    m = json.loads((revisit_run / "metrics.json").read_text())["rounds"]["0"]
    lc = m["loop_closure"]
    assert lc["n_loops"] >= 3
    assert lc["precision"] == 1.0  # no false loop
    assert lc["segment_recall"] == 1.0 and lc["recall"] >= 0.8
    # the jump between the two stretches is a detected, flagged failure ...
    assert m["n_flagged_odometry_edges"] == 1
    # ... which the loops repair: odometry alone is tens of metres off, SLAM is not
    assert m["odometry"]["ate_rmse"] > 5.0
    assert m["slam"]["ate_rmse"] < 0.1
    # NEES against ground truth is in the summary, equal to the evaluation of the written round
    from gr_graph.noise_consistency import round_noise_consistency

    nc = m["noise_consistency"]
    assert nc == json.loads(json.dumps(round_noise_consistency(revisit_run / "round_0")))
    assert nc["edges"]["loop"]["n"] == lc["n_loops"] and nc["edges"]["n_flagged_left_out"] == 1
    assert nc["position"]["n"] == m["n_frames"] - 1 and nc["position"]["mean"] > 0


@pytest.mark.slow
def test_revisit_marginals_drop_at_loops(revisit_run):
    with np.load(revisit_run / "round_0" / "marginals.npz") as z:
        tr = np.trace(z["position_cov_world"], axis1=1, axis2=2)
        kind, ok, edges = z["edge_kind"], z["edge_ok"], z["edges"]
        gt, P = z["gt_poses"], z["poses"]
    assert int((~ok).sum()) == 1 and tuple(edges[~ok][0]) == (100, 99)
    # without loops the flagged edge (1 m sigmas) would add ~3 m^2 after position 100;
    # with loops the second stretch is tied to the first
    assert tr[100:].max() < 0.5
    loops = edges[kind == 1]
    assert len(loops) >= 3 and np.all(loops[:, 0] >= 100) and np.all(loops[:, 1] < 100)
    err = np.linalg.norm(P[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert err.max() < 0.3


@pytest.mark.slow
def test_revisit_memory_has_loop_edges(revisit_run):
    mem = load_memory(revisit_run / "round_0" / "memory")
    n_loop = int((mem.edge_kind == EDGE_LOOP).sum())
    assert mem.n_scans == 160 and mem.n_edges == 159 + n_loop and n_loop >= 3
    for e in np.flatnonzero(mem.edge_kind == EDGE_LOOP):
        ed = mem.edge(int(e))
        assert len(ed.corr) > 0.3 * len(mem.scan(ed.k))
    assert mem.info["round"] == 0 and len(mem.info["frame_index"]) == 160
    assert mem.info["flagged_edges"] == [99]  # edge (100, 99), the jump


@pytest.mark.slow
def test_cli_real_kitti_16_channels(kitti_root, tmp_path):
    """16 of the 64 real rings (lead's ring recovery): fewer points, still the real ~0.7 m/frame."""
    out = tmp_path / "c16"
    assert main(["--data-root", str(kitti_root), "--channels", "16", "--out", str(out), "--quiet",
                 "--no-memory"]) == 0
    P = read_kitti_poses(out / "round_0" / "poses_kitti.txt")
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    assert np.all((steps > 0.6) & (steps < 0.8))
    m = json.loads((out / "metrics.json").read_text())
    assert m["channels"] == 16 and m["rounds"]["0"]["n_flagged_odometry_edges"] == 0
    assert not (out / "round_0" / "memory").exists()


@pytest.mark.slow
def test_learning_round_structure_with_stub_trainer(kitti_root, tmp_path, monkeypatch):
    """Algorithm 3's loop with stand-ins for the trainer and the densifier (identity): round 1
    trains on round 0's memory, runs SLAM on the 'densified' scans, and stops as converged
    (the trajectory did not move) although more rounds were allowed."""
    from gr_graph.densify import DensifiedSequence
    from gr_graph.memory import load_memory as _load

    calls = []

    def train_from_memory(memory_dir, out_dir, config, resume=True):
        mem = _load(memory_dir)  # the trainer can read what round r-1 wrote
        calls.append((str(memory_dir), mem.n_edges, dict(config)))
        ckpt = tmp_path / "ckpt.pt"
        ckpt.write_text("stub")
        return ckpt

    class IdentityDensified(DensifiedSequence):
        """The raw frames; no predicted covariances (every edge keeps its registration information)."""

        def __getitem__(self, i):
            return self.parent[i]

    def densified_sequence(sequence, ckpt, config, device="cpu", preprocess=None, keep_predictions=16):
        calls.append(("densify", str(ckpt), device))
        return IdentityDensified(sequence, lambda p: None, config, preprocess, keep_predictions)

    monkeypatch.setattr("training.train.train_from_memory", train_from_memory)
    monkeypatch.setattr("gr_graph.pipeline.densified_sequence", densified_sequence)
    out = tmp_path / "rounds"
    assert main(["--data-root", str(kitti_root), "--out", str(out), "--rounds", "3", "--quiet"]) == 0
    assert calls[0][0] == str(out / "round_0" / "memory") and calls[0][1] == 5
    assert "rounds" not in calls[0][2] and calls[1] == ("densify", str(tmp_path / "ckpt.pt"), "cpu")
    m = json.loads((out / "metrics.json").read_text())
    assert sorted(m["rounds"]) == ["0", "1"]  # converged after round 1
    assert m["rounds"]["1"]["trajectory_change"] < 1e-9
    assert m["rounds"]["1"]["edge_noise"]["fallbacks"] == {"no_covariances": 5}
    assert (out / "round_1" / "round.json").exists() and not (out / "round_2").exists()
    # not allowed to converge: round 2 is judged against round 1 and also against round 0 (the same poses)
    (tmp_path / "go_on.yaml").write_text("training:\n  convergence_delta: 0.0\n  warm_start: false\n")
    out2 = tmp_path / "rounds_go_on"
    assert main(["--data-root", str(kitti_root), "--out", str(out2), "--rounds", "2", "--quiet",
                 "--config", str(tmp_path / "go_on.yaml")]) == 0
    a2 = json.loads((out2 / "metrics.json").read_text())["rounds"]["2"]["acceptance"]
    assert a2["accepted"] and a2["reference_round"] == 1
    assert a2["map_sharpness_round_0"]["mean_entropy_increase"] == 0.0
    assert a2["map_sharpness_round_0"]["n_windows"] == a2["n_windows"] > 0


@pytest.mark.slow
def test_deterministic(kitti_root):
    """Same input and config -> bit-identical poses, covariances and loop decisions."""
    from gr_graph.datasets.registry import open_sequence
    from gr_graph.frame_loop import run_slam

    seq, _ = open_sequence("00", data_root=kitti_root)
    cfg = load_config(overrides={"output": {"progress": False}, "loops": {"min_frame_gap": 2, "check_every": 1}})
    a, b = run_slam(seq, cfg), run_slam(seq, cfg)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.covariances, b.covariances)
    assert [(x["query"], x["match"], x["accepted"]) for x in a.loop_attempts] == \
        [(x["query"], x["match"], x["accepted"]) for x in b.loop_attempts]


@pytest.mark.slow
def test_metrics_record_provenance(revisit_run):
    """metrics.json says which code, packages, seeds, threads and device made it."""
    import subprocess

    from gr_graph.provenance import REPO_ROOT

    prov = json.loads((revisit_run / "metrics.json").read_text())["provenance"]
    head = subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:
        commit = prov["git"]["commit"]
        assert len(commit) == 40 and isinstance(prov["git"]["dirty"], bool)
        # the commit of the run is HEAD, or an ancestor of it when a commit landed during the session
        ancestor = subprocess.run(["git", "-C", str(REPO_ROOT), "merge-base", "--is-ancestor", commit, "HEAD"])
        assert ancestor.returncode == 0, commit
    assert prov["packages"]["numpy"] == np.__version__
    assert {"gtsam", "small_gicp", "scipy"} <= set(prov["packages"])
    assert prov["seeds"] == {"world": 0, "training": 0}
    assert prov["device"] == "cpu" and prov["num_threads"] >= 1 and prov["cpu_count"] >= 1
    assert prov["cpu"]["model"] and "simd" in prov["cpu"]  # learning rounds differ between kernel sets


def test_cpu_description_names_the_model_and_torch_kernels():
    from pathlib import Path

    import torch

    from gr_graph.experiments.report import machine_line
    from gr_graph.provenance import cpu_description, provenance

    cpu = cpu_description()
    assert cpu["torch_capability"] == torch.backends.cpu.get_cpu_capability()
    info = Path("/proc/cpuinfo")
    names = ([ln.split(":", 1)[1].strip() for ln in info.read_text().splitlines()
              if ln.lower().startswith("model name")] if info.exists() else [])
    if names:
        assert cpu["model"] == names[0]
    assert cpu["model"]
    assert provenance()["cpu"] == cpu
    assert f"{cpu['model']} (torch kernels {cpu['torch_capability']})" in machine_line()


def test_record_machine_from_stored_provenance_matches_the_live_machine_line():
    import torch  # noqa: F401  (the kernel set is known)

    from gr_graph.experiments.records import _machine_of
    from gr_graph.provenance import machine_line, provenance

    stored = {"provenance": provenance()}  # a cell result without its own machine line
    assert _machine_of(stored) == machine_line()
    assert _machine_of({"machine": "given"}) == "given" and _machine_of({}) is None
    bare = {"provenance": {"cpu": {}, "cpu_count": 2, "platform": "P", "python": "3.11"}}
    assert _machine_of(bare) == "unknown CPU, 2 cores, P, Python 3.11"


def test_cli_route_seed_and_trajectory_reach_the_config(tmp_path):
    from gr_graph.slam import build_parser, overrides_from_args

    args = build_parser().parse_args(["--route-seed", "2", "--trajectory", str(tmp_path / "poses.txt")])
    cfg = load_config(None, overrides_from_args(args))
    assert cfg.data.route_seed == 2 and cfg.data.trajectory == str(tmp_path / "poses.txt")
    assert load_config(None, {}).data.route_seed == 0 and load_config(None, {}).data.trajectory is None
    # a missing trajectory file is a clear error naming it (exit code 2)
    assert main(["--trajectory", str(tmp_path / "poses.txt"), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
