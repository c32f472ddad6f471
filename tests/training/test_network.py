"""f_theta: neighbourhoods against brute force, Cholesky parametrisation, inference wrapper."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from training.network import CovarianceNet, NetConfig, cholesky_to_cov, neighborhoods_to_torch
from training.neighbors import build_neighborhoods, farthest_point_sampling
from training.predict import predict_covariances

torch.set_num_threads(1)


def test_neighborhoods_match_brute_force():
    rng = np.random.default_rng(0)
    x = rng.uniform(-5, 5, (300, 3))
    for sampling in ("random", "fps"):
        nb = build_neighborhoods(x, k0=8, ratio1=4, k1=6, ratio2=3, k2=5, start=7, sampling=sampling)
        D = ((x[:, None] - x[None]) ** 2).sum(-1)
        np.testing.assert_array_equal(np.sort(nb.knn0, 1), np.sort(np.argsort(D, 1)[:, :8], 1))
        assert len(nb.idx1) == 75 and len(set(nb.idx1)) == 75 and len(nb.idx2) == 25
        x1 = x[nb.idx1]
        D1 = ((x1[:, None] - x[None]) ** 2).sum(-1)
        np.testing.assert_array_equal(np.sort(nb.knn1, 1), np.sort(np.argsort(D1, 1)[:, :6], 1))
        np.testing.assert_allclose(nb.w10.sum(1), 1, rtol=1e-6)
        np.testing.assert_allclose(nb.w21.sum(1), 1, rtol=1e-6)
        # input points -> level 1: the wide neighbourhood (kw nearest) and the interpolation (3
        # nearest, inverse-distance weights) come from one query; both against brute force
        D01 = np.sqrt(((x[:, None] - x1[None]) ** 2).sum(-1))
        order = np.argsort(D01, 1)
        np.testing.assert_array_equal(np.sort(nb.knnw, 1), np.sort(order[:, :16], 1))
        np.testing.assert_array_equal(nb.up10, order[:, :3])
        w = 1.0 / np.maximum(np.take_along_axis(D01, order[:, :3], 1), 1e-8)  # a centroid is an input point
        np.testing.assert_allclose(nb.w10, w / w.sum(1, keepdims=True), rtol=1e-6)
        assert nb.knnw.flags.c_contiguous and nb.up10.flags.c_contiguous
    # farthest-point sampling: each new point is the farthest from those chosen before
    idx = farthest_point_sampling(x, 10, 0)
    for i in range(1, 10):
        dmin = ((x[:, None] - x[idx[:i]][None]) ** 2).sum(-1).min(1)
        assert dmin[idx[i]] == pytest.approx(dmin.max())
    small = build_neighborhoods(x[:5], k0=8)  # fewer points than k: padded, still valid
    assert small.knn0.shape == (5, 8) and small.knn0.max() < 5
    assert small.up10.shape == (5, 3) and small.knnw.shape == (5, 16) and small.knnw.max() < len(small.idx1)
    np.testing.assert_allclose(small.w10.sum(1), 1, rtol=1e-6)


def test_cholesky_parametrisation_gives_spd_covariances():
    raw = torch.randn(100, 6) * 3
    raw[0, :3] = 1e4  # clamped, no overflow
    raw[1, :3] = -1e4
    L, C = cholesky_to_cov(raw, 0.1, 1e-6)
    assert torch.all(torch.diagonal(L, dim1=1, dim2=2) > 0)
    assert torch.equal(L, torch.tril(L))
    assert torch.isfinite(C).all()
    torch.testing.assert_close(C, L @ L.transpose(1, 2) + 1e-6 * torch.eye(3))
    assert torch.linalg.eigvalsh(C.double()).min() >= 0.99e-6


def test_network_output_and_predict_wrapper():
    rng = np.random.default_rng(1)
    cfg = NetConfig(n_points=256, k0=8, k1=8, k2=8, c0=16, c1=16, c2=16)
    torch.manual_seed(0)
    net = CovarianceNet(cfg)
    for p in net.head.parameters():  # a non-trivial head
        torch.nn.init.normal_(p, std=0.3)
    x = rng.uniform(-20, 20, (200, 3)).astype(np.float32)
    L, C = net(torch.tensor(x), neighborhoods_to_torch(cfg.neighborhoods(x, start=3)))
    assert C.shape == (200, 3, 3) and torch.isfinite(C).all()
    # one chunk (N <= n_points): predict_covariances == a direct forward with the same sampling seed
    g = np.random.default_rng(0)
    perm = g.permutation(200)
    start = int(g.integers(200))
    _, C_direct = net(torch.tensor(x[perm]), neighborhoods_to_torch(cfg.neighborhoods(x[perm], start=start)))
    C_pred = predict_covariances(net, x, seed=0)
    np.testing.assert_allclose(C_pred[perm], C_direct.detach().double().numpy(), rtol=1e-5, atol=1e-9)
    # many chunks: every point gets an SPD covariance
    big = rng.uniform(-20, 20, (1000, 3))
    Cb = predict_covariances(net, big, n_points=256)
    assert Cb.shape == (1000, 3, 3) and np.linalg.eigvalsh(Cb).min() > 0
    with pytest.raises(ValueError, match="non-finite"):
        predict_covariances(net, np.full((4, 3), np.nan))


def test_eps_must_be_positive_and_a_network_is_predicted_on_its_own_device(tmp_path):
    import pydantic

    from training.trainer import TrainingError, load_model

    with pytest.raises(pydantic.ValidationError, match="eps must be > 0 with the Cholesky head"):
        NetConfig(eps=0.0, head="cholesky")  # the paper's epsilon keeps its C positive definite
    NetConfig(eps=0.0)  # the geometric head adds its own floor (and checkpoints stored with eps 0 still load)
    cfg = NetConfig(n_points=64, k0=8, k1=8, k2=8, c0=8, c1=8, c2=8)
    net = CovarianceNet(cfg)
    x = np.random.default_rng(0).uniform(-5, 5, (50, 3))
    np.testing.assert_array_equal(predict_covariances(net, x, device="meta"),  # its weights are on the CPU
                                  predict_covariances(net, x))
    if not torch.cuda.is_available():
        ckpt = tmp_path / "m.pt"
        ckpt.write_bytes(b"x")
        with pytest.raises(TrainingError, match="no CUDA device"):
            load_model(ckpt, "cuda")


def test_full_passes_predict_every_point_at_the_training_density():
    """A scan one point over n_points was predicted in two parts of about n_points / 2: sparser
    neighbourhoods than training's, and (shipped weights, a toy street) a median smallest
    eigenvalue about 3x that of the same points predicted in one pass. Filled passes hold n_points
    points, as in training: the same points get the covariances of one pass, up to the sampling."""
    from gr_graph.config import PreprocessConfig
    from gr_graph.pretrained import PRETRAINED_WEIGHTS
    from gr_graph.preprocess import preprocess_scan
    from training.toy_scenes import pose_xy_yaw, render_scan, street_scene
    from training.trainer import load_model

    model = load_model(PRETRAINED_WEIGHTS)
    n = model.config.n_points
    pts, _ = render_scan(street_scene(length=200), pose_xy_yaw(0, 0, 1.7, 0), np.random.default_rng(0),
                         n_rings=64, n_azimuth=2000, max_range=80)
    s = preprocess_scan(pts, PreprocessConfig()).points
    base = s[np.random.default_rng(0).permutation(len(s))[: n + 1]]
    assert len(base) == n + 1

    def median_lmin(C: np.ndarray) -> float:
        return float(np.median(np.linalg.eigvalsh(C[:n])[:, 0]))

    one_pass = median_lmin(predict_covariances(model, base[:n], seed=0))
    split = median_lmin(predict_covariances(model, base, seed=0))
    filled = median_lmin(predict_covariances(model, base, seed=0, full_passes=True))
    assert split > 2.0 * one_pass  # the density the network never saw in training
    assert abs(np.log(filled / one_pass)) < np.log(1.25)
    np.testing.assert_array_equal(predict_covariances(model, base[:n], seed=0, full_passes=True),
                                  predict_covariances(model, base[:n], seed=0))  # one part: nothing to fill


@pytest.mark.parametrize("head", ["geometric", "cholesky"])
def test_both_heads_give_spd_covariances_and_gradients(head):
    rng = np.random.default_rng(2)
    cfg = NetConfig(n_points=256, k0=8, k1=8, k2=8, c0=16, c1=16, c2=16, head=head)
    net = CovarianceNet(cfg)
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.2)
    x = rng.uniform(-20, 20, (256, 3)).astype(np.float32)
    L, C = net(torch.tensor(x), neighborhoods_to_torch(cfg.neighborhoods(x)))
    assert torch.isfinite(C).all() and torch.linalg.eigvalsh(C.double()).min() > 0
    assert torch.all(torch.diagonal(L, dim1=1, dim2=2) > 0)
    torch.testing.assert_close(C, L @ L.transpose(1, 2) + cfg.eps * torch.eye(3), rtol=1e-4, atol=1e-6)
    C.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_geometric_head_normal_follows_the_measured_surface():
    """On a noiseless plane, whatever the weights, C's smallest eigenvector is the plane normal."""
    rng = np.random.default_rng(3)
    cfg = NetConfig(n_points=400, k0=8, k1=8, k2=8, kw=8, c0=16, c1=16, c2=16)
    torch.manual_seed(1)
    net = CovarianceNet(cfg)
    for p in net.parameters():
        torch.nn.init.normal_(p, std=0.2)
    uv = rng.uniform(-5, 5, (400, 2))
    for axis in (np.array([0.0, 0.0, 1.0]), np.array([0.6, 0.0, 0.8]), np.array([0.0, 1.0, 0.0])):
        a = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(axis, a)
        x = (uv[:, :1] * a + uv[:, 1:] * b + np.array([3.0, -2.0, 1.0])).astype(np.float32)
        _, C = net(torch.tensor(x), neighborhoods_to_torch(cfg.neighborhoods(x)))
        w, v = np.linalg.eigh(C.detach().double().numpy())
        cosang = np.abs(v[:, :, 0] @ axis)
        assert cosang.min() > 1 - 1e-4
        assert (w[:, 1] / w[:, 0]).min() > 10  # clearly flat


