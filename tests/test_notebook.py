"""The marginal-covariance notebook runs on a short SLAM run (so it cannot rot)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "marginal_covariances.ipynb"


@pytest.mark.slow
def test_marginal_covariances_notebook_executes(revisit_run, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    run_dir = revisit_run
    monkeypatch.setenv("GR_GRAPH_RUN_DIR", str(run_dir))
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                            resources={"metadata": {"path": str(NOTEBOOK.parent)}}).execute()
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs
                   if o.get("output_type") == "stream")
    n_images = sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert n_images >= 4  # uncertainty, ellipses, loop drop, NEES
    line = [ln for ln in text.splitlines() if ln.startswith("SUMMARY ")][-1]
    s = json.loads(line[len("SUMMARY "):])
    assert s["run_dir"] == str(run_dir) and s["n_poses"] == 160 and s["n_loops"] >= 3
    assert s["round"] == json.loads((run_dir / "metrics.json").read_text())["final_round"]  # the run's answer
    assert s["nees_poses_left_out"] == 0
    # the loops tie the second stretch (after the flagged jump) to the first: big drop
    assert s["uncertainty_drop_at_loops_median"] > 10
    # NEES is computed against the renderer's ground truth, independently of the notebook
    with np.load(run_dir / "round_0" / "marginals.npz") as z:
        e = z["poses"][1:, :3, 3] - z["gt_poses"][1:, :3, 3]
        nees = np.einsum("ki,kij,kj->k", e, np.linalg.inv(z["position_cov_world"][1:] + 1e-12 * np.eye(3)), e)
    assert np.isclose(s["nees_mean"], nees.mean(), rtol=1e-6)
    assert np.isfinite(s["nees_mean"]) and 0 < s["nees_frac_below_95"] <= 1


def test_committed_notebook_shows_its_figures() -> None:
    """The repository's copy carries its outputs (figures visible on a code host), made by
    ``python scripts/regenerate_notebook.py`` on a run named relative to the repository."""
    nb = json.loads(NOTEBOOK.read_text())
    outputs = [o for c in nb["cells"] if c["cell_type"] == "code" for o in c.get("outputs", [])]
    assert sum("image/png" in o.get("data", {}) for o in outputs) >= 4
    assert all(c.get("execution_count") for c in nb["cells"] if c["cell_type"] == "code")
    text = json.dumps(outputs)
    assert "SUMMARY " in text and "/tmp/" not in text and "/home/" not in text
