"""Shared fixtures: the real LiDAR files in ``../shared/data`` (skipped when absent) and the
short synthetic SLAM runs that several test modules read (made once per session)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real LiDAR test data not found at {path} (../shared/data is absent)")
    return path


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    """Root of the real KITTI odometry excerpt (sequence 00, frames 0-5)."""
    return _require(SHARED_DATA / "kitti")


@pytest.fixture(scope="session")
def kitti00_gt_dir() -> Path:
    """Folder with the full official KITTI 00 ground truth (camera frame) and times."""
    return _require(SHARED_DATA / "kitti00_gt")


@pytest.fixture(scope="session")
def small_gicp_pair_dir() -> Path:
    """Folder with small_gicp's real scan pair and its reference transform."""
    return _require(SHARED_DATA / "small_gicp_pair")


@pytest.fixture(scope="session")
def revisit_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Output directory of the short synthetic revisit run (``slam_support.run_revisit``)."""
    from slam_support import run_revisit

    return run_revisit(tmp_path_factory.mktemp("revisit_run"))


@pytest.fixture(scope="session")
def learning_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, tuple[str, ...]]:
    """(run dir, argv) of the short ``--rounds 1`` run (``slam_support.run_learning``)."""
    from slam_support import run_learning

    return run_learning(tmp_path_factory.mktemp("learning_run"))