# A point of a 16-channel synthetic scan (frame 67 of route seed 0, a random 489-point part of
# the scan as predict_covariances splits it) where a trained network (3 epochs, lr 3e-3) gave an
# indefinite covariance (eigenvalue -2.6e-4 m^2) before the geometric head was made
# positive semi-definite by construction: its neighbours are 2-52 m away (S's largest
# eigenvalue ~650 m^2 against kappa 0.02 m^2) and its attention logits reach -74.
_FAR_OFFSETS = [[0.0, 0.0, 0.0], [-0.44644, -1.17458, 2.22903], [0.90154, 2.6202, 2.09179], [7.39504, 16.66943, 1.58337],
                [9.73252, 23.29252, 1.34899], [-12.54621, 22.9996, -1.95604], [8.5204, 34.04361, -0.40351],
                [8.73341, 34.60392, -1.77507], [0.0, 0.0, 0.0], [8.5204, 34.04361, -0.40351], [8.73341, 34.60392, -1.77507],
                [8.73723, 34.68386, -0.41108], [-4.83046, 42.39232, -1.71357], [-6.21289, 44.23524, 0.72568],
                [14.82048, 48.34655, -0.56943], [-8.06215, 52.11738, -1.6221]]
_FAR_LOGITS = [-3.7478, -12.925, -13.4525, -18.4384, -19.9773, -0.2973, -19.8879, -16.2645, -10.513, -58.4325, -60.6125,
               -59.073, -63.6365, -61.8516, -73.6577, -71.7649]
