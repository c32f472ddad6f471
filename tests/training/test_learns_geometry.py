"""Proof that self-supervised training learns the right thing (known geometry, known noise).

Scene: a 16-channel LiDAR (elevations +2..-24.8 deg, 0.5 deg azimuth steps) in a street of
planes (ground, two walls) and vertical cylinders (poles / trunks, radius 0.3-1 m); every
return is displaced along the true surface normal by N(0, sigma^2), sigma = 2 cm, so the
true local covariance has its smallest eigenvector along the normal with variance sigma^2.
The memory holds 6 scans from varied poses, 9 pairs with the true T̂ and nearest-neighbour
correspondences (as SLAM would produce). f_theta is trained self-supervised (no normals,
no noise level given) and evaluated on a held-out scan from a new pose.

Bounds (measured values in benchmarks/results/training.md, section "What is learned"):
* planar points: median angle(smallest eigenvector, true normal) < 5 deg, >= 75 % within
  10 deg; median normal variance n^T C n within a factor 2 of sigma^2 (0.5 .. 2);
* all points: the learned covariances beat PCA of the raw 16-NN neighbourhood on the same
  points (median angle and fraction within 10 deg), PCA's collinear neighbourhoods on the
  sparse scan lines being the paper's premise; the smallest PCA eigenvalue on the ground is
  off by more than a factor 5 while the learned one is within a factor 2.
Cylinders are harder (thin, few points per scan line); their numbers are reported in the
benchmark, and only a loose bound (median < 45 deg, i.e. better than a random direction's
~60 deg) is asserted here. Honest caveat (see the benchmark): on walls and cylinders PCA with
k >= 10 is more accurate than the learned covariances at this training budget; the learned
ones win overall because of the ground, where k-NN PCA fails on sparse scan lines.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from training.predict import predict_covariances
from training.toy_scenes import normal_angles_deg as _angles
from training.toy_scenes import pca_covariances as _pca
from training.toy_scenes import street_learning_problem
from training.trainer import TrainConfig, Trainer

torch.set_num_threads(1)
SIGMA = 0.02


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    prob = street_learning_problem(sigma=SIGMA)
    cfg = TrainConfig.from_dict({"epochs": 20, "lr": 3e-3, "max_corr": 1024, "progress": False, "net": {"n_points": 4096},
                                 "corr_likelihood": "gaussian"})  # the paper's NLL (the t: the test below)
    out = tmp_path_factory.mktemp("learn")
    path = Trainer(prob.memory, out, cfg).fit(resume=False)
    C = predict_covariances(path, prob.points, n_points=4096)
    return {"pts": prob.points, "nrm": prob.normals, "ids": prob.ids, "C": C, "n_planes": prob.n_planes}


@pytest.mark.slow
def test_planes_normal_and_noise_level_are_learned(trained):
    m = trained["ids"] < trained["n_planes"]
    ang, _ = _angles(trained["C"][m], trained["nrm"][m])
    nvar = np.einsum("ni,nij,nj->n", trained["nrm"][m], trained["C"][m], trained["nrm"][m]) / SIGMA**2
    print(f"planes: median angle {np.median(ang):.2f} deg, within 10 deg {np.mean(ang < 10):.2f}, "
          f"median n^T C n / sigma^2 {np.median(nvar):.2f}")
    assert np.median(ang) < 5.0
    assert np.mean(ang < 10.0) >= 0.75
    assert 0.5 < np.median(nvar) < 2.0


def test_beats_pca_on_sparse_16_channel_scan(trained):
    pts, nrm, C = trained["pts"], trained["nrm"], trained["C"]
    ang_net, w_net = _angles(C, nrm)
    ang_pca, w_pca = _angles(_pca(pts, 16), nrm)
    print(f"all points: net median {np.median(ang_net):.2f} deg ({np.mean(ang_net < 10):.2f} within 10 deg), "
          f"PCA-16 median {np.median(ang_pca):.2f} deg ({np.mean(ang_pca < 10):.2f})")
    assert np.median(ang_net) < np.median(ang_pca)
    assert np.mean(ang_net < 10) > np.mean(ang_pca < 10) + 0.2
    ground = trained["ids"] == 0
    r_net = np.median(w_net[ground, 0]) / SIGMA**2
    r_pca = np.median(w_pca[ground, 0]) / SIGMA**2
    print(f"ground: median lambda_min / sigma^2: net {r_net:.2f}, PCA-16 {r_pca:.3f}")
    assert 0.5 < r_net < 2.0
    assert r_pca < 0.2 or r_pca > 5.0


def test_cylinders_loose_bound(trained):
    m = trained["ids"] >= trained["n_planes"]
    ang, _ = _angles(trained["C"][m], trained["nrm"][m])
    print(f"cylinders: median angle {np.median(ang):.2f} deg")
    assert np.median(ang) < 45.0


def _contaminated(memory, fraction: float, seed: int = 0):
    """The memory with ``fraction`` of every edge's correspondences moved to a wrong target: a point
    of the same target scan 0.3-1.0 m from the right one (another surface, within the 1 m gate)."""
    from scipy.spatial import cKDTree

    from gr_graph.memory import Memory

    rng = np.random.default_rng(seed)
    scans = [np.asarray(memory.scan(k)) for k in range(memory.n_scans)]
    corr = []
    for e in range(memory.n_edges):
        edge = memory.edge(e)
        c = np.array(edge.corr, np.int32)
        Q = scans[edge.l]
        tree = cKDTree(Q)
        for row in rng.choice(len(c), int(round(fraction * len(c))), replace=False):
            q = Q[c[row, 1]]
            near = np.array(tree.query_ball_point(q, 1.0), dtype=np.int64)
            near = near[np.linalg.norm(Q[near] - q, axis=1) > 0.3]
            if len(near):
                c[row, 1] = rng.choice(near)
        corr.append(c)
    return Memory.from_scans(scans, np.asarray(memory.poses), [tuple(map(int, x)) for x in memory.edges],
                             list(np.asarray(memory.edge_kind)), list(np.asarray(memory.edge_T)),
                             list(np.asarray(memory.edge_H)), corr)


@pytest.mark.slow
def test_student_t_learns_the_noise_level_where_wrong_correspondences_inflate_the_gaussian(tmp_path):
    """8 % of the correspondences on another surface 0.3-1 m away (nearest neighbours under the 1 m
    gate do that on the synthetic kitti world: benchmarks/results/correspondence_residuals.md). The
    Gaussian NLL fits their spread: the planes' normal variance comes out at about twice sigma^2 here
    (0.98 sigma^2 on the clean correspondences, test above); the Student t's scale stays under sigma^2
    (a t's scale matrix is not its covariance: for nu = 4 the covariance is twice the scale) and the
    normals stay right. In this toy the Gaussian's covariances stay flat (dense walls); on the
    synthetic world's sparse 16-ring walls they do not (the study above)."""
    prob = street_learning_problem(sigma=SIGMA)
    memory = _contaminated(prob.memory, 0.08)
    planes = prob.ids < prob.n_planes
    result = {}
    for likelihood in ("gaussian", "student_t"):
        cfg = TrainConfig.from_dict({"epochs": 20, "lr": 3e-3, "max_corr": 1024, "progress": False,
                                     "net": {"n_points": 4096}, "corr_likelihood": likelihood})
        path = Trainer(memory, tmp_path / likelihood, cfg).fit(resume=False)
        C = predict_covariances(path, prob.points, n_points=4096)[planes]
        ang, w = _angles(C, prob.normals[planes])
        nvar = np.einsum("ni,nij,nj->n", prob.normals[planes], C, prob.normals[planes]) / SIGMA**2
        result[likelihood] = (np.median(ang), np.median(nvar), np.median(w[:, 0] / w[:, 2]))
        print(f"{likelihood}: planes median angle {result[likelihood][0]:.2f} deg, n^T C n / sigma^2 "
              f"{result[likelihood][1]:.2f}, l_min/l_max {result[likelihood][2]:.3f}")
    assert result["gaussian"][1] > 1.4  # measured 2.04
    assert 0.3 < result["student_t"][1] < 0.5 * result["gaussian"][1]  # measured 0.58
    assert result["student_t"][0] < 5.0 and result["gaussian"][0] < 5.0
