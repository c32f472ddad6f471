"""``densify_cloud`` and ``gr-densify``: one cloud densified with a network checkpoint, the same
way the learning rounds densify a scan; checkpoints checked on load; cloud files in and out."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gr_graph.cloud_io import read_cloud, read_ply_covariances, write_cloud
from gr_graph.config import PreprocessConfig, TrainingConfig
from gr_graph.datasets.base import DatasetError, LidarFrame
from gr_graph.densify import densified_sequence, densify_cloud
from gr_graph.densify_cli import main as densify_main
from gr_graph.preprocess import preprocess_scan
from training.densify import anisotropy
from training.network import CovarianceNet, NetConfig
from training.predict import predict_covariances
from training.trainer import CHECKPOINT_FORMAT, TrainingError, load_model, save_atomic

REPO = Path(__file__).resolve().parents[1]
SMALL_NET = NetConfig(n_points=512, k0=8, k1=8, k2=8, c0=16, c1=16, c2=16, kw=8)


def street_cloud(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A ground plane, two walls and clutter around the origin, with intensity."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-12, 12, (6000, 2))
    xy = xy[np.linalg.norm(xy, axis=1) > 4.0]
    ground = np.column_stack([xy, -1.73 + rng.normal(0, 0.01, len(xy))])
    wall = np.column_stack([rng.uniform(-12, 12, 2000), np.full(2000, 8.0), rng.uniform(-1.7, 4, 2000)])
    wall2 = wall * [1, -1, 1]
    clutter = rng.uniform([-10, -10, 0], [10, 10, 3], (500, 3))
    pts = np.vstack([ground, wall, wall2, clutter])
    return pts, rng.uniform(0, 1, len(pts)).astype(np.float32)


class OneFrame:
    """A one-frame LidarSequence."""

    name = "one"
    timestamps = np.zeros(1)
    gt_poses = None
    T_cam_velo = np.eye(4)

    def __init__(self, points: np.ndarray, intensity: np.ndarray) -> None:
        self.frame = LidarFrame(index=0, timestamp=0.0, points=points, intensity=intensity, n_rings=64)

    def __len__(self) -> int:
        return 1

    def __getitem__(self, i: int) -> LidarFrame:
        return self.frame


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    """An untrained CovarianceNet with fixed seed, saved as the trainer saves model.pt."""
    torch.manual_seed(0)
    net = CovarianceNet(SMALL_NET)
    path = tmp_path_factory.mktemp("model") / "model.pt"
    save_atomic({"format_version": CHECKPOINT_FORMAT, "model_state": net.state_dict(),
                 "net_config": net.config.to_dict()}, path)
    return path


@pytest.fixture(scope="module")
def pcd_file(tmp_path_factory) -> Path:
    """The street cloud written by open3d (legacy API) as PCD, with intensity via the tensor API."""
    import open3d as o3d

    pts, inten = street_cloud()
    path = tmp_path_factory.mktemp("cloud") / "scan.pcd"
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts.astype(np.float32)))
    cloud.point.intensity = o3d.core.Tensor(inten.reshape(-1, 1))
    assert o3d.t.io.write_point_cloud(str(path), cloud)
    return path


#: the paper's Algorithm 2 (the samples replace the anisotropic points, the others are dropped), not the default
PAPER = {"keep_original": False, "keep_dropped": False}


def _median_anisotropy(model_path: Path, points: np.ndarray) -> float:
    s = preprocess_scan(points, PreprocessConfig()).points
    return float(np.median(anisotropy(predict_covariances(model_path, s, seed=0))))


def test_densify_cloud_is_algorithm_2_on_the_preprocessed_cloud(model_path: Path) -> None:
    pts, inten = street_cloud()
    tau = _median_anisotropy(model_path, pts)  # about half the points pass
    res = densify_cloud(pts, model_path, intensity=inten, tau_ani=tau, samples_per_point=3, seed=2, **PAPER)
    # independent reference: preprocessing, the network, the filter, per-point Gaussians
    s = preprocess_scan(pts, PreprocessConfig()).points
    C = predict_covariances(load_model(model_path), s, seed=2)
    kept = anisotropy(C) > tau
    np.testing.assert_array_equal(res.network_input, s)
    np.testing.assert_array_equal(res.kept, kept)
    assert 0.3 < kept.mean() < 0.7 and res.fallback is None
    assert res.points.shape == (3 * kept.sum(), 3)
    np.testing.assert_array_equal(res.source, np.repeat(np.flatnonzero(kept), 3))
    np.testing.assert_allclose(res.covariances, C[res.source], atol=1e-12)
    # every sample is near its source point in the metric of its covariance (chi^2(3) tail)
    d = res.points - s[res.source]
    m2 = np.einsum("ni,nij,nj->n", d, np.linalg.inv(res.covariances), d)
    assert np.quantile(m2, 0.99) < 20.0 and 2.0 < m2.mean() < 4.0
    # intensity of the nearest raw point of each source point (a voxel centroid of two raw points
    # is as near to both: either one's intensity)
    from scipy.spatial import cKDTree

    d, j = cKDTree(pts).query(s[res.source], k=4)
    tied = d <= d[:, :1] * (1 + 1e-9) + 1e-12
    assert (tied & (inten[j] == res.intensity[:, None])).any(1).all()
    assert tied[:, 1].mean() < 0.5  # the check above has teeth: most points have one nearest raw point
    # same as frame 0 of the pipeline's densified view with the same settings
    cfg = TrainingConfig(tau_ani=tau, samples_per_point=3, seed=2, **PAPER)
    view = densified_sequence(OneFrame(pts, inten), model_path, cfg)
    np.testing.assert_array_equal(view[0].points, res.points)
    # deterministic; another seed samples differently
    again = densify_cloud(pts, model_path, tau_ani=tau, samples_per_point=3, seed=2, **PAPER)
    np.testing.assert_array_equal(again.points, res.points)
    other_seed = densify_cloud(pts, model_path, tau_ani=tau, samples_per_point=3, seed=3, **PAPER)
    assert not np.array_equal(other_seed.points, res.points)


def test_densify_cloud_refuses_bad_input(model_path: Path) -> None:
    with pytest.raises(ValueError, match="weights is required"):
        densify_cloud(np.zeros((10, 3)), None)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        densify_cloud(np.zeros((10, 2)), model_path)
    with pytest.raises(ValueError, match="after preprocessing"):
        densify_cloud(np.random.default_rng(0).uniform(5, 6, (50, 3)), model_path)
    with pytest.raises(ValueError, match="tau_ani"):
        densify_cloud(street_cloud()[0], model_path, tau_ani=1.5)
    pts, inten = street_cloud()
    with pytest.raises(ValueError, match=f"{len(pts) - 1} intensities for {len(pts)} points"):
        densify_cloud(pts, model_path, intensity=inten[:-1])
    nan_inten = inten.copy()
    nan_inten[::2] = np.nan  # set to 0, as the file readers do, never passed on as NaN
    res = densify_cloud(pts, model_path, intensity=nan_inten)
    assert np.isfinite(res.intensity).all() and (res.intensity == 0).any()


def test_gr_densify_pcd_to_ply_with_covariances(model_path: Path, pcd_file: Path, tmp_path: Path, capsys) -> None:
    import open3d as o3d

    pts, inten = read_cloud(pcd_file)
    assert len(pts) == len(street_cloud()[0]) and inten is not None
    out, cov = tmp_path / "dense.ply", tmp_path / "dense_cov.npy"
    argv = [str(pcd_file), str(out), "--weights", str(model_path), "--tau-ani", "0.0", "--samples", "2",
            "--covariances", str(cov), "--ply-covariances", "--seed", "1", "--no-keep-original", "--no-keep-dropped"]
    assert densify_main(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    ref = densify_cloud(pts, model_path, intensity=inten, tau_ani=0.0, samples_per_point=2, seed=1, **PAPER)
    assert summary["input_points"] == len(pts) and summary["kept_points"] == ref.n_kept
    assert summary["output_points"] == 2 * ref.n_kept == len(ref.points)
    # the PLY as open3d reads it (legacy reader: positions only; tensor reader: the properties)
    legacy = np.asarray(o3d.io.read_point_cloud(str(out)).points)
    np.testing.assert_allclose(legacy, ref.points.astype(np.float32), atol=0)
    C = np.load(cov)
    assert C.shape == (len(ref.points), 3, 3)
    np.testing.assert_array_equal(C, np.transpose(C, (0, 2, 1)))
    assert np.linalg.eigvalsh(C).min() > 0  # positive definite
    np.testing.assert_array_equal(read_ply_covariances(out), C)
    _, out_inten = read_cloud(out)
    np.testing.assert_array_equal(out_inten, ref.intensity)


def test_gr_densify_keep_dropped_and_original_adds_samples_to_every_point(model_path: Path, pcd_file: Path,
                                                                          tmp_path: Path, capsys) -> None:
    """By default (``--keep-original --keep-dropped``) the network's whole input comes back, plus M samples
    per point above the anisotropy threshold (the same samples as the paper's densification draws)."""
    pts, inten = read_cloud(pcd_file)
    out, out_flags = tmp_path / "dense.npy", tmp_path / "dense_flags.npy"
    argv = [str(pcd_file), str(out), "--weights", str(model_path), "--tau-ani", "0.5", "--samples", "2", "--seed", "1"]
    assert densify_main(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert densify_main([str(pcd_file), str(out_flags), *argv[2:], "--keep-original", "--keep-dropped"]) == 0
    np.testing.assert_array_equal(np.load(out_flags), np.load(out))
    plain = densify_cloud(pts, model_path, intensity=inten, tau_ani=0.5, samples_per_point=2, seed=1, **PAPER)
    n_in, n_kept = len(plain.network_input), plain.n_kept
    assert 0 < n_kept < n_in  # the threshold splits the cloud: both branches are exercised
    assert summary["output_points"] == n_in + 2 * n_kept
    back, _ = read_cloud(out)
    samples = back[n_kept: n_kept + 2 * n_kept]
    np.testing.assert_allclose(samples, plain.points.astype(np.float32), atol=1e-6)
    originals = np.vstack([back[:n_kept], back[3 * n_kept:]])
    def rows_sorted(a: np.ndarray) -> np.ndarray:  # whole points in lexicographic order (not column by column)
        a = np.asarray(a, np.float32)
        return a[np.lexsort(a.T[::-1])]

    np.testing.assert_allclose(rows_sorted(originals), rows_sorted(plain.network_input), atol=1e-5)


@pytest.mark.parametrize("suffix", [".pcd", ".bin", ".npy"])
def test_gr_densify_writes_the_format_of_out(model_path: Path, pcd_file: Path, tmp_path: Path, suffix: str,
                                             capsys) -> None:
    out = tmp_path / f"dense{suffix}"
    assert densify_main([str(pcd_file), str(out), "--weights", str(model_path), "--tau-ani", "0.0",
                         "--samples", "1"]) == 0
    n = json.loads(capsys.readouterr().out)["output_points"]
    back, _ = read_cloud(out)
    assert back.shape == (n, 3) and n > 1000


@pytest.mark.slow
def test_gr_densify_as_a_module(model_path: Path, pcd_file: Path, tmp_path: Path) -> None:
    """``python -m gr_graph.densify_cli`` on a .npy input (x,y,z,intensity)."""
    pts, inten = street_cloud(1)
    np.save(tmp_path / "in.npy", np.column_stack([pts, inten]).astype(np.float32))
    out = tmp_path / "out.ply"
    r = subprocess.run([sys.executable, "-m", "gr_graph.densify_cli", str(tmp_path / "in.npy"), str(out),
                        "--weights", str(model_path), "--tau-ani", "0.0", "--samples", "1"],
                       cwd=REPO, capture_output=True, text=True, timeout=300,
                       env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["output_points"] == len(read_cloud(out)[0])


def test_checkpoints_are_checked_on_load(model_path: Path, tmp_path: Path) -> None:
    state = torch.load(model_path, weights_only=False)
    # an old checkpoint without format_version loads as before
    old = {k: v for k, v in state.items() if k != "format_version"}
    save_atomic(old, tmp_path / "old.pt")
    a, b = load_model(tmp_path / "old.pt"), load_model(model_path)
    assert all(torch.equal(a.state_dict()[k], b.state_dict()[k]) for k in a.state_dict())
    # a newer format, a config this network does not know, weights of another size: errors naming the file
    save_atomic({**state, "format_version": CHECKPOINT_FORMAT + 1}, tmp_path / "new.pt")
    with pytest.raises(TrainingError, match=r"new\.pt.*newer"):
        load_model(tmp_path / "new.pt")
    save_atomic({**state, "net_config": {**state["net_config"], "depth": 9}}, tmp_path / "unknown.pt")
    with pytest.raises(TrainingError, match=r"(?s)unknown\.pt.*network configuration.*depth"):
        load_model(tmp_path / "unknown.pt")
    save_atomic({**state, "net_config": {**state["net_config"], "c2": 32}}, tmp_path / "mismatch.pt")
    with pytest.raises(TrainingError, match=r"mismatch\.pt: the weights do not fit"):
        load_model(tmp_path / "mismatch.pt")
    (tmp_path / "text.pt").write_text("not a checkpoint")
    with pytest.raises(TrainingError, match=r"text\.pt: not a torch checkpoint"):
        load_model(tmp_path / "text.pt")
    save_atomic({"weights": 1}, tmp_path / "foreign.pt")
    with pytest.raises(TrainingError, match=r"foreign\.pt: not a training checkpoint"):
        load_model(tmp_path / "foreign.pt")


def test_gr_densify_errors_name_the_file(model_path: Path, pcd_file: Path, tmp_path: Path, capsys) -> None:
    cases = [
        ([str(tmp_path / "missing.pcd"), str(tmp_path / "o.ply"), "--weights", str(model_path)], "missing.pcd"),
        ([str(pcd_file), str(tmp_path / "o.ply"), "--weights", str(tmp_path / "nope.pt")], "nope.pt"),
        ([str(pcd_file), str(tmp_path / "o.xyz"), "--weights", str(model_path)], "o.xyz"),
        ([str(pcd_file), str(tmp_path / "o.pcd"), "--weights", str(model_path), "--ply-covariances"], "o.pcd"),
    ]
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((10, 2)))
    cases.append(([str(bad), str(tmp_path / "o.ply"), "--weights", str(model_path)], "bad.npy"))
    # --covariances that would overwrite OUT or IN, and a range crop that leaves nothing, are refused at once
    cases.append(([str(pcd_file), str(tmp_path / "o.npy"), "--weights", str(model_path), "--covariances",
                   str(tmp_path / "o.npy")], "o.npy: --covariances is OUT"))
    cases.append(([str(bad), str(tmp_path / "o.ply"), "--weights", str(model_path), "--covariances", str(bad)],
                  "bad.npy: --covariances is IN"))
    cases.append(([str(tmp_path / "missing.pcd"), str(tmp_path / "o.ply"), "--min-range", "50", "--max-range", "10"],
                  "--min-range 50 m is not below --max-range 10 m"))
    # an OUT of unknown format is refused before anything is read (the input does not even exist)
    cases.append(([str(tmp_path / "missing.pcd"), str(tmp_path / "o.xyz"), "--weights", str(model_path)],
                  "o.xyz: unknown point cloud format"))
    (tmp_path / "a_file").write_text("")  # OUT inside a file: the OS refuses, the message names it
    cases.append(([str(pcd_file), str(tmp_path / "a_file" / "o.ply"), "--weights", str(model_path)], "a_file"))
    for argv, name in cases:
        assert densify_main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("error: ") and name in err, err
    assert not list(tmp_path.glob("o.*"))  # nothing written
    np.testing.assert_array_equal(np.load(bad), np.zeros((10, 2)))  # IN untouched

    # bad option values are named by their option, before anything is read (the input does not exist)
    for option, value, message in (("--tau-ani", "1.0", "argument --tau-ani: 1.0 is not in [0, 1)"),
                                   ("--samples", "0", "argument --samples: 0 is below 1"),
                                   ("--voxel-size", "0", "argument --voxel-size: 0 is not a finite number > 0"),
                                   ("--min-range", "-1", "argument --min-range: -1 is below 0")):
        with pytest.raises(SystemExit):
            densify_main([str(tmp_path / "missing.pcd"), str(tmp_path / "o.ply"), option, value])
        assert message in capsys.readouterr().err


def test_read_ply_covariances_names_a_missing_or_foreign_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="missing.ply: point file not found"):
        read_ply_covariances(tmp_path / "missing.ply")
    write_cloud(tmp_path / "c.pcd", np.random.default_rng(0).normal(size=(20, 3)))
    with pytest.raises(DatasetError, match="c.pcd: not a PLY file"):
        read_ply_covariances(tmp_path / "c.pcd")


def test_gr_densify_writes_covariances_under_an_upper_case_suffix(model_path: Path, pcd_file: Path,
                                                                   tmp_path: Path) -> None:
    out, cov = tmp_path / "dense.ply", tmp_path / "COV.NPY"
    assert densify_main([str(pcd_file), str(out), "--weights", str(model_path), "--covariances", str(cov)]) == 0
    C = np.load(cov)  # numpy would have written "COV.NPY.npy" beside an empty COV.NPY
    assert C.ndim == 3 and C.shape[1:] == (3, 3) and len(C) == len(read_cloud(out)[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["COV.NPY", "dense.ply"]


def test_write_cloud_round_trips(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    x, i = rng.normal(size=(300, 3)) * 10, rng.random(300).astype(np.float32)
    A = rng.normal(size=(300, 3, 3))
    C = A @ A.transpose(0, 2, 1)
    for suffix in (".ply", ".pcd", ".bin", ".npy", ".NPY"):  # numpy would append .npy to a .NPY name
        p = write_cloud(tmp_path / f"c{suffix}", x, i, C if suffix == ".ply" else None)
        back, bi = read_cloud(p)
        np.testing.assert_array_equal(back, x.astype(np.float32))
        np.testing.assert_array_equal(bi, i)
    assert not list(tmp_path.glob("*.NPY.npy")) and not list(tmp_path.glob(".*"))  # no stray file beside it
    np.testing.assert_array_equal(read_ply_covariances(tmp_path / "c.ply"), C)
    x0 = x.copy()
    x0[2] = 0.0  # a point exactly at the origin: read_cloud drops it (no return), the covariances follow
    write_cloud(tmp_path / "origin.ply", x0, i, C)
    back, _ = read_cloud(tmp_path / "origin.ply")
    np.testing.assert_array_equal(back, np.delete(x0, 2, axis=0).astype(np.float32))
    np.testing.assert_array_equal(read_ply_covariances(tmp_path / "origin.ply"), np.delete(C, 2, axis=0))
    with pytest.raises(ValueError, match="only"):
        write_cloud(tmp_path / "c.pcd", x, covariances=C)
    with pytest.raises(DatasetError, match="unknown point cloud format"):
        read_cloud(tmp_path / "c.txt")
    for suffix in (".ply", ".pcd", ".bin", ".npy"):  # read_cloud refuses an empty cloud: none is written
        with pytest.raises(ValueError, match=rf"empty{suffix}: no points to write"):
            write_cloud(tmp_path / f"empty{suffix}", np.zeros((0, 3)))
    assert not list(tmp_path.glob("empty*"))


def test_source_intensity_is_the_nearest_raw_points() -> None:
    """Intensity of a densified point = its source point's nearest raw point (brute force);
    non-finite raw rows are skipped, no finite raw point gives zeros."""
    from gr_graph.densify import source_intensity

    rng = np.random.default_rng(4)
    raw = rng.uniform(-20, 20, (3000, 3))
    raw[::50] = np.nan
    inten = rng.uniform(0, 1, len(raw)).astype(np.float32)
    q = rng.uniform(-20, 20, (400, 3))
    D = ((q[:, None] - raw[None]) ** 2).sum(-1)
    D[np.isnan(D)] = np.inf
    np.testing.assert_array_equal(source_intensity(raw, inten, q), inten[np.argmin(D, 1)])
    assert not source_intensity(np.full((4, 3), np.nan), inten[:4], q).any()
    assert source_intensity(raw, None, q).shape == (400,)
    q[3] = np.nan  # a non-finite query has no nearest point: an error, not some point's intensity
    with pytest.raises(ValueError, match="finite"):
        source_intensity(raw, inten, q)


def test_densified_frames_keep_the_sensor_times_of_their_source_points() -> None:
    """A frame with per-point times: every densified point carries the time of the raw point nearest
    to its source point (the preprocessed point it was sampled around), as intensity does."""
    from gr_graph.config import PreprocessConfig, TrainingConfig
    from gr_graph.datasets.base import LidarFrame
    from gr_graph.densify import densified_sequence, nearest_raw_rows
    from gr_graph.preprocess import preprocess_scan

    pts, inten = street_cloud()
    az = np.arctan2(pts[:, 1], pts[:, 0])
    time = (az + np.pi) / (2 * np.pi)  # a sweep fraction per point

    class OneFrame:
        name = "one-frame"
        timestamps = np.zeros(1)
        gt_poses = None
        T_cam_velo = np.eye(4)
        motion_compensated = False

        def __len__(self) -> int:
            return 1

        def __getitem__(self, i: int) -> LidarFrame:
            return LidarFrame(index=0, timestamp=0.0, points=pts, intensity=inten, time=time)

    def planes(p: np.ndarray) -> np.ndarray:  # anisotropic everywhere: every point kept and sampled
        return np.tile(np.diag([0.04, 0.04, 1e-4]), (len(p), 1, 1))

    pre = PreprocessConfig()
    frame = densified_sequence(OneFrame(), planes, TrainingConfig(), preprocess=pre)[0]
    s = preprocess_scan(pts, pre, index=0).points
    rows = nearest_raw_rows(pts, s)
    assert frame.time is not None and len(frame.time) == len(frame.points) > len(s)
    # each output point's time is that of a source point; the kept originals exactly their own
    assert set(np.unique(frame.time)) <= set(np.unique(time[rows]))
    where = {tuple(p): k for k, p in enumerate(s)}
    originals = [(o, where[tuple(p)]) for o, p in enumerate(frame.points) if tuple(p) in where]
    assert len(originals) == len(s)
    out_rows, s_rows = np.array(originals).T
    np.testing.assert_array_equal(frame.time[out_rows], time[rows][s_rows])
    np.testing.assert_array_equal(frame.intensity[out_rows], inten[rows][s_rows])


def test_gr_densify_counts_the_points_it_drops(model_path: Path, tmp_path: Path, capsys, caplog) -> None:
    """Points without a return (NaN, or exactly the origin) are dropped on reading: logged and counted in the
    summary (``input_points`` are those kept)."""
    pts, inten = street_cloud()
    cloud = np.column_stack([pts, inten])
    cloud[::50, :3] = np.nan
    cloud[1, :3] = 0.0
    n_bad = len(cloud[::50]) + 1
    np.save(tmp_path / "in.npy", cloud)
    with caplog.at_level("WARNING", logger="gr_graph.cloud_io"):
        assert densify_main([str(tmp_path / "in.npy"), str(tmp_path / "o.ply"), "--weights", str(model_path)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["dropped_points"] == n_bad and summary["input_points"] == len(cloud) - n_bad
    assert f"in.npy: dropped {n_bad} points without a return" in caplog.text


def test_cloud_files_truncated_or_not_written_are_errors_naming_them(tmp_path: Path, monkeypatch) -> None:
    """A truncated PLY is an error for its covariances too (open3d returned uninitialised rows); a write that
    fails (a full disk) names the file and leaves nothing behind."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-10, 10, (50, 3))
    p = write_cloud(tmp_path / "t.ply", x, None, np.tile(np.eye(3), (50, 1, 1)))
    data = p.read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) // 2])
    for read in (read_cloud, read_ply_covariances):
        with pytest.raises(DatasetError, match=r"cut.ply: .* truncated"):
            read(tmp_path / "cut.ply")

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "save", full_disk)
    with pytest.raises(OSError, match=r"cannot write .*full.npy: No space left") as err:
        write_cloud(tmp_path / "full.npy", x)
    assert err.value.errno == 28  # the same kind of error, now naming the file
    assert not list(tmp_path.glob("full*")) and not list(tmp_path.glob(".*"))


def test_cloudcompare_intensity_is_read_whatever_its_case(tmp_path: Path) -> None:
    from gr_graph.cloud_io import write_ply

    rng = np.random.default_rng(1)
    x, i = rng.uniform(-10, 10, (40, 3)), rng.random(40).astype(np.float32)
    write_ply(tmp_path / "cc.ply", x, extra={"scalar_Intensity": i})
    np.testing.assert_array_equal(read_cloud(tmp_path / "cc.ply")[1], i)
    # a name as written wins over one in another case, and over a preferred name in another case
    for extra, wanted in (({"Intensity": i + 1, "intensity": i}, i), ({"reflectance": i, "scalar_Intensity": i + 1}, i)):
        write_ply(tmp_path / "two.ply", x, extra={k: v.astype(np.float32) for k, v in extra.items()})
        np.testing.assert_array_equal(read_cloud(tmp_path / "two.ply")[1], wanted)