_FAR_RAW = [0.31621, 0.69455, 2.40148]


def _closed_form(raw: np.ndarray, logits: np.ndarray, offsets: np.ndarray, cov_scale: float, eps: float) -> np.ndarray:
    """Independent float64 reference of the geometric head: eigen-decomposition of S, eigenvalues
    mapped by lambda -> alpha kappa lambda / (lambda + kappa) + gamma^2 + eps."""
    from scipy.special import expit

    out = []
    for r, lg, o in zip(raw, logits, offsets):
        w = expit(lg.astype(np.float64))
        if w.sum() == 0.0:  # every weight underflows: they are equal in the limit
            w = np.exp(lg - lg.max())
        S = (w[:, None, None] * o[:, :, None] * o[:, None, :]).sum(0) / w.sum()
        lam, V = np.linalg.eigh(S)
        lam = np.maximum(lam, 0.0)
        a = np.clip(r, -12.0, 8.0)
        alpha, kappa, gamma2 = 0.5 * np.exp(a[0]), cov_scale**2 * np.exp(a[1]), (0.03 * cov_scale) ** 2 * np.exp(2 * a[2])
        out.append(V @ np.diag(alpha * kappa * lam / (lam + kappa) + gamma2 + eps) @ V.T)
    return np.array(out)


