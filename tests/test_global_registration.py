"""Global registration evaluation: pair sampling, error measures, both solvers on a real pair."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gr_graph.global_registration import (
    evaluate_pairs,
    is_success,
    load_pairs,
    relative_transform,
    rotation_error_deg,
    sample_pairs,
    save_pairs,
    translation_error_m,
    write_results,
)
from gr_graph.global_solvers import kiss_matcher_available, register_fpfh_ransac, register_kiss_matcher

REPO = Path(__file__).resolve().parents[1]


def make_T(rotvec: list[float], t: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_error_measures_closed_form() -> None:
    ref = make_T([0.1, 0.2, 0.3], [1.0, 2.0, 3.0])
    est = ref @ make_T([0.0, 0.0, np.radians(7.0)], [0.0, 0.0, 0.0])
    assert rotation_error_deg(est, ref) == pytest.approx(7.0, abs=1e-9)
    assert translation_error_m(est, ref) == pytest.approx(0.0, abs=1e-12)
    est2 = ref.copy()
    est2[:3, 3] += [1.2, 0.0, -1.6]
    assert translation_error_m(est2, ref) == pytest.approx(2.0, abs=1e-12)
    assert not is_success(est2, ref)  # 2.0 m is not < 2 m
    est2[:3, 3] -= [0.0, 0.0, -0.1]
    assert is_success(est2, ref)
    est3 = ref @ make_T([0.0, np.radians(10.5), 0.0], [0, 0, 0])
    assert not is_success(est3, ref)
    assert rotation_error_deg(ref @ make_T([np.pi, 0, 0], [0, 0, 0]), ref) == pytest.approx(180.0, abs=1e-9)


def test_sample_pairs_on_the_generated_route(tmp_path: Path) -> None:
    from gr_graph.datasets.synthetic.route import generate_route

    poses = np.asarray(generate_route(0).T_w_velo)  # a 3.7 km drive with revisits
    pairs = sample_pairs(poses, n=100, max_distance=10.0, seed=3, min_frame=14)
    assert pairs.shape == (100, 2)
    assert len({tuple(p) for p in pairs.tolist()}) == 100
    assert np.all(pairs[:, 0] > pairs[:, 1]) and pairs.min() >= 14
    d = np.linalg.norm(poses[pairs[:, 0], :3, 3] - poses[pairs[:, 1], :3, 3], axis=1)
    assert d.max() <= 10.0
    # some pairs are revisits far apart in time (loop closures), not only neighbours
    assert (pairs[:, 0] - pairs[:, 1]).max() > 100
    np.testing.assert_array_equal(pairs, sample_pairs(poses, 100, 10.0, seed=3, min_frame=14))
    assert not np.array_equal(pairs, sample_pairs(poses, 100, 10.0, seed=4, min_frame=14))
    # the candidate set is complete: brute-force count of pairs within 10 m in a window
    sub = poses[:300]
    brute = sum(
        1 for i in range(300) for j in range(i) if np.linalg.norm(sub[i, :3, 3] - sub[j, :3, 3]) <= 10.0
    )
    assert len(sample_pairs(sub, n=brute, seed=0)) == brute
    with pytest.raises(ValueError, match=f"only {brute} scan pairs"):
        sample_pairs(sub, n=brute + 1)
    path = save_pairs(tmp_path / "pairs.json", pairs, {"seed": 3, "max_distance_m": 10.0})
    back, meta = load_pairs(path)
    np.testing.assert_array_equal(back, pairs)
    assert meta == {"seed": 3, "max_distance_m": 10.0}


def load_small_gicp_pair(d: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    import open3d as o3d

    src = np.asarray(o3d.io.read_point_cloud(str(d / "source.ply")).points, dtype=np.float64)
    tgt = np.asarray(o3d.io.read_point_cloud(str(d / "target.ply")).points, dtype=np.float64)
    T = np.loadtxt(d / "T_target_source.txt")
    assert src.shape[0] > 50_000 and tgt.shape[0] > 50_000
    return src, tgt, T


# A large known motion applied on top of the real pair: 120 deg yaw, 6 m, so that the
# identity (or any local method) cannot pass the 10 deg / 2 m test by accident.
G = make_T([0.0, 0.0, np.radians(120.0)], [6.0, -3.0, 0.5])


def moved_source(src: np.ndarray, T_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Express the source scan in a frame moved by G: p' = G^-1 p, reference T_ref @ G."""
    return (src - G[:3, 3]) @ G[:3, :3], T_ref @ G


