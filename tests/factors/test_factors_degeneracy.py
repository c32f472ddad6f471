"""factors.degeneracy: weak eigen-directions of a pose information matrix."""

from __future__ import annotations

import numpy as np
import pytest
from factors_testutils import transform

from factors.degeneracy import degeneracy_report
from factors.wls import solve_wls


def _flat_covariances(normals: np.ndarray, in_plane: float = 0.5, normal: float = 1e-3) -> np.ndarray:
    """Flat Gaussians (std in_plane along the surface, normal across it) for unit normals."""
    out = np.empty((normals.shape[0], 3, 3))
    for i, n in enumerate(normals):
        P = np.eye(3) - np.outer(n, n)
        out[i] = in_plane**2 * P + normal**2 * np.outer(n, n)
    return out


def test_diagonal_information_names_its_weak_directions():
    H = np.diag([1e4, 1e4, 1e4, 1e3, 1e-2, 1e3])  # y translation unconstrained
    rep = degeneracy_report(H)
    assert rep.is_degenerate and rep.weak_directions == (0,)
    np.testing.assert_allclose(rep.eigenvectors[:, 0], [0, 0, 0, 0, 1, 0])
    assert rep.condition_number == pytest.approx(1e6)
    assert "translation along [0.000, 1.000, 0.000]" in rep.describe()

    H = np.diag([1e4, 1e4, 1e-3, 1e3, 1e3, 1e3])  # yaw unconstrained
    text = degeneracy_report(H).describe()
    assert "rotation about [0.000, 0.000, 1.000]" in text and "1 direction" in text


def test_well_conditioned_information_is_not_degenerate():
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    # eigenvalues kept well off every threshold tested below (5 and 2.5): an eigenvalue on a
    # threshold would be classified by the eigen-solver's last-bit rounding
    H = (Q * np.array([1.0, 2, 3, 4, 6, 100])) @ Q.T
    rep = degeneracy_report(0.5 * (H + H.T))
    assert not rep.is_degenerate and rep.weak_directions == ()
    assert rep.condition_number == pytest.approx(100.0, rel=1e-9)
    assert rep.describe().startswith("well constrained")
    # thresholds: relative 0.05 of 100 = 5 -> four weak (1, 2, 3, 4); absolute 2.5 -> two weak (1, 2)
    assert degeneracy_report(H, rel_threshold=0.05).weak_directions == (0, 1, 2, 3)
    assert degeneracy_report(H, rel_threshold=0.0, abs_threshold=2.5).weak_directions == (0, 1)


def test_corridor_leaves_translation_along_the_corridor_unconstrained():
    """Two walls y = +-2 and a floor z = 0 with flat covariances: only x translation is free."""
    rng = np.random.default_rng(1)
    m = 200
    x = rng.uniform(-20, 20, size=3 * m)
    left = np.column_stack([x[:m], np.full(m, 2.0), rng.uniform(0, 3, m)])
    right = np.column_stack([x[m : 2 * m], np.full(m, -2.0), rng.uniform(0, 3, m)])
    floor = np.column_stack([x[2 * m :], rng.uniform(-2, 2, m), np.zeros(m)])
    q = np.vstack([left, right, floor])
    normals = np.repeat(np.eye(3)[[1, 1, 2]], m, axis=0)
    cov_q = _flat_covariances(normals)
    T = np.eye(4)
    T[:3, 3] = [0.5, 0.0, 0.0]
    p = transform(np.linalg.inv(T), q)
    res = solve_wls(p, q, cov_q, T0=T)
    rep = degeneracy_report(res.hessian)
    assert rep.weak_directions == (0,), rep.describe()
    v = rep.eigenvectors[:, 0]
    assert abs(v[3]) > 0.999  # translation along x
    assert "translation along [1.000, 0.000, 0.000]" in rep.describe()
    # length_scale only rescales the rotation block: same weak direction here
    rep_l = degeneracy_report(res.hessian, length_scale=10.0)
    assert rep_l.weak_directions == (0,)
    np.testing.assert_allclose(
        np.sort(np.linalg.eigvalsh(res.hessian * np.outer(*[np.r_[[0.1] * 3, [1.0] * 3]] * 2))),
        rep_l.eigenvalues,
        rtol=1e-9,
    )


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="6x6"):
        degeneracy_report(np.eye(3))
    H = np.eye(6)
    H[0, 1] = 1.0
    with pytest.raises(ValueError, match="not symmetric"):
        degeneracy_report(H)
    with pytest.raises(ValueError, match="non-finite"):
        degeneracy_report(np.full((6, 6), np.nan))
    with pytest.raises(ValueError, match="rel_threshold"):
        degeneracy_report(np.eye(6), rel_threshold=1.5)


def test_collinear_points_leave_one_rotation_free_and_the_solver_still_fits(caplog):
    """Points on a line (isotropic noise): rotation about the line is unobservable."""
    rng = np.random.default_rng(2)
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    p = np.outer(rng.uniform(-10, 10, 50), axis) + np.array([0.0, 1.0, -1.0])
    T = np.eye(4)
    T[:3, 3] = [0.3, -0.2, 0.1]
    q = transform(T, p)
    cov = np.tile(0.01 * np.eye(3), (50, 1, 1))
    res = solve_wls(p, q, cov)
    assert res.converged
    np.testing.assert_allclose(transform(res.T, p), q, atol=1e-9)  # fits, whatever the roll
    rep = degeneracy_report(res.hessian)
    assert len(rep.weak_directions) == 1, rep.describe()
    v = rep.eigenvectors[:, rep.weak_directions[0]]
    # a rotation about the line through (0, 1, -1): omega along the axis (in the source frame)
    w = v[:3] / np.linalg.norm(v[:3])
    assert abs(abs(w @ axis) - 1.0) < 1e-6  # res.T has no rotation to speak of
    # the screw axis passes through the line: point = omega x v / |omega|^2 is on it
    point = np.cross(v[:3], v[3:]) / (v[:3] @ v[:3])
    offset = point - np.array([0.0, 1.0, -1.0])
    assert np.linalg.norm(offset - (offset @ axis) * axis) < 1e-6
    text = rep.describe()
    assert "rotation about" in text and "through" in text and "pitch" not in text


@pytest.mark.parametrize("length_scale", [None, 10.0])
def test_a_screw_direction_is_named_with_its_axis_point_and_pitch_at_any_length_scale(length_scale):
    """Information blind to one screw motion: rotation about z through (5, 0, 0) with a pitch of 0.2 m per
    rad. Its name gives that point and pitch whether or not rotations were analysed as arc lengths."""
    omega = np.array([0.0, 0.0, 1.0])
    v = -np.cross(omega, [5.0, 0.0, 0.0]) + 0.2 * omega
    xi = np.concatenate([omega, v]) / np.linalg.norm(np.concatenate([omega, v]))
    H = 1e4 * (np.eye(6) - np.outer(xi, xi))
    rep = degeneracy_report(H, length_scale=length_scale)
    assert rep.is_degenerate and len(rep.weak_directions) == 1
    name = rep.direction_names()[0]
    assert "rotation about [0.000, 0.000, " in name and "through [5.000, 0.000, 0.000]" in name, name  # axis: +-z
    assert "(pitch 0.2 per rad)" in name, name