def test_geometric_head_on_a_far_isolated_point_is_positive_definite():
    from training.network import geometric_covariance

    raw = torch.tensor([_FAR_RAW], dtype=torch.float32)
    logits = torch.tensor([_FAR_LOGITS], dtype=torch.float32)[..., None]
    offsets = torch.tensor([_FAR_OFFSETS], dtype=torch.float32)
    _, C = geometric_covariance(raw, logits, offsets, 0.1, 1e-6)
    ref = _closed_form(np.array([_FAR_RAW]), np.array([_FAR_LOGITS]), np.array(_FAR_OFFSETS)[None], 0.1, 1e-6)
    np.testing.assert_allclose(C.numpy(), ref, rtol=1e-6, atol=1e-10)
    assert np.linalg.eigvalsh(C.numpy()).min() > 1e-3  # the reference's smallest eigenvalue is 1.1e-3 m^2


def test_geometric_head_is_positive_definite_on_extreme_inputs():
    """Needle-like neighbourhoods up to 60 m, kappa down to its clamp, logits down to -300:
    every covariance finite, positive definite and equal to the closed form."""
    from training.network import geometric_covariance

    g = torch.Generator().manual_seed(0)
    n = 3000
    o = torch.randn(n, 16, 3, generator=g, dtype=torch.float64) * torch.tensor([60.0, 1e-2, 1e-4], dtype=torch.float64)
    Q = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))[0]
    o = (o @ Q.transpose(1, 2)).float()
    raw = (torch.rand(n, 3, generator=g) * 22 - 13)
    logits = torch.randn(n, 16, 1, generator=g) * 80 - 60
    logits[: n // 10] -= 300.0  # every weight of these points underflows in float32
    _, C = geometric_covariance(raw, logits, o, 0.1, 1e-6)
    Cn = C.numpy()
    assert np.isfinite(Cn).all() and np.linalg.eigvalsh(Cn)[:, 0].min() > 0.99e-6
    ref = _closed_form(raw.double().numpy(), logits[..., 0].double().numpy(), o.double().numpy(), 0.1, 1e-6)
    rel = np.linalg.norm(Cn - ref, axis=(1, 2)) / np.linalg.norm(ref, axis=(1, 2))
    assert rel.max() < 1e-4, rel.max()  # condition numbers up to 1e11 here


def test_geometric_head_values_and_gradients_equal_the_kxk_form():
    """The 3x3 Gram form of the head against the k x k form: same covariances and the same
    gradients with respect to every input (raw outputs, attention logits, offsets), on ordinary
    neighbourhoods and on the far, needle-like ones of the tests above."""
    from training.network import geometric_covariance, geometric_covariance_kxk

    g = torch.Generator().manual_seed(3)
    n, k = 400, 24
    scale = torch.where(torch.arange(n)[:, None, None] < n // 2, torch.tensor([1.0, 0.5, 0.05]),
                        torch.tensor([40.0, 0.3, 1e-3])).to(torch.float64)
    offsets = torch.randn(n, k, 3, generator=g, dtype=torch.float64) * scale
    Q = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))[0]
    offsets = offsets @ Q.transpose(1, 2)
    raw = torch.rand(n, 3, generator=g, dtype=torch.float64) * 10 - 6
    logits = torch.randn(n, k, 1, generator=g, dtype=torch.float64) * 20
    weights = torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    grads = []
    for fn in (lambda *a: geometric_covariance(*a, 0.1, 1e-6)[1], lambda *a: geometric_covariance_kxk(*a, 0.1, 1e-6)[1]):
        inputs = [t.clone().requires_grad_(True) for t in (raw, logits, offsets)]
        C = fn(*inputs)
        (C * weights).sum().backward()
        grads.append((C.detach(), [t.grad for t in inputs]))
    (C_new, g_new), (C_ref, g_ref) = grads
    rel = torch.linalg.matrix_norm(C_new - C_ref) / torch.linalg.matrix_norm(C_ref)
    assert float(rel.max()) < 1e-7, float(rel.max())  # condition numbers of B up to ~1e8 here
    for name, a, b in zip(("raw", "logits", "offsets"), g_new, g_ref):
        err = (a - b).abs().max() / b.abs().max()
        assert err < 1e-7, (name, float(err))