SOLVERS = [
    pytest.param("fpfh_ransac", id="fpfh_ransac"),
    pytest.param(
        "kiss_matcher",
        id="kiss_matcher",
        marks=pytest.mark.skipif(not kiss_matcher_available(), reason="kiss-matcher not installed"),
    ),
]


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("moved", [False, True], ids=["as_is", "moved_120deg_6m"])
def test_real_small_gicp_pair(small_gicp_pair_dir: Path, solver: str, moved: bool) -> None:
    src, tgt, T_ref = load_small_gicp_pair(small_gicp_pair_dir)
    if moved:
        src, T_ref = moved_source(src, T_ref)
        assert not is_success(np.eye(4), T_ref)
    fn = register_fpfh_ransac if solver == "fpfh_ransac" else register_kiss_matcher
    out = fn(src, tgt, voxel=0.5)
    assert is_success(out.T, T_ref)
    # tighter than the success thresholds: a real solution, not a lucky one
    assert rotation_error_deg(out.T, T_ref) < 4.0
    assert translation_error_m(out.T, T_ref) < 0.8
    assert out.n_inliers >= 10


def test_fpfh_ransac_is_deterministic(small_gicp_pair_dir: Path) -> None:
    src, tgt, _ = load_small_gicp_pair(small_gicp_pair_dir)
    a = register_fpfh_ransac(src[::3], tgt[::3], voxel=1.0, seed=7)
    b = register_fpfh_ransac(src[::3], tgt[::3], voxel=1.0, seed=7)
    np.testing.assert_array_equal(a.T, b.T)


def test_evaluate_pairs_end_to_end(small_gicp_pair_dir: Path, tmp_path: Path) -> None:
    """A 3-scan 'sequence' built from the real pair: target, source, moved source."""
    src, tgt, T_ref = load_small_gicp_pair(small_gicp_pair_dir)
    src_moved, T_ref_moved = moved_source(src, T_ref)
    W = make_T([0.05, -0.02, 1.0], [100.0, 50.0, 2.0])  # arbitrary world frame
    scans = [tgt, src, src_moved]
    poses = np.stack([W, W @ T_ref, W @ T_ref_moved])
    np.testing.assert_allclose(relative_transform(poses, 2, 0), T_ref_moved, atol=1e-9)
    pairs = np.array([[1, 0], [2, 0]])
    res = evaluate_pairs(scans, poses, pairs, solvers=["fpfh_ransac"], voxel=0.5, progress=False)
    s = res["summary"]["fpfh_ransac"]
    assert s["n_pairs"] == 2 and s["n_success"] == 2 and s["success_rate"] == 1.0
    row = res["pairs"][1]
    assert row["source"] == 2 and row["target"] == 0
    assert row["gt_distance_m"] == pytest.approx(np.linalg.norm(T_ref_moved[:3, 3]), rel=1e-9)
    path = write_results(tmp_path / "res.json", res)
    assert json.loads(path.read_text())["summary"]["fpfh_ransac"]["n_success"] == 2
    # a wrong reference makes the same estimates fail: the scoring is not vacuous
    bad = poses.copy()
    bad[2] = W @ T_ref_moved @ make_T([0, 0, np.radians(30)], [0, 0, 0])
    res_bad = evaluate_pairs(scans, bad, pairs[1:], solvers=["fpfh_ransac"], voxel=0.5, progress=False)
    assert res_bad["summary"]["fpfh_ransac"]["n_success"] == 0
    with pytest.raises(ValueError, match="pair indices"):
        evaluate_pairs(scans, poses, np.array([[3, 0]]), solvers=["fpfh_ransac"], progress=False)
    with pytest.raises(ValueError, match="unknown solver"):
        evaluate_pairs(scans, poses, pairs, solvers=["teaser"], progress=False)


def test_no_solution_is_a_failure_and_the_identity_baseline_is_reported(monkeypatch: pytest.MonkeyPatch) -> None:
    """A solver that finds nothing returns the identity: on a pair 0.5 m apart that is within the
    thresholds, yet it must count as a failure; the identity's own success is reported beside."""
    import gr_graph.global_registration as gr
    from gr_graph.global_solvers import RegistrationOutcome

    poses = np.stack([np.eye(4), make_T([0, 0, 0.01], [0.5, 0, 0]), make_T([0, 0, 1.0], [8.0, 0, 0])])
    scans = [np.zeros((20, 3))] * 3
    answers = {(1, 0): RegistrationOutcome("fpfh_ransac", np.eye(4), 0, 0.0, valid=False),
               (2, 0): RegistrationOutcome("fpfh_ransac", relative_transform(poses, 2, 0), 50, 0.0)}
    calls = iter([(1, 0), (2, 0), (2, 1)])

    def fake_register(solver, src, tgt, voxel, seed):
        key = next(calls)
        return answers.get(key, RegistrationOutcome("fpfh_ransac", relative_transform(poses, *key), 40, 0.0))

    monkeypatch.setattr(gr, "register", fake_register)
    res = evaluate_pairs(scans, poses, np.array([[1, 0], [2, 0], [2, 1]]), solvers=["fpfh_ransac"], progress=False)
    rows = res["pairs"]
    assert [r["success"] for r in rows] == [False, True, True] and [r["valid"] for r in rows] == [False, True, True]
    assert rows[0]["rot_err_deg"] < 10 and rows[0]["trans_err_m"] < 2  # the identity was close enough
    assert res["identity"] == {"n_success": 1, "success_rate": pytest.approx(1 / 3)}
    s = res["summary"]["fpfh_ransac"]
    assert s["n_invalid"] == 1 and s["n_success"] == 2 and s["n_nontrivial"] == 2
    assert s["success_rate_nontrivial"] == 1.0


