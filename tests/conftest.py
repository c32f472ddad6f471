"""Shared fixtures: the real LiDAR files in ``../shared/data`` (skipped when absent)."""

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