def _head_gradients(fn, raw, logits, offsets, weights):
    inputs = [t.clone().requires_grad_(True) for t in (raw, logits, offsets)]
    C = fn(*inputs, 0.1, 1e-6)[1]
    (C * weights).sum().backward()
    return C.detach(), [t.grad for t in inputs]


def test_geometric_head_gradients_at_the_kappa_clamp_and_with_underflowing_weights():
    """kappa at its clamp against needles 60 m long (condition numbers of S + kappa I ~1e11): the
    gradients stay finite and within the conditioning's reach of the k x k form's; a weight that
    underflows to exactly 0 (logit gap < -745) gives finite gradients (sqrt's derivative at 0
    used to give NaN) equal to those without that neighbour's weight."""
    from training.network import geometric_covariance, geometric_covariance_kxk

    g = torch.Generator().manual_seed(7)
    n, k = 300, 16
    o = torch.randn(n, k, 3, generator=g, dtype=torch.float64) * torch.tensor([60.0, 1e-2, 1e-4], dtype=torch.float64)
    raw = torch.rand(n, 3, generator=g, dtype=torch.float64) * 4 - 2
    raw[:, 1] = -13.0  # kappa clamped at cov_scale^2 e^-12
    logits = torch.randn(n, k, 1, generator=g, dtype=torch.float64) * 5
    weights = torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    C, grads = _head_gradients(geometric_covariance, raw, logits, o, weights)
    C_ref, grads_ref = _head_gradients(geometric_covariance_kxk, raw, logits, o, weights)
    assert all(bool(torch.isfinite(x).all()) for x in grads)
    assert float((torch.linalg.matrix_norm(C - C_ref) / torch.linalg.matrix_norm(C_ref)).max()) < 1e-4
    for a, b in zip(grads, grads_ref):
        assert float((a - b).norm() / b.norm()) < 5e-2  # ~1 % seen (module docstring)
    under = logits.clone()
    under[:, 3] = -2000.0  # exp(logsigmoid) gap far below float64's range: the weight is exactly 0
    C_u, grads_u = _head_gradients(geometric_covariance, raw[:50] * 0, under[:50], o[:50] + 1.0, weights[:50])
    assert all(bool(torch.isfinite(x).all()) for x in grads_u)
    dropped = torch.cat([under[:50, :3], under[:50, 4:]], 1)
    C_d, grads_d = _head_gradients(geometric_covariance, raw[:50] * 0, dropped,
                                   torch.cat([o[:50, :3], o[:50, 4:]], 1) + 1.0, weights[:50])
    assert float((torch.linalg.matrix_norm(C_u - C_d) / torch.linalg.matrix_norm(C_d)).max()) < 1e-10
    assert float((grads_u[0] - grads_d[0]).norm() / grads_d[0].norm()) < 1e-9
    assert float(grads_u[1][:, 3].abs().max()) == 0.0 and float(grads_u[2][:, 3].abs().max()) == 0.0