def test_pair_files_are_checked(tmp_path: Path) -> None:
    path = tmp_path / "pairs.json"
    for doc, message in [({"pairs": [[3, 3]]}, r"pair row 0 \[3, 3\] is not two different frames"),
                         ({"pairs": [[5, 1], [2, -1]]}, r"pair row 1 \[2, -1\]"),
                         ({"pairs": [[1, 2, 3]]}, "rows of two frame numbers"),
                         ({"pairs": [[3.7, 1.2]]}, r"pair row 0 \[3.7, 1.2\] is not two whole frame numbers"),
                         ({"seed": 0}, "no 'pairs' entry")]:
        path.write_text(json.dumps(doc))
        with pytest.raises(ValueError, match=message):
            load_pairs(path)
    path.write_bytes(b"\x89PNG\r\n")
    with pytest.raises(ValueError, match="pairs.json: not a pair file"):
        load_pairs(path)


def _hard_pair() -> tuple[np.ndarray, np.ndarray]:
    """A street corner seen from two poses 4.5 m and 40 deg apart, with 15 cm noise and half of each
    scan cut away: a pair on which KISS-Matcher's answer depended on thread scheduling."""
    rng = np.random.default_rng(1)
    ground = np.c_[rng.uniform(-30, 30, (20000, 2)), np.full(20000, -1.7) + rng.normal(0, 0.01, 20000)]
    walls = [np.c_[np.full(5000, x0), rng.uniform(-30, 30, 5000), rng.uniform(-1.7, 4, 5000)] for x0 in (-15, 12)]
    walls += [np.c_[rng.uniform(-15, 12, 5000), np.full(5000, y0), rng.uniform(-1.7, 4, 5000)] for y0 in (-20, 18)]
    boxes = [np.c_[rng.uniform(a, a + 2, (1500, 2)), rng.uniform(-1.7, b, 1500)]
             for a, b in zip(rng.uniform(-10, 10, 8), rng.uniform(0, 3, 8))]
    world = np.vstack([ground, *walls, *boxes])
    T = make_T([0.0, 0.0, 0.7], [4.0, -2.0, 0.1])
    src = (world - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 0.15, world.shape)
    tgt = world + rng.normal(0, 0.15, world.shape)
    return src[src[:, 0] > -3], tgt[tgt[:, 1] < 5]


@pytest.mark.skipif(not kiss_matcher_available(), reason="kiss-matcher not installed")
def test_kiss_matcher_gives_the_same_answer_in_every_call_and_process(tmp_path: Path) -> None:
    src, tgt = _hard_pair()
    outs = [register_kiss_matcher(src, tgt, voxel=0.5) for _ in range(3)]
    for o in outs[1:]:
        np.testing.assert_array_equal(o.T, outs[0].T)
        assert (o.n_inliers, o.valid) == (outs[0].n_inliers, outs[0].valid)
    np.save(tmp_path / "src.npy", src)
    np.save(tmp_path / "tgt.npy", tgt)
    code = ("import sys, numpy as np\n"
            "from gr_graph.global_solvers import register_kiss_matcher\n"
            "if __name__ == '__main__':\n"
            f"    o = register_kiss_matcher(np.load(r'{tmp_path / 'src.npy'}'), np.load(r'{tmp_path / 'tgt.npy'}'), voxel=0.5)\n"
            f"    np.save(r'{tmp_path / 'T.npy'}', o.T)\n")
    (tmp_path / "other.py").write_text(code)
    subprocess.run([sys.executable, str(tmp_path / "other.py")], check=True, cwd=REPO, timeout=300)
    np.testing.assert_array_equal(np.load(tmp_path / "T.npy"), outs[0].T)


