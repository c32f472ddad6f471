"""The realism report: local-geometry statistics of KITTI-layout folders."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gr_graph.datasets.realism import chosen_frames, frame_statistics, local_eigenvalues, main


def _noisy_ground(n: int, sigma: float, seed: int) -> np.ndarray:
    """A flat ground disc (3-60 m) with Gaussian height noise ``sigma``, dense enough for 0.5 m voxels."""
    rng = np.random.default_rng(seed)
    r = np.sqrt(rng.uniform(3.0**2, 60.0**2, n))
    a = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([r * np.cos(a), r * np.sin(a), rng.normal(-1.7, sigma, n)])


def test_local_eigenvalues_closed_forms() -> None:
    # a 0.5 m grid plane: lambda_min = 0; a line: two zero eigenvalues
    g = np.arange(20) * 0.5
    plane = np.column_stack([np.repeat(g, 20), np.tile(g, 20), np.zeros(400)])
    ev = local_eigenvalues(plane)
    assert np.all(np.abs(ev[:, 0]) < 1e-12) and np.all(ev[:, 1] > 0.01)
    line = np.column_stack([g, 2 * g, -g])
    ev = local_eigenvalues(line)
    assert np.all(np.abs(ev[:, :2]) < 1e-12)
    # the 10 points of a line spaced 0.5 m: variance along it = 0.5^2 (k^2 - 1) / 12 per unit length^2
    inner = ev[5:-5, 2]
    np.testing.assert_allclose(inner, 0.25 * 99 / 12 * (1 + 4 + 1), rtol=1e-9)


def test_thickness_follows_the_surface_noise() -> None:
    thin = frame_statistics(_noisy_ground(200_000, 0.01, 0))
    thick = frame_statistics(_noisy_ground(200_000, 0.10, 0))
    # voxel centroids average the noise of the points in a voxel: thinner than sigma, but ordered
    assert thin.thickness_cm < thick.thickness_cm
    assert 0.2 < thin.thickness_cm < 1.0 and 2.0 < thick.thickness_cm < 10.0
    assert thin.a99 > 0.9 and thick.a99 < thin.a99
    assert thin.frac_beyond_40m == pytest.approx((60**2 - 40**2) / (60**2 - 3**2), abs=0.08)


def test_chosen_frames_spread_and_leave_a_successor() -> None:
    np.testing.assert_array_equal(chosen_frames(6, 50), [0, 1, 2, 3, 4])
    f = chosen_frames(4541, 50)
    assert len(f) == 50 and f[0] == 0 and f[-1] == 4539
    with pytest.raises(ValueError, match="at least 2 frames"):
        chosen_frames(1, 5)


def _write_kitti_folder(root: Path, frames: list[np.ndarray]) -> Path:
    velo = root / "sequences" / "00" / "velodyne"
    velo.mkdir(parents=True)
    for i, p in enumerate(frames):
        np.column_stack([p, np.full(len(p), 0.5)]).astype(np.float32).tofile(velo / f"{i:06d}.bin")
    (root / "sequences" / "00" / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(len(frames))))
    (root / "sequences" / "00" / "calib.txt").write_text(
        "Tr: " + " ".join(f"{v:.1f}" for v in np.eye(4)[:3].ravel()) + "\n")
    return root


def test_cli_compares_folders_and_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    thin = _write_kitti_folder(tmp_path / "thin", [_noisy_ground(60_000, 0.01, s) for s in range(3)])
    thick = _write_kitti_folder(tmp_path / "thick", [_noisy_ground(60_000, 0.08, s) for s in range(3)])
    out = tmp_path / "r.json"
    assert main([str(thin), str(thick), "--out", str(out), "--no-progress"]) == 0
    table = capsys.readouterr().out
    assert "| statistic | thin | thick |" in table and "%)" in table
    res = json.loads(out.read_text())["results"]
    assert [r["frames"] for r in res] == [[0, 1], [0, 1]]
    assert res[1]["mean"]["thickness_cm"] > 2 * res[0]["mean"]["thickness_cm"]
    assert np.isfinite(res[0]["mean"]["vgicp_inlier_rmse_cm"])


def test_missing_folder_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path / "nowhere"), "--no-progress"]) == 1
    assert "nowhere" in capsys.readouterr().err


def test_real_kitti_frames_match_the_published_figures(kitti_root: Path) -> None:
    """Issue 9's table: thickness 9.3 cm, a90 0.69, a99 0.39, ~10,500 points, median 24.9 m, 0.26 beyond 40 m."""
    from gr_graph.datasets.realism import folder_statistics

    m = folder_statistics(kitti_root, progress=False)["mean"]
    assert m["thickness_cm"] == pytest.approx(9.3, abs=0.2)
    assert m["a90"] == pytest.approx(0.69, abs=0.01) and m["a99"] == pytest.approx(0.39, abs=0.01)
    assert m["points_per_frame"] == pytest.approx(10_500, rel=0.02)
    assert m["median_range_m"] == pytest.approx(24.9, abs=0.2) and m["frac_beyond_40m"] == pytest.approx(0.26, abs=0.01)