def test_spd_inverse3_against_lapack():
    from training.network import _spd_inverse3

    g = torch.Generator().manual_seed(1)
    Q = torch.linalg.qr(torch.randn(500, 3, 3, generator=g, dtype=torch.float64))[0]
    lam = 10.0 ** (torch.rand(500, 3, generator=g, dtype=torch.float64) * 12 - 8)  # condition up to 1e12
    A = Q @ torch.diag_embed(lam) @ Q.transpose(1, 2)
    inv = _spd_inverse3(A, 0.5 * lam.amin(1))
    assert torch.equal(inv, inv.transpose(1, 2))
    ref = torch.linalg.inv(A)
    rel = torch.linalg.matrix_norm(inv - ref) / torch.linalg.matrix_norm(ref)
    cond = lam.amax(1) / lam.amin(1)
    assert bool((rel < 1e-14 * cond + 1e-15).all())  # the accuracy a backward-stable inverse has
    eye = torch.eye(3, dtype=torch.float64).expand(500, 3, 3)
    well = lam.amax(1) / lam.amin(1) < 1e4
    torch.testing.assert_close((inv @ A)[well], eye[well], rtol=0, atol=1e-10)


def test_network_with_underflowing_attention_weights_is_finite():
    """Attention logits of -150 everywhere (float32 sigmoid = 0, the former 0 / 0): the weights
    only count through their ratios, so the covariances equal those of logits 0."""
    rng = np.random.default_rng(5)
    cfg = NetConfig(n_points=256, k0=8, k1=8, k2=8, kw=8, c0=16, c1=16, c2=16)
    torch.manual_seed(0)
    net = CovarianceNet(cfg)
    for p in net.head.parameters():
        torch.nn.init.normal_(p, std=0.3)
    x = rng.uniform(-20, 20, (200, 3)).astype(np.float32)
    nb = neighborhoods_to_torch(cfg.neighborhoods(x, start=1))
    with torch.no_grad():
        _, C0 = net(torch.tensor(x), nb)
        net.att_out.bias.fill_(-150.0)
        _, C1 = net(torch.tensor(x), nb)
    assert torch.isfinite(C1).all() and torch.linalg.eigvalsh(C1).min() > 0
    torch.testing.assert_close(C1, C0, rtol=1e-9, atol=1e-12)


def test_cholesky_head_keeps_small_eigenvalues_of_anisotropic_factors():
    """L with diagonal 4 m and 1e-5 m and large off-diagonals: in float32, L L^T + eps I lost
    its small eigenvalues (indefinite); the head forms C in float64."""
    raw = torch.tensor([[np.log(40.0), np.log(1e-4), np.log(1e-4), 35.0, -20.0, 15.0]] * 4, dtype=torch.float32)
    _, C = cholesky_to_cov(raw, 0.1, 1e-6)
    assert C.dtype == torch.float64
    assert torch.linalg.eigvalsh(C).min() >= 0.99e-6


def test_row_gather_equals_advanced_indexing_in_values_and_gradients():
    """``_rows`` (``index_select``, the network's gathers) against ``src[idx]`` bit for bit: values
    and the accumulated gradient of rows picked many times, 2-D and 3-D sources, under
    deterministic algorithms (how the trainer runs; without them ``src[idx]``'s own gradient
    varies from run to run on several threads)."""
    from training.network import _rows

    g = torch.Generator().manual_seed(3)
    previous = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        for shape in [(300, 32), (300, 3, 3)]:
            idx = torch.randint(0, 300, (500, 16), generator=g)  # every row ~27 times
            upstream = torch.randn(500, 16, *shape[1:], generator=g)
            out, grads = [], []
            for gather in (_rows, lambda s, i: s[i]):
                src = torch.randn(*shape, generator=torch.Generator().manual_seed(4), requires_grad=True)
                y = gather(src, idx)
                y.backward(upstream)
                out.append(y.detach())
                grads.append(src.grad)
            assert out[0].shape == (500, 16, *shape[1:])
            assert torch.equal(out[0], out[1])
            assert torch.equal(grads[0], grads[1])
            assert float(grads[0].abs().sum()) > 0
    finally:
        torch.use_deterministic_algorithms(previous)