@pytest.mark.skipif(not kiss_matcher_available(), reason="kiss-matcher not installed")
def test_a_script_without_a_main_guard_runs_once(tmp_path: Path) -> None:
    """The worker is started with -m: it never imports the caller's script (spawn would run it again)."""
    script = tmp_path / "plain.py"
    script.write_text("import numpy as np\n"
                      "from gr_graph.global_solvers import register_kiss_matcher, worker_cpu_seconds\n"
                      f"open(r'{tmp_path / 'runs.txt'}', 'a').write('ran\\n')\n"
                      "rng = np.random.default_rng(0)\n"
                      "pts = rng.uniform(-20, 20, (3000, 3))\n"
                      "out = register_kiss_matcher(pts, pts, voxel=0.5)\n"
                      "print(out.valid, worker_cpu_seconds() > 0)\n")
    res = subprocess.run([sys.executable, str(script)], cwd=REPO, timeout=300, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "runs.txt").read_text() == "ran\n" and res.stdout.split()[-1] == "True"


@pytest.mark.skipif(not kiss_matcher_available(), reason="kiss-matcher not installed")
def test_a_worker_that_dies_is_started_again_once_then_the_evaluation_stops(monkeypatch: pytest.MonkeyPatch) -> None:
    import os
    import signal

    import gr_graph.global_solvers as gs

    worker = gs._BoundWorker()
    monkeypatch.setattr(gs, "_WORKER", worker)
    src, tgt = _hard_pair()
    first = register_kiss_matcher(src, tgt, voxel=0.5)
    os.kill(worker._proc.pid, signal.SIGKILL)  # a crash in the native library, or the OOM killer
    worker._proc.wait()
    again = register_kiss_matcher(src, tgt, voxel=0.5)  # started again, the same answer
    np.testing.assert_array_equal(again.T, first.T)
    assert worker.cpu_seconds > 0
    worker.close()
    monkeypatch.setattr(worker, "_start", lambda: subprocess.Popen(
        [sys.executable, "-c", "import sys; sys.exit(3)"], stdin=subprocess.PIPE, stdout=subprocess.PIPE))
    poses = np.stack([np.eye(4), make_T([0, 0, 0.1], [3.0, 0, 0])])
    with pytest.raises(gs.SolverCrashError, match="died twice on one pair \\(exit code 3"):
        evaluate_pairs([src, tgt], poses, np.array([[1, 0]]), solvers=["kiss_matcher"], progress=False)


def test_a_pair_the_solver_cannot_take_is_a_failure_not_a_lost_run(monkeypatch: pytest.MonkeyPatch) -> None:
    """A scan with too few points (e.g. densified into nothing) fails its pairs; the others are kept."""
    import gr_graph.global_registration as gr
    from gr_graph.global_solvers import RegistrationOutcome

    poses = np.stack([np.eye(4), make_T([0, 0, 0.1], [3.0, 0, 0]), make_T([0, 0, 0.2], [6.0, 0, 0])])
    scans = [np.random.default_rng(0).uniform(-5, 5, (50, 3)), np.zeros((5, 3)), np.ones((50, 3))]
    real = gr.register

    def register(solver, src, tgt, voxel, seed):
        if len(src) < 10:
            return real(solver, src, tgt, voxel=voxel, seed=seed)  # the solver's own check raises
        return RegistrationOutcome(solver, relative_transform(poses, 2, 0), 30, 0.0)

    monkeypatch.setattr(gr, "register", register)
    res = evaluate_pairs(scans, poses, np.array([[1, 0], [2, 0]]), solvers=["fpfh_ransac"], progress=False)
    bad, good = res["pairs"]
    assert "ValueError" in bad["error"] and not bad["valid"] and not bad["success"]
    assert good["success"] and "error" not in good
    s = res["summary"]["fpfh_ransac"]
    assert (s["n_pairs"], s["n_success"], s["n_errors"], s["n_invalid"]) == (2, 1, 1, 1)


def test_pair_sampling_options_are_checked(kitti_root: Path, tmp_path: Path, capsys) -> None:
    from gr_graph.global_registration import main

    poses = np.tile(np.eye(4), (30, 1, 1))
    poses[:, 0, 3] = np.arange(30.0)
    with pytest.raises(ValueError, match="min_frame must be integers >= 0"):
        sample_pairs(poses, 10, 10.0, min_frame=-3)  # used to wrap around to the last frames
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "o"), "--min-frame", "-3"])
    assert "--min-frame: -3 is below 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "o"), "--n-pairs", "0"])
    out = tmp_path / "o"
    out.mkdir()
    (out / "results.json").write_text("{}")  # an earlier run's
    code = main(["--out", str(out), "--data-root", str(kitti_root), "--n-pairs", "100", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "only 0 scan pairs" in err and "lower --n-pairs or --min-frame" in err
    assert (out / "results.json").is_file()  # nothing was run: the earlier results stay
