"""Shared fixtures: the real LiDAR files (skipped when absent) and a private home directory.

The real LiDAR files are looked up in ``$GR_GRAPH_TEST_DATA`` when set, else in
``../shared/data`` beside the checkout. Only tests that need a real LiDAR recording use them;
every other test generates its data.

The tests never write into the user's home: ``HOME`` (and with it evo's settings folder
``~/.evo`` and matplotlib's cache) points to a temporary directory for the whole session,
also for the subprocesses the tests start.

The short synthetic SLAM runs that several test modules read are made once per session
(fixtures ``revisit_run`` and ``learning_run``). The synthetic towns stay cached for the whole
session: a pipeline frees the town of a sequence it opened after each round (about 2 GB on
the full route), and the tests run dozens of pipelines on the same few towns, each rebuild
20-30 s; that release is tested by the tests marked ``frees_render_cache``.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA_ENV = "GR_GRAPH_TEST_DATA"
SHARED_DATA = Path(os.environ.get(DATA_ENV) or REPO.parent / "shared" / "data")
REAL_HOME = Path.home()
_PRIVATE_HOME = tempfile.TemporaryDirectory(prefix="gr_graph-test-home-")


def pytest_configure(config: pytest.Config) -> None:
    """Point HOME (and matplotlib's config dir) at a temporary directory before any test runs."""
    os.environ["HOME"] = _PRIVATE_HOME.name
    os.environ.setdefault("MPLCONFIGDIR", os.path.join(_PRIVATE_HOME.name, ".config", "matplotlib"))


def pytest_unconfigure(config: pytest.Config) -> None:
    os.environ["HOME"] = str(REAL_HOME)
    _PRIVATE_HOME.cleanup()


@pytest.fixture(scope="session", autouse=True)
def _keep_synthetic_towns():
    """Pipelines keep their synthetic town in the cache during the tests (module docstring)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("gr_graph.pipeline.release_render_cache", lambda sequence: False)
        yield


@pytest.fixture(autouse=True)
def _free_towns_where_tested(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """Tests marked ``frees_render_cache`` run the pipeline's real release."""
    if request.node.get_closest_marker("frees_render_cache") is not None:
        from gr_graph.datasets.base import release_render_cache

        monkeypatch.setattr("gr_graph.pipeline.release_render_cache", release_render_cache)


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"needs real LiDAR data: {path} not found (set {DATA_ENV} to a folder laid out like "
                    f"../shared/data: kitti/, kitti00_gt/, small_gicp_pair/)")
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
