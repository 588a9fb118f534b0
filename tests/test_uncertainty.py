"""Concentrated Gaussians: sample statistics against the parameters (chi-square / Wishart
tolerances, fixed seeds), propagation against Monte Carlo, second-order compounding closer
than first order, log_prob integrating to 1 (importance sampling), fusion against a
brute-force maximisation of the posterior, and bad input."""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import scipy.stats
import torch
from host_syncs import HostSyncs

import torchsgal as ts
from torchsgal.uncertainty import ConcentratedGaussian

IDS = lambda g: g.__name__  # noqa: E731
N_MC = 20000


def _cov(dof, scale, seed, rot_scale=None, rot_slice=None):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(dof, dof, dtype=torch.float64, generator=g) * scale / math.sqrt(dof)
    S = A @ A.T + (0.1 * scale) ** 2 * torch.eye(dof, dtype=torch.float64)
    if rot_scale is not None:
        S[rot_slice, rot_slice] += rot_scale**2 * torch.eye(3, dtype=torch.float64)
    return S


def _dist(G, scale=0.1, seed=0, side="right"):
    torch.manual_seed(seed)
    mean = G.random((), dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    return ConcentratedGaussian(mean, _cov(G.dof, scale, seed), side)


def _mc_cov(x):
    return torch.cov(x.reshape(-1, x.shape[-1]).T)


def _mc_rel_tol(model, n=N_MC):
    """3 root-mean-square relative Frobenius errors of an n-sample covariance of ``model``
    (Wishart: E|S_hat - S|_F^2 = (tr(S)^2 + |S|_F^2) / n), capped at the former 5%: measured
    errors were 0.3 to 2.3 of it (the rest is the first-order models' own bias)."""
    rms = math.sqrt((float(model.trace()) ** 2 + float(model.norm()) ** 2) / n) / float(model.norm())
    return min(3.0 * rms, 0.05)


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_sample_statistics_match_parameters(G, side):
    d = _dist(G, scale=0.3, seed=1, side=side)
    xi = d.perturbation(d.sample(N_MC, generator=torch.Generator().manual_seed(2)))
    S = d.covariance
    m = xi.mean(0)
    t2 = N_MC * m @ torch.linalg.solve(S, m)  # ~ chi2(dof)
    assert t2 < scipy.stats.chi2.ppf(0.9999, G.dof), f"mean: T^2 = {t2:.2f}"
    # Wishart: var(S_hat_ij) = (S_ii S_jj + S_ij^2) / n
    z = (_mc_cov(xi) - S) / torch.sqrt((torch.outer(S.diagonal(), S.diagonal()) + S**2) / N_MC)
    assert z.abs().max() < 5.0, f"covariance: max |z| = {z.abs().max():.2f}"


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_propagation_matches_monte_carlo(G):
    """compose and between (independent and correlated), inverse, act: small noise, within 3
    root-mean-square Monte Carlo errors (relative Frobenius error of the covariance, at most
    5%)."""
    gen = torch.Generator().manual_seed(3)
    d1, d2 = _dist(G, 0.05, seed=4), _dist(G, 0.05, seed=5)
    s1, s2 = d1.sample(N_MC, generator=gen), d2.sample(N_MC, generator=gen)

    def rel(emp, model):
        return float((emp - model).norm() / model.norm())

    c = d1.compose(d2)
    assert rel(_mc_cov(c.perturbation(s1 @ s2)), c.covariance) < _mc_rel_tol(c.covariance)
    inv = d1.inverse()
    assert rel(_mc_cov(inv.perturbation(s1.inverse())), inv.covariance) < _mc_rel_tol(inv.covariance)
    b = d1.between(d2)
    assert rel(_mc_cov(b.perturbation(s1.between(s2))), b.covariance) < _mc_rel_tol(b.covariance)
    # correlated operands: xi2 = xi1 (the same draw), cross covariance Sigma
    joint = ConcentratedGaussian(d2.mean, d1.covariance)
    xi = d1.perturbation(s1)
    s2c = joint.mean.rplus(xi)
    cc = d1.compose(joint, cross_covariance=d1.covariance)
    assert rel(_mc_cov(cc.perturbation(s1 @ s2c)), cc.covariance) < _mc_rel_tol(cc.covariance)
    # between with correlated operands: xi2 = -xi1, cross covariance -Sigma (xi2 = xi1 would
    # cancel exactly on the abelian SO2); a sign error of the cross term is far off
    s2n = joint.mean.rplus(-xi)
    bc = d1.between(joint, cross_covariance=-d1.covariance)
    emp = _mc_cov(bc.perturbation(s1.between(s2n)))
    assert rel(emp, bc.covariance) < _mc_rel_tol(bc.covariance)
    A = -bc.mean.inverse().adjoint()  # the cross term with the other sign
    flipped = bc.covariance - 2 * (A @ -d1.covariance + (A @ -d1.covariance).T)
    assert float((emp - flipped).norm()) > 10 * float((emp - bc.covariance).norm())
    # actions on directions and velocities: Gaussians on R^n (linear in the group element)
    dim, k = G.point_dim, G.rotation_dim
    x = torch.randn(dim, dtype=torch.float64, generator=gen)
    gd = d1.act_direction(x[:k])
    assert rel(_mc_cov(s1.act_direction(x[:k])), gd.covariance) < _mc_rel_tol(gd.covariance)
    if hasattr(s1, "act_velocity"):
        gv = d1.act_velocity(x[:3])
        assert rel(_mc_cov(s1.act_velocity(x[:3])), gv.covariance) < _mc_rel_tol(gv.covariance)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_point_action_propagation_matches_monte_carlo(G):
    """act on points (events for SGal3): covariance against Monte Carlo, the first-order mean
    plus its second-order bias, and an uncertain point."""
    gen = torch.Generator().manual_seed(3)
    d1 = _dist(G, 0.05, seed=4)
    s1 = d1.sample(N_MC, generator=gen)

    def rel(emp, model):
        return float((emp - model).norm() / model.norm())

    dim = G.point_dim
    x = torch.randn(dim, dtype=torch.float64, generator=gen)
    ga = d1.act(x)
    assert rel(_mc_cov(s1.act(x)), ga.covariance) < _mc_rel_tol(ga.covariance)
    # the first-order mean plus its known second-order bias (M/2) E[xi^ xi^] x_h, within 4 SE
    ys = s1.act(x)
    hats = G.hat(torch.eye(G.dof, dtype=torch.float64))
    E2 = torch.einsum("ij,iab,jbc->ac", d1.covariance, hats, hats)
    n = G.matrix_dim
    xh = torch.zeros(n, dtype=torch.float64)
    xh[:dim] = x
    if n > dim:
        xh[n - 1] = 1.0
    # z = M exp(xi^) x_h: E[z] = z0 + (M/2) E[xi^ xi^] x_h to second order; y = z[:k] / z[n-1]
    # (z[n-1] = 1 for the affine groups), so by the delta method for a ratio
    # E[y] = E[z_k]/E[z_n] - Cov(z_k, z_n)/z_n^2 + z_k Var(z_n)/z_n^3.
    M = d1.mean.as_matrix()
    Ez = M @ xh + 0.5 * (M @ E2 @ xh)
    Hz = M @ torch.einsum("jab,b->aj", hats, xh)
    Cz = Hz @ d1.covariance @ Hz.T
    if n > dim:
        zn = (M @ xh)[n - 1]
        predicted = (Ez[:dim] / Ez[n - 1] - Cz[:dim, n - 1] / zn**2
                     + (M @ xh)[:dim] * Cz[n - 1, n - 1] / zn**3)
    else:  # rotations: no homogeneous coordinate
        predicted = Ez[:dim]
    se = ys.std(0) / math.sqrt(N_MC)
    assert ((ys.mean(0) - predicted).abs() < 4 * se).all()
    # with an uncertain point: exact linear term
    Sx = 0.01 * torch.eye(dim, dtype=torch.float64)
    xs = x + torch.randn(N_MC, dim, dtype=torch.float64, generator=gen) @ torch.linalg.cholesky(Sx).T
    gx = d1.act(x, Sx)
    assert rel(_mc_cov(s1.act(xs)), gx.covariance) < _mc_rel_tol(gx.covariance)


@pytest.mark.parametrize("G", [ts.SE3, ts.SGal3], ids=IDS)
def test_second_order_compounding_beats_first_order(G):
    """Large rotational noise (Barfoot and Furgale's experiment): the fourth-order terms bring
    the compounded covariance closer to Monte Carlo."""
    phi = G._f.PHI
    gen = torch.Generator().manual_seed(6)
    S1 = _cov(G.dof, 0.05, 7, rot_scale=0.35, rot_slice=phi)
    S2 = _cov(G.dof, 0.05, 8, rot_scale=0.35, rot_slice=phi)
    m1 = G.exp(torch.randn(G.dof, dtype=torch.float64, generator=gen))
    m2 = G.exp(torch.randn(G.dof, dtype=torch.float64, generator=gen))
    d1, d2 = ConcentratedGaussian(m1, S1), ConcentratedGaussian(m2, S2)
    n = 200000
    emp = _mc_cov(d1.compose(d2).perturbation(d1.sample(n, generator=gen) @ d2.sample(n, generator=gen)))
    e1 = float((emp - d1.compose(d2).covariance).norm())
    e2 = float((emp - d1.compose(d2, second_order=True).covariance).norm())
    assert e2 < 0.8 * e1, f"second order {e2:.4g} vs first order {e1:.4g}"


def _haar_integral(p, n, gen, std=0.4, volume_factor=True):
    """E_q[p(F) / q(F)] with F sampled from the Haar measure dF = dR dv dr dtau of these
    semi-direct products: R uniform on SO(3) (volume 8 pi^2 in the |det J_r| dxi measure) and
    the Euclidean parts (the matrix's v, r, tau) Gaussian around the mean's.  Sim3 (matrix
    [[R, r], [0, 1/s]], not unimodular): its left-invariant measure is dR dr dlambda,
    lambda = log s (left translation by (R1, r1, s1) maps r to R1 r + r1 / s, lambda to
    lambda1 + lambda: Jacobian determinant 1), the Euclidean parts (r, lambda)."""
    G = p.group
    R = ts.SO3.random((n,), dtype=torch.float64, generator=gen).as_matrix()
    logq = torch.full((n,), -math.log(8 * math.pi**2), dtype=torch.float64)
    if G is ts.SO3:
        F = ts.SO3.from_matrix(R)
    else:
        M0 = p.mean.as_matrix()
        cols = [3] if G in (ts.SE3, ts.Sim3) else [3, 4]
        e0 = torch.cat([M0[:3, c] for c in cols] + ([M0[3, 4:5]] if G is ts.SGal3 else [])
                       + ([-torch.log(M0[3, 3:4])] if G is ts.Sim3 else []))
        k = e0.numel()
        e = e0 + std * torch.randn(n, k, dtype=torch.float64, generator=gen)
        logq = logq - 0.5 * ((e - e0) ** 2).sum(-1) / std**2 - k * math.log(std * math.sqrt(2 * math.pi))
        if G is ts.SE3:
            F = ts.SE3.from_components(R, e[:, :3])
        elif G is ts.Sim3:
            F = ts.Sim3.from_components(R, e[:, :3], torch.exp(e[:, 3]))
        elif G is ts.SE23:
            F = ts.SE23.from_components(R, e[:, :3], e[:, 3:6])
        else:
            F = ts.SGal3.from_components(R, e[:, :3], e[:, 3:6], e[:, 6])
    lp = p.log_prob(F)
    if not volume_factor:
        lp = lp + torch.linalg.slogdet(G.jr(p.perturbation(F)))[1]
    w = torch.exp(lp - logq)
    return float(w.mean()), float(w.std() / math.sqrt(n))


@pytest.mark.parametrize("G", ts.GROUPS, ids=IDS)
def test_log_prob_integrates_to_one(G):
    """log_prob is a density on the group, (4.11): it integrates to 1 against the Haar measure
    (within 4 standard errors); without the 1/|det J_r| volume factor it does not."""
    gen = torch.Generator().manual_seed(9)
    S = _cov(G.dof, 0.2, 10, rot_scale=0.8, rot_slice=G._f.PHI)
    p = ConcentratedGaussian(G.exp(0.1 * torch.randn(G.dof, dtype=torch.float64, generator=gen)), S)
    est, se = _haar_integral(p, 100000, gen)
    assert abs(est - 1.0) < 4 * se, f"integral {est:.4f} +- {se:.4f}"
    wrong, se_w = _haar_integral(p, 100000, gen, volume_factor=False)
    assert abs(wrong - 1.0) > 6 * se_w, f"without |det J|: {wrong:.4f} +- {se_w:.4f}"


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_to_side_round_trip_and_consistency(G):
    d = _dist(G, 0.1, seed=11)
    back = d.to_side("left").to_side("right")
    np.testing.assert_allclose(back.covariance.numpy(), d.covariance.numpy(), rtol=0, atol=1e-12)
    left = d.to_side("left")
    s = d.sample(N_MC, generator=torch.Generator().manual_seed(12))
    emp = _mc_cov(left.perturbation(s))
    assert float((emp - left.covariance).norm() / left.covariance.norm()) < 0.05


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_fusion_matches_brute_force_posterior(G):
    """The fused mean maximises p1 p2 (LBFGS with autograd); its covariance is the Gauss-Newton
    posterior (sum_k J_k^T W_k J_k)^-1 at that point, with the residual Jacobians J_k taken
    by plain autograd (torch.func.jacrev) through the forward closed forms exp_impl and
    log_impl: not through log's custom backward, which applies the same closed-form J_r^-1
    family that fuse uses."""
    d1 = _dist(G, 0.2, seed=13)
    d2 = ConcentratedGaussian(d1.mean.rplus(0.3 * torch.ones(G.dof, dtype=torch.float64)),
                              _cov(G.dof, 0.3, 14))
    fused = d1.fuse(d2, iterations=20)
    W1, W2 = torch.linalg.inv(d1.covariance), torch.linalg.inv(d2.covariance)

    def cost(delta, base):
        F = base.rplus(delta)
        r1, r2 = F.rminus(d1.mean), F.rminus(d2.mean)
        return 0.5 * (r1 @ W1 @ r1 + r2 @ W2 @ r2)

    delta = torch.zeros(G.dof, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([delta], lr=1, max_iter=200, tolerance_grad=1e-14,
                            tolerance_change=1e-16, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        c = cost(delta, d1.mean)
        c.backward()
        return c

    opt.step(closure)
    best = d1.mean.rplus(delta.detach())
    np.testing.assert_allclose(fused.mean.as_matrix().numpy(), best.as_matrix().numpy(), rtol=0, atol=1e-7)
    zero = torch.zeros(G.dof, dtype=torch.float64)
    f, M_best = G._f, best.as_matrix()
    info = 0
    for d, W in ((d1, W1), (d2, W2)):
        M_inv = d.mean.inverse().as_matrix()
        # rminus(best exp(x), mean) = log(mean^-1 best exp(x)), differentiated at x = 0
        J = torch.func.jacrev(lambda x: f.log_impl(M_inv @ M_best @ f.exp_impl(x)))(zero)
        info = info + J.T @ W @ J
    np.testing.assert_allclose(fused.covariance.numpy(), torch.linalg.inv(info).numpy(), rtol=0, atol=1e-9)


def test_reparameterised_gradients():
    mean = ts.SGal3.random((), dtype=torch.float64)
    L = (0.1 * torch.eye(10, dtype=torch.float64)).requires_grad_(True)
    xi0 = torch.zeros(10, dtype=torch.float64, requires_grad=True)
    d = ConcentratedGaussian(mean.rplus(xi0), L @ L.T)
    s = d.sample(64, generator=torch.Generator().manual_seed(0))
    loss = s.act(torch.ones(4, dtype=torch.float64)).square().sum()
    g_mean, g_L = torch.autograd.grad(loss, (xi0, L))
    assert torch.isfinite(g_mean).all() and g_mean.abs().sum() > 0
    assert torch.isfinite(g_L).all() and g_L.abs().sum() > 0

    def sampled_loss(xi, L):  # the same draws every call: a deterministic function of (xi, L)
        d = ConcentratedGaussian(mean.rplus(xi), L @ L.T)
        s = d.sample(8, generator=torch.Generator().manual_seed(0))
        return s.act(torch.ones(4, dtype=torch.float64)).square().sum()

    # the reparameterised gradients are those of the samples' formula (finite differences)
    gen = torch.Generator().manual_seed(1)
    xi = 0.1 * torch.randn(10, dtype=torch.float64, generator=gen)
    L = 0.1 * torch.eye(10, dtype=torch.float64) + 0.01 * torch.randn(10, 10, dtype=torch.float64, generator=gen).tril()
    assert torch.autograd.gradcheck(sampled_loss, (xi.requires_grad_(), L.requires_grad_()))


def test_bad_input():
    m = ts.SE3.random((), dtype=torch.float64)
    d = ConcentratedGaussian(m, torch.eye(6, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"sample_shape must have sizes >= 0, got \(-1,\)"):
        d.sample(-1)
    with pytest.raises(TypeError, match=r"sample_shape must be an int or a sequence of ints, got float"):
        d.sample(2.5)
    with pytest.raises(ValueError, match=r"covariance must have shape \(\.\.\., 6, 6\) for SE3, got \(5, 5\)"):
        ConcentratedGaussian(m, torch.eye(5, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"not symmetric"):
        ConcentratedGaussian(m, torch.eye(6, dtype=torch.float64) + torch.triu(torch.ones(6, 6, dtype=torch.float64), 1))
    with pytest.raises(ValueError, match=r"not positive definite"):
        ConcentratedGaussian(m, -torch.eye(6, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"side must be 'right' or 'left'"):
        ConcentratedGaussian(m, torch.eye(6, dtype=torch.float64), side="up")
    with pytest.raises(TypeError, match=r"must match the mean"):
        ConcentratedGaussian(m, torch.eye(6, dtype=torch.float32))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast"):
        ConcentratedGaussian(ts.SE3.random((3,), dtype=torch.float64), torch.eye(6, dtype=torch.float64).expand(4, 6, 6))
    with pytest.raises(TypeError, match=r"mean must be a group element"):
        ConcentratedGaussian(torch.eye(4), torch.eye(6))
    with pytest.raises(TypeError, match=r"covariance \(torch.float16, cpu\) must match the mean"):
        ConcentratedGaussian(m, torch.eye(6, dtype=torch.float16))
    d = ConcentratedGaussian(m, torch.eye(6, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"other must be a ConcentratedGaussian on SE3, got a ConcentratedGaussian on SO3"):
        d.compose(ConcentratedGaussian(ts.SO3.random((), dtype=torch.float64), torch.eye(3, dtype=torch.float64)))
    with pytest.raises(TypeError, match=r"other must be a ConcentratedGaussian on SE3, got SE3"):
        d.fuse(m)


def test_empty_batch():
    """A batch of 0: validation, propagation and fusion return empty results."""
    from torchsgal.uncertainty import check_covariance

    D = torch.float64
    check_covariance(torch.zeros(0, 3, 3, dtype=D), 3)
    d = ConcentratedGaussian(ts.SGal3.identity((0,), dtype=D), 0.01 * torch.eye(10, dtype=D).expand(0, 10, 10))
    assert d.fuse(d).covariance.shape == (0, 10, 10)
    assert d.compose(d, cross_covariance=torch.zeros(0, 10, 10, dtype=D)).covariance.shape == (0, 10, 10)
    a = d.act(torch.zeros(0, 4, dtype=D), torch.zeros(0, 4, 4, dtype=D))
    assert a.mean.shape == (0, 4) and a.covariance.shape == (0, 4, 4)


def test_check_covariance_validates_dim():
    """dim is checked first, by name: an integer >= 0, bool refused (unchecked, dim=True would
    pass a (1, 1) covariance as dim 1, and dim "1" or -1 give a shape message about it)."""
    from torchsgal.uncertainty import check_covariance

    S = torch.eye(1, dtype=torch.float64)
    for bad in (True, False, 1.0, "1", None):
        with pytest.raises(TypeError, match=f"^dim must be an integer >= 0, got {bad!r}$"):
            check_covariance(S, bad)
    with pytest.raises(ValueError, match="^dim must be an integer >= 0, got -1$"):
        check_covariance(S, -1)
    check_covariance(S, 1)
    check_covariance(S, np.int64(1))  # numpy integers are integers
    check_covariance(torch.zeros(0, 0, dtype=torch.float64), 0)


def test_propagation_covariance_arguments_validated():
    """x_covariance (act) and cross_covariance (compose, between): shape, dtype, device, batch
    named; x_covariance is a covariance (symmetric positive semi-definite: zero is an exact
    point); a cross-covariance need not be symmetric."""
    D = torch.float64
    d = ConcentratedGaussian(ts.SE3.random((3,), dtype=D), 0.01 * torch.eye(6, dtype=D))
    x = torch.randn(3, dtype=D)
    with pytest.raises(ValueError, match=r"x_covariance is not positive semi-definite"):
        d.act(x, x_covariance=-torch.eye(3, dtype=D))
    with pytest.raises(ValueError, match=r"x_covariance is not symmetric"):
        d.act(x, x_covariance=torch.eye(3, dtype=D) + torch.triu(torch.ones(3, 3, dtype=D), 1))
    with pytest.raises(ValueError, match=r"x_covariance must have shape \(\.\.\., 3, 3\), got \(4, 4\)"):
        d.act(x, x_covariance=torch.eye(4, dtype=D))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: gaussian \(3,\), x \(\), x_covariance \(4,\)"):
        d.act(x, x_covariance=torch.eye(3, dtype=D).expand(4, 3, 3))
    with pytest.raises(ValueError, match=r"x_covariance is on meta but x is on cpu"):
        d.act(x, x_covariance=torch.eye(3, dtype=D, device="meta"))
    with pytest.raises(TypeError, match=r"x_covariance has dtype torch.float32 but x has dtype torch.float64"):
        d.act(x, x_covariance=torch.eye(3))
    with pytest.raises(ValueError, match=r"d_covariance is not positive semi-definite"):
        d.act_direction(x, d_covariance=-torch.eye(3, dtype=D))
    # validate=False skips the data check (not the metadata ones); an exact point is allowed
    d.act(x, x_covariance=-torch.eye(3, dtype=D), validate=False)
    exact = d.act(x, x_covariance=torch.zeros(3, 3, dtype=D))
    torch.testing.assert_close(exact.covariance, d.act(x).covariance)
    for op in (d.compose, d.between):
        with pytest.raises(ValueError, match=r"cross_covariance must have shape \(\.\.\., 6, 6\), got \(9, 9\)"):
            op(d, cross_covariance=torch.eye(9, dtype=D))
        with pytest.raises(ValueError, match=r"batch shapes do not broadcast: .*cross_covariance \(4,\)"):
            op(d, cross_covariance=torch.eye(6, dtype=D).expand(4, 6, 6))
        with pytest.raises(ValueError, match=r"cross_covariance is on meta but self is on cpu"):
            op(d, cross_covariance=torch.eye(6, dtype=D, device="meta"))
        with pytest.raises(TypeError, match=r"other has dtype torch.float32 but self has dtype torch.float64"):
            op(ConcentratedGaussian(ts.SE3.random((), dtype=torch.float32), 0.01 * torch.eye(6)))
        with pytest.raises(ValueError, match=r"batch shapes do not broadcast: self \(3,\), other \(4,\)"):
            op(ConcentratedGaussian(ts.SE3.random((4,), dtype=D), 0.01 * torch.eye(6, dtype=D)))
    # a cross-covariance is not symmetric: accepted as is
    C = 1e-3 * torch.triu(torch.ones(6, 6, dtype=D))
    assert torch.isfinite(d.compose(d, cross_covariance=C).covariance).all()


def test_element_arguments_named():
    """mahalanobis, log_prob and perturbation name their argument g and the Gaussian's group."""
    d = _dist(ts.SGal3)
    for fn in (d.mahalanobis, d.log_prob, d.perturbation):
        with pytest.raises(TypeError, match=r"g must be a SGal3 \(the group of this Gaussian\), got SE3"):
            fn(ts.SE3.random((), dtype=torch.float64))
        with pytest.raises(TypeError, match=r"g has dtype torch.float32 but mean has dtype torch.float64"):
            fn(ts.SGal3.random(()))
    d3 = ConcentratedGaussian(ts.SGal3.random((3,), dtype=torch.float64), torch.eye(10, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: gaussian \(3,\), g \(4,\)"):
        d3.mahalanobis(ts.SGal3.random((4,), dtype=torch.float64))


def test_validation_skipped_under_vmap():
    """The covariance checks read values; under torch.func.vmap they are skipped (bool of a
    batched tensor raises), so a validating constructor and act work there."""
    D = torch.float64
    m = ts.SE3.random((5,), dtype=D, generator=torch.Generator().manual_seed(0))
    S = 0.01 * torch.eye(6, dtype=D).expand(5, 6, 6)
    x = torch.randn(5, 3, dtype=D, generator=torch.Generator().manual_seed(1))

    def f(M, S, x):
        return ConcentratedGaussian(ts.SE3.from_matrix(M), S).act(x, 0.1 * S[:3, :3]).covariance

    out = torch.vmap(f)(m.as_matrix(), S, x)
    torch.testing.assert_close(out, ConcentratedGaussian(m, S).act(x, 0.1 * S[..., :3, :3]).covariance)


# ------------------------------------------------------------- event fusion (mahony Sec. 6)
def _event_problem(seed=20):
    gen = torch.Generator().manual_seed(seed)
    C = ts.SO3.exp(torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64)).as_matrix()
    F_hat = ts.SGal3.from_components(C, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                                     torch.zeros(3, dtype=torch.float64), torch.tensor(2.0, dtype=torch.float64))
    Q = torch.diag(torch.tensor([0.3, 0.3, 0.3, 0.05, 0.05, 0.05, 0.01, 0.01, 0.01, 0.2], dtype=torch.float64) ** 2)
    prior = ConcentratedGaussian(F_hat, Q)
    event = torch.tensor([0.4, -0.2, 0.1, 2.3], dtype=torch.float64) + 0.05 * torch.randn(4, dtype=torch.float64, generator=gen)
    Sigma = torch.diag(torch.tensor([0.2, 0.2, 0.2, 0.3], dtype=torch.float64) ** 2)
    return prior, event, Sigma


def _event_cost(prior, event, Sigma, eps, time_row=False):
    """The negative log posterior (64)-(66) in the exponential coordinates E = exp(eps) (65);
    by default without the uninformative time row (see torchsgal/uncertainty/events.py)."""
    from torchsgal.uncertainty import near_inertial_relative_frame

    F_hat, Q = prior.mean, prior.covariance
    d = F_hat.inverse().act(event)
    N_mu = F_hat.inverse().as_matrix()[:4, :4].clone()
    N_mu[3, 3] -= 1.0
    S = N_mu @ Sigma @ N_mu.T
    S[3, 3] += Q[9, 9]
    kF = near_inertial_relative_frame(event[3], F_hat.time())
    y0 = torch.tensor([0, 0, 0, 0, 1.0], dtype=torch.float64)
    pred = (ts.SGal3.exp(eps).as_matrix() @ kF.as_matrix() @ y0)[:4]
    n = 4 if time_row else 3
    r = (d - pred)[:n]
    return eps @ torch.linalg.solve(Q, eps) + r @ torch.linalg.solve(S[:n, :n], r)


def _event_gn_covariance(prior, event, Sigma, eps, time_row=False):
    """The Gauss-Newton posterior covariance at eps, re-expressed about F_hat exp(eps):
    J_r (Q^-1 + Jm^T S^-1 Jm)^-1 J_r^T, with Jm the Jacobian of I4^T exp(eps) kF_i y0 and J_r
    that of log(exp(eps)^-1 exp(eps + d)), both by plain autograd through the forward closed
    forms exp_impl and log_impl (not the library's J_l, J_r)."""
    from torchsgal.uncertainty import near_inertial_relative_frame

    F_hat, Q = prior.mean, prior.covariance
    N_mu = F_hat.inverse().as_matrix()[:4, :4].clone()
    N_mu[3, 3] -= 1.0
    S = N_mu @ Sigma @ N_mu.T
    S[3, 3] += Q[9, 9]
    n = 4 if time_row else 3
    x = near_inertial_relative_frame(event[3], F_hat.time()).as_matrix() @ torch.tensor(
        [0, 0, 0, 0, 1.0], dtype=torch.float64)
    f = ts.SGal3._f
    Jm = torch.func.jacrev(lambda e: (f.exp_impl(e) @ x)[:n])(eps)
    P = torch.linalg.inv(torch.linalg.inv(Q) + Jm.T @ torch.linalg.solve(S[:n, :n], Jm))
    E_inv = torch.linalg.inv(f.exp_impl(eps))
    Jr = torch.func.jacrev(lambda d: f.log_impl(E_inv @ f.exp_impl(eps + d)))(torch.zeros_like(eps))
    return Jr @ P @ Jr.T


@pytest.mark.parametrize("time_row", [False, True], ids=["default", "paper-time-row"])
def test_event_fusion_matches_brute_force_posterior(time_row):
    from torchsgal.uncertainty import fuse_event

    prior, event, Sigma = _event_problem()
    cost_fn = functools.partial(_event_cost, time_row=time_row)

    eps = torch.zeros(10, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([eps], lr=1, max_iter=500, tolerance_grad=1e-15,
                            tolerance_change=1e-18, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        c = cost_fn(prior, event, Sigma, eps)
        c.backward()
        return c

    opt.step(closure)
    # polish with Newton steps on the autograd Hessian (LBFGS stops near 1e-6 in gradient)
    e = eps.detach()
    for _ in range(5):
        g = torch.func.grad(lambda x: cost_fn(prior, event, Sigma, x))(e)
        e = e - torch.linalg.solve(torch.autograd.functional.hessian(lambda x: cost_fn(prior, event, Sigma, x), e), g)
    eps = e.clone().requires_grad_(True)
    best = prior.mean.rplus(eps.detach())
    iterated = fuse_event(prior, event, Sigma, iterations=10, time_row=time_row)
    np.testing.assert_allclose(iterated.mean.as_matrix().numpy(), best.as_matrix().numpy(), rtol=0, atol=1e-8)
    # the paper's single step lands near the optimum; it lowers the cost a lot
    one = fuse_event(prior, event, Sigma, time_row=time_row)
    eps_one = one.mean.rminus(prior.mean)
    c0 = float(cost_fn(prior, event, Sigma, torch.zeros(10, dtype=torch.float64)))
    c1 = float(cost_fn(prior, event, Sigma, eps_one))
    cb = float(cost_fn(prior, event, Sigma, eps.detach()))
    assert cb <= c1 < cb + 0.05 * (c0 - cb)
    # the printed sign of (68) (E ~ I - eps^) moves the estimate the wrong way
    assert float(cost_fn(prior, event, Sigma, -eps_one)) > c0
    # the posterior covariance: J_r P J_r^T with P the inverse Gauss-Newton information, the
    # Jacobians of the measurement and J_r taken by autograd (_event_gn_covariance)
    eps_b = eps.detach()
    W = torch.autograd.functional.hessian(lambda e: cost_fn(prior, event, Sigma, e), eps_b)
    assert torch.linalg.eigvalsh(W).min() > 0  # a minimum
    assert torch.allclose(iterated.covariance, iterated.covariance.T)
    expected = _event_gn_covariance(prior, event, Sigma, iterated.mean.rminus(prior.mean), time_row)
    torch.testing.assert_close(iterated.covariance, expected, rtol=0, atol=1e-10)


def test_event_time_row_is_uninformative():
    """The time row's residual is -eps_iota for every eps (it is built from tau itself): with an
    uncorrelated prior the posterior time variance stays the prior's by default, and the paper's
    model halves it (double counting)."""
    from torchsgal.uncertainty import fuse_event

    prior, event, Sigma = _event_problem()
    default = fuse_event(prior, event, Sigma)
    paper = fuse_event(prior, event, Sigma, time_row=True)
    q = prior.covariance[9, 9]
    assert abs(float(default.covariance[9, 9] / q) - 1.0) < 1e-6
    assert abs(float(paper.covariance[9, 9] / q) - 0.5) < 1e-6


@pytest.mark.parametrize("time_row", [False, True], ids=["default", "paper-time-row"])
def test_event_fusion_prior_covariance_batch_larger_than_its_mean(time_row):
    """A prior whose covariance has a batch of its own (the mean unbatched) fuses as the same
    prior with the mean expanded; time_row=True added Q_99 in place into S, which had no
    batch, and raised torch's expand error."""
    from torchsgal.uncertainty import fuse_event

    prior, event, Sigma = _event_problem()
    scales = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)[:, None, None]
    batched = ConcentratedGaussian(prior.mean, scales * prior.covariance)
    expanded = ConcentratedGaussian(prior.mean.expand(3), scales * prior.covariance)
    got = fuse_event(batched, event, Sigma, time_row=time_row)
    want = fuse_event(expanded, event, Sigma, time_row=time_row)
    assert got.batch_shape == (3,)
    torch.testing.assert_close(got.mean.as_matrix(), want.mean.as_matrix(), rtol=0, atol=1e-15)
    torch.testing.assert_close(got.covariance, want.covariance, rtol=0, atol=1e-15)


def test_event_fusion_trades_time_against_position():
    """Figure 5: the timestamp noise enters the position residual along the velocity (N_mu maps
    it to -v Sigma_t v^T), so the Galilean fusion trusts the measurement less along the velocity
    than classical fusion (no temporal uncertainty): it moves less along x and its posterior
    uncertainty stretches along x."""
    from torchsgal.uncertainty import fuse_event

    F_hat = ts.SGal3.from_components(torch.eye(3, dtype=torch.float64), torch.tensor([1.0, 0, 0], dtype=torch.float64),
                                     torch.zeros(3, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
    Q = torch.diag(torch.tensor([0.5] * 3 + [0.01] * 3 + [0.01] * 3 + [0.5], dtype=torch.float64) ** 2)
    event = torch.tensor([0.8, 0.0, 0.0, 0.0], dtype=torch.float64)
    Sigma = torch.diag(torch.tensor([0.3, 0.3, 0.3, 0.6], dtype=torch.float64) ** 2)
    post = fuse_event(ConcentratedGaussian(F_hat, Q), event, Sigma, iterations=5)
    Q_c, Sigma_c = Q.clone(), Sigma.clone()
    Q_c[9, 9], Sigma_c[3, 3] = 1e-12, 1e-12  # classical: timestamps taken as exact
    classical = fuse_event(ConcentratedGaussian(F_hat, Q_c), event, Sigma_c, iterations=5)
    x_gal, x_cls = post.mean.position()[0], classical.mean.position()[0]
    assert 0 < x_gal < x_cls - 0.05  # moves towards the measurement, less than classical
    cov_p = post.act(torch.zeros(4, dtype=torch.float64)).covariance[:2, :2]
    cov_c = classical.act(torch.zeros(4, dtype=torch.float64)).covariance[:2, :2]
    assert cov_p[0, 0] > 1.5 * cov_p[1, 1]  # stretched along the velocity (x)
    assert cov_c[0, 0] < 1.1 * cov_c[1, 1]  # classical: round
    with pytest.raises(TypeError, match=r"prior on SGal3"):
        fuse_event(ConcentratedGaussian(ts.SE3.random((), dtype=torch.float64), torch.eye(6, dtype=torch.float64)), event, Sigma)
    with pytest.raises(ValueError, match=r"event must have shape \(\.\.\., 4\)"):
        fuse_event(ConcentratedGaussian(F_hat, Q), event[:3], Sigma)


def test_event_fusion_bad_input():
    """fuse_event validates its arguments, naming them: event_covariance as a covariance (its
    position block positive definite), relative_frame's group, dtypes, devices and batches."""
    from torchsgal.uncertainty import fuse_event, near_inertial_relative_frame

    D = torch.float64
    prior, event, Sigma = _event_problem()
    with pytest.raises(ValueError, match=r"event_covariance is not positive semi-definite"):
        fuse_event(prior, event, -torch.eye(4, dtype=D))
    for bad in (0, -1):
        with pytest.raises(ValueError, match=r"iterations must be an integer >= 1"):
            fuse_event(prior, event, Sigma, iterations=bad)
    for bad in (1.5, True):
        with pytest.raises(TypeError, match=r"iterations must be an integer >= 1"):
            fuse_event(prior, event, Sigma, iterations=bad)
    with pytest.raises(ValueError, match=r"event_covariance is not symmetric"):
        fuse_event(prior, event, Sigma + 0.01 * torch.triu(torch.ones(4, 4, dtype=D), 1))
    with pytest.raises(ValueError, match=r"position block event_covariance\[\.\.\., :3, :3\] is not positive definite"):
        fuse_event(prior, event, torch.diag(torch.tensor([0.0, 0.0, 0.0, 0.1], dtype=D)))
    with pytest.raises(TypeError, match=r"relative_frame must be an SGal3"):
        fuse_event(prior, event, Sigma, relative_frame=ts.SE23.identity(dtype=D))
    with pytest.raises(TypeError, match=r"relative_frame has dtype torch.float32 but prior has dtype torch.float64"):
        fuse_event(prior, event, Sigma, relative_frame=ts.SGal3.identity())
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: .*relative_frame \(4,\)"):
        fuse_event(prior, event.expand(3, 4), Sigma, relative_frame=ts.SGal3.identity((4,), dtype=D))
    with pytest.raises(ValueError, match=r"event_covariance is on meta but prior is on cpu"):
        fuse_event(prior, event, torch.eye(4, dtype=D, device="meta"))
    with pytest.raises(TypeError, match=r"event_covariance has dtype torch.float32 but prior has dtype torch.float64"):
        fuse_event(prior, event, Sigma.float())
    with pytest.raises(TypeError, match=r"event has dtype torch.float32 but prior has dtype torch.float64"):
        fuse_event(prior, event.float(), Sigma)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: prior \(\), event \(3,\), event_covariance \(4,\)"):
        fuse_event(prior, event.expand(3, 4), Sigma.expand(4, 4, 4))
    with pytest.raises(TypeError, match=r"event must be a torch.Tensor, got list"):
        fuse_event(prior, event.tolist(), Sigma)
    with pytest.raises(TypeError, match=r"prior must be a ConcentratedGaussian on SGal3, got SGal3"):
        fuse_event(prior.mean, event, Sigma)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: tau \(3,\), t_hat \(4,\)"):
        near_inertial_relative_frame(torch.zeros(3, dtype=D), torch.zeros(4, dtype=D))
    # a number t_hat is used as it is (no tensor of it made on the device); a non-finite one refused
    tau = torch.tensor([0.5, 2.0], dtype=D)
    assert torch.equal(near_inertial_relative_frame(tau, 0.25).time(), tau - 0.25)
    with pytest.raises(ValueError, match=r"t_hat must be a finite number, got inf"):
        near_inertial_relative_frame(tau, float("inf"))
    # validate=False skips the data checks; an exact timestamp (zero time variance) is allowed
    # and is the limit of a tiny one
    fuse_event(prior, event, Sigma + 0.01 * torch.triu(torch.ones(4, 4, dtype=D), 1), validate=False)
    exact_t = Sigma.clone()
    exact_t[3, 3] = 0.0
    tiny_t = Sigma.clone()
    tiny_t[3, 3] = 1e-14
    a, b = fuse_event(prior, event, exact_t), fuse_event(prior, event, tiny_t)
    torch.testing.assert_close(a.covariance, b.covariance, rtol=1e-8, atol=1e-12)


def test_gaussian_errors_name_the_groups_and_follow_the_error_policy():
    """act_velocity on a group without velocities names the groups that have them (it raised
    AttributeError from the mean); a dtype mismatch is a TypeError like everywhere else (a
    device mismatch stays a ValueError); the mean's message lists all seven groups."""
    f64 = torch.float64
    for G in ts.ALL_GROUPS:
        g = ConcentratedGaussian(G.identity(dtype=f64), 1e-2 * torch.eye(G.dof, dtype=f64))
        if G in (ts.SE23, ts.SGal3):
            assert g.act_velocity(torch.ones(3, dtype=f64)).covariance.shape == (3, 3)
        else:
            with pytest.raises(TypeError, match=rf"act_velocity is not available for a Gaussian "
                                                rf"on {G.__name__}: only SE23, SGal3 have act_velocity"):
                g.act_velocity(torch.ones(3, dtype=f64))
        with pytest.raises(TypeError, match=r"covariance \(torch.float32, cpu\) must match the mean "
                                            r"\(torch.float64, cpu\)"):
            ConcentratedGaussian(G.identity(dtype=f64), torch.eye(G.dof))
        with pytest.raises(ValueError, match=r"covariance \(torch.float64, meta\) must match the mean"):
            ConcentratedGaussian(G.identity(dtype=f64), torch.eye(G.dof, dtype=f64, device="meta"))
    with pytest.raises(TypeError, match=r"mean must be a group element \(SO2, SE2, SO3, SE3, SE23, "
                                        r"SGal3, Sim3\), got Tensor"):
        ConcentratedGaussian(torch.eye(3), torch.eye(3))


def test_fuse_checks_iterations_and_tol():
    """fuse's iterations and tol follow the conventions of fuse_event (checks.integer and
    checks.finite_number, naming the argument); they were not checked: iterations=-5, True or a
    tensor ran one step, tol=nan or -1 never stopped early."""
    f64 = torch.float64
    d = ConcentratedGaussian(ts.SE3.random(2, dtype=f64, generator=torch.Generator().manual_seed(3)),
                             0.1 * torch.eye(6, dtype=f64))
    e = ConcentratedGaussian(ts.SE3.random(2, dtype=f64, generator=torch.Generator().manual_seed(4)),
                             0.2 * torch.eye(6, dtype=f64))
    want = d.fuse(e, iterations=3)
    for it in (np.int64(3), 3):
        assert torch.equal(d.fuse(e, iterations=it).covariance, want.covariance)
    assert torch.equal(d.fuse(e, iterations=3, tol=0).covariance, want.covariance)
    for bad in (0, -5):
        with pytest.raises(ValueError, match=r"iterations must be an integer >= 1, got"):
            d.fuse(e, iterations=bad)
    for bad in (True, torch.tensor(3), 2.0):
        with pytest.raises(TypeError, match=r"iterations must be an integer >= 1, got"):
            d.fuse(e, iterations=bad)
    for bad in (float("nan"), -1, float("inf")):
        with pytest.raises(ValueError, match=r"tol must be a finite number >= 0, got"):
            d.fuse(e, tol=bad)
    with pytest.raises(TypeError, match=r"tol must be a finite number >= 0, got tensor"):
        d.fuse(e, tol=torch.tensor(1e-9))


def test_fuse_default_tol_follows_the_dtype(monkeypatch):
    """fuse's default step tolerance is 1e-12 in float64 and 1e-6 in float32: a float32 step
    never falls below 1e-12, so that default ran (and synced) every iteration."""
    calls = []
    original = ts.SE3.jr_inv
    monkeypatch.setattr(ts.SE3, "jr_inv", classmethod(lambda cls, r: calls.append(1) or original(r)))
    gen = torch.Generator().manual_seed(5)
    d = ConcentratedGaussian(ts.SE3.random(2, generator=gen), 0.1 * torch.eye(6))
    e = ConcentratedGaussian(d.mean.rplus(0.3 * torch.randn(2, 6, generator=gen)), 0.2 * torch.eye(6))

    def steps(a, b, **kw):
        calls.clear()
        out = a.fuse(b, **kw)
        return (len(calls) - 2) // 2, out  # two jr_inv per step, two for the covariance

    n32, f32 = steps(d, e)
    n32_tol, f32_tol = steps(d, e, tol=1e-6)
    assert n32 == n32_tol < 10
    assert torch.equal(f32.mean.as_matrix(), f32_tol.mean.as_matrix())
    d64, e64 = (ConcentratedGaussian(g.mean.to(torch.float64), g.covariance.double()) for g in (d, e))
    n64, _ = steps(d64, e64)
    assert n64 == steps(d64, e64, tol=1e-12)[0] > n32
    torch.testing.assert_close(f32.mean.as_matrix().double(), steps(d64, e64)[1].mean.as_matrix(),
                               rtol=0, atol=1e-5)


@pytest.mark.parametrize("G", ts.ALL_GROUPS, ids=IDS)
def test_log_prob_does_not_depend_on_the_side(G):
    """to_side is the same distribution, so it has the same density.  log_prob evaluated a left
    Gaussian with J_l: against the right-invariant measure, which on Sim3 (not unimodular)
    differs from the right side's by |det Ad(F)| = s^3 (values apart by 3 log s)."""
    D = torch.float64
    gen = torch.Generator().manual_seed(30)
    mean = G.random((), dtype=D, generator=gen)
    if G is ts.Sim3:  # a scale far from 1
        mean = mean.rplus(torch.tensor([0, 0, 0, 0, 0, 0, 0.8], dtype=D))
    for side in ("right", "left"):
        d = ConcentratedGaussian(mean, _cov(G.dof, 0.2, 31), side)
        other = d.to_side("left" if side == "right" else "right")
        x = d.sample(16, generator=gen)
        torch.testing.assert_close(other.log_prob(x), d.log_prob(x), rtol=0, atol=1e-9)


@pytest.mark.parametrize("side", ["right", "left"])
def test_sim3_log_prob_integrates_to_one(side):
    """Sim3 is not unimodular: log_prob is a density against its left-invariant Haar measure
    (|det J_r(xi)| dxi about the mean, dR dr dlambda in the matrix's parts) on either side; a
    left Gaussian integrated to E[s^-3] (about 0.1 here) before."""
    gen = torch.Generator().manual_seed(32)
    S = _cov(7, 0.2, 33, rot_scale=0.8, rot_slice=ts.Sim3._f.PHI)
    mean = ts.Sim3.exp(torch.tensor([0.1, -0.2, 0.05, 0.1, 0.2, -0.1, 0.7], dtype=torch.float64))
    p = ConcentratedGaussian(mean, S, side)
    est, se = _haar_integral(p, 100000, gen)
    assert abs(est - 1.0) < 4 * se, f"integral {est:.4f} +- {se:.4f}"


@pytest.mark.parametrize("G", [ts.SE3, ts.SGal3], ids=IDS)
def test_second_order_compounding_matches_monte_carlo(G):
    """Operands of very different covariances (the first of scale 0.2 with 0.2 rad more on the
    rotation, the second of scale 0.05 with 0.4 rad more): the second-order covariance is within
    3 root-mean-square Monte Carlo errors (0.7 and 0.8 measured), the first-order one is not
    (8.7, 6.9).  Swapping the operands of the Barfoot-Furgale terms (A_a Sa + A_b Sb), dropping
    B / 4 or taking 1/6 for 1/12 was 4.5 to 9.4 of them off."""
    phi = G._f.PHI
    gen = torch.Generator().manual_seed(34)
    S1 = _cov(G.dof, 0.2, 8, rot_scale=0.2, rot_slice=phi)
    S2 = _cov(G.dof, 0.05, 7, rot_scale=0.4, rot_slice=phi)
    m1 = G.exp(torch.randn(G.dof, dtype=torch.float64, generator=gen))
    m2 = G.exp(torch.randn(G.dof, dtype=torch.float64, generator=gen))
    d1, d2 = ConcentratedGaussian(m1, S1), ConcentratedGaussian(m2, S2)
    n = 200000
    c1, c2 = d1.compose(d2), d1.compose(d2, second_order=True)
    emp = _mc_cov(c1.perturbation(d1.sample(n, generator=gen) @ d2.sample(n, generator=gen)))
    rms = math.sqrt((float(emp.trace()) ** 2 + float(emp.norm()) ** 2) / n)
    e1, e2 = float((emp - c1.covariance).norm()) / rms, float((emp - c2.covariance).norm()) / rms
    assert e2 < 3.0, f"second order {e2:.2f} rms errors off"
    assert e1 > 5.0, f"first order only {e1:.2f} rms errors off: the case does not discriminate"


@pytest.mark.parametrize("time_row", [False, True], ids=["default", "paper-time-row"])
def test_event_fusion_covariance_large_innovation(time_row):
    """An event far from the prediction (|eps| ~ 1, J_r(eps) far from I): the iterated posterior
    is a stationary point of the cost (autograd gradient) and its covariance is the Gauss-Newton
    oracle J_r (Q^-1 + Jm^T S^-1 Jm)^-1 J_r^T to 1e-10.  Without the reset (J = I) or with J_l
    for J_r, the covariance is 0.05 or 0.13 off."""
    from torchsgal.uncertainty import fuse_event

    D = torch.float64
    prior, _, _ = _event_problem()
    Q = torch.diag(torch.tensor([0.5, 0.5, 0.5, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3, 0.2], dtype=D) ** 2)
    prior = ConcentratedGaussian(prior.mean, Q)
    event = torch.tensor([1.0, -0.7, 0.5, 2.4], dtype=D)
    Sigma = torch.diag(torch.tensor([0.1, 0.1, 0.1, 0.2], dtype=D) ** 2)
    post = fuse_event(prior, event, Sigma, iterations=20, time_row=time_row)
    eps = post.mean.rminus(prior.mean)
    assert float((ts.SGal3.jr(eps) - torch.eye(10, dtype=D)).norm()) > 0.3
    grad = torch.func.grad(lambda e: _event_cost(prior, event, Sigma, e, time_row))(eps)
    assert float(grad.norm()) < 1e-9
    expected = _event_gn_covariance(prior, event, Sigma, eps, time_row)
    torch.testing.assert_close(post.covariance, expected, rtol=0, atol=1e-10)


def test_host_reads():
    """The validation reads its measures once (it read three or four times); propagation of a
    left Gaussian reads nothing (it inverted Ad with linalg.inv, an error check per call); fuse
    with tol=0 and fuse_event read their status once at the end (they read at every inversion
    and solve); sample, mahalanobis and log_prob once (the Cholesky factorisation's check)."""
    from torchsgal.uncertainty import fuse_event

    D = torch.float64
    g = ts.SGal3.random((8,), dtype=D, generator=torch.Generator().manual_seed(35))
    P = 0.01 * torch.eye(10, dtype=D).expand(8, 10, 10)
    prior, event, Sigma = _event_problem()
    left = ConcentratedGaussian(g, P, side="left", validate=False)
    other = ConcentratedGaussian(g.rplus(0.1 * torch.ones(10, dtype=D)), P, validate=False)
    cases = {
        "ConcentratedGaussian(validate=True)": (lambda: ConcentratedGaussian(g, P), 1),
        "left compose, between, inverse": (lambda: left.compose(left).between(left).inverse(), 0),
        "act with a covariance": (lambda: left.act(torch.zeros(4, dtype=D), 0.1 * P[0, :4, :4]), 1),
        "fuse, tol=0": (lambda: left.fuse(other, iterations=3, tol=0), 1),
        "fuse_event": (lambda: fuse_event(prior, event, Sigma, iterations=3), 1),
        "fuse_event, validate=False": (lambda: fuse_event(prior, event, Sigma, validate=False), 1),
        "sample": (lambda: left.sample(2), 1),
        "log_prob": (lambda: left.log_prob(g), 1),
    }
    for name, (fn, expected) in cases.items():
        with HostSyncs() as reads:
            fn()
        assert len(reads.events) == expected, f"{name}: host reads {reads.events}, expected {expected}"
    # fuse with tol > 0: one read per iteration (the step test) and one at the end
    with HostSyncs() as reads:
        left.fuse(other, iterations=3, tol=1e-300)
    assert len(reads.events) == 4, reads.events


def test_singular_covariances_raise_in_fusion():
    """The unchecked inversions of fuse and fuse_event (torch.linalg.*_ex) still raise, by name,
    for a singular covariance (validate=False let it in), instead of returning inf or NaN."""
    from torchsgal.uncertainty import fuse_event

    D = torch.float64
    prior, event, Sigma = _event_problem()
    singular = ConcentratedGaussian(prior.mean, torch.zeros(10, 10, dtype=D), validate=False)
    with pytest.raises(ValueError, match=r"fuse: self.covariance is singular"):
        singular.fuse(prior)
    for tol in (0, 1e-12):
        with pytest.raises(ValueError, match=r"fuse: other.covariance is singular"):
            prior.fuse(singular, tol=tol)
    with pytest.raises(ValueError, match=r"fuse_event: the prior's covariance is singular"):
        fuse_event(singular, event, Sigma)
    with pytest.raises(ValueError, match=r"event_covariance has non-finite entries"):
        fuse_event(prior, event, Sigma * float("nan"))


def test_gaussian_of_a_subclass_element():
    """A Gaussian whose mean is a user subclass of a group combines with one of the built-in
    class and evaluates its elements (the group is compared through the built-in class, as the
    group operations do); fuse_event takes a prior on a subclass of SGal3."""
    from torchsgal.uncertainty import fuse_event

    class MySGal3(ts.SGal3):
        pass

    D = torch.float64
    prior, event, Sigma = _event_problem()
    sub = ConcentratedGaussian(MySGal3(prior.mean.as_matrix()), prior.covariance)
    for a, b in ((sub, prior), (prior, sub)):
        torch.testing.assert_close(a.compose(b).covariance, prior.compose(prior).covariance)
        torch.testing.assert_close(a.fuse(b).covariance, prior.fuse(prior).covariance)
    torch.testing.assert_close(sub.log_prob(prior.mean), prior.log_prob(prior.mean))
    torch.testing.assert_close(prior.mahalanobis(sub.mean), torch.zeros((), dtype=D))
    torch.testing.assert_close(fuse_event(sub, event, Sigma).covariance,
                               fuse_event(prior, event, Sigma).covariance)
    with pytest.raises(TypeError, match=r"other must be a ConcentratedGaussian on SGal3"):
        sub.compose(ConcentratedGaussian(ts.SE23.identity(dtype=D), torch.eye(9, dtype=D)))


def test_fusion_under_vmap_over_the_means_only():
    """fuse and fuse_event read their status at the end; under vmap with only a mean (or the
    relative frame) mapped that read is not attempted (deciding readability on the
    covariances alone would attempt it and crash).  Each mapped result equals the batched call."""
    D = torch.float64
    gen = torch.Generator().manual_seed(71)
    means = ts.SE3.random((4,), dtype=D, generator=gen)
    S = 0.01 * torch.eye(6, dtype=D)
    prior = ConcentratedGaussian(ts.SE3.random((), dtype=D, generator=gen), 0.02 * torch.eye(6, dtype=D))
    f = lambda M: prior.fuse(ConcentratedGaussian(ts.SE3(M), S)).covariance  # noqa: E731
    want = prior.fuse(ConcentratedGaussian(means, S.expand(4, 6, 6))).covariance
    torch.testing.assert_close(torch.func.vmap(f)(means.as_matrix()), want, rtol=0, atol=1e-15)
    from torchsgal.uncertainty import fuse_event

    _, event, Sigma = _event_problem()
    P = 0.01 * torch.eye(10, dtype=D)
    frames = ts.SGal3.random((3,), dtype=D, generator=gen).as_matrix()
    g = lambda M: fuse_event(ConcentratedGaussian(ts.SGal3(M), P), event, Sigma).covariance  # noqa: E731
    want = fuse_event(ConcentratedGaussian(ts.SGal3(frames), P.expand(3, 10, 10)), event, Sigma).covariance
    torch.testing.assert_close(torch.func.vmap(g)(frames), want, rtol=0, atol=1e-15)


# ------------------------------------------------------------------ singular covariances
def _imu_gaussian():
    """The rank-9 covariance of an IMU increment (exact timestamps: zero time row and column)."""
    from torchsgal.imu import preintegrate
    g = torch.Generator().manual_seed(3)
    gyro = torch.randn(40, 3, dtype=torch.float64, generator=g)
    acc = torch.randn(40, 3, dtype=torch.float64, generator=g) + 9.8
    pre = preintegrate(gyro, acc, 0.01, gyro_noise_density=0.05, acc_noise_density=0.5)
    return pre.delta, pre.covariance


def test_imu_rank9_covariance_is_accepted_with_a_9_dof_nees():
    mean, S = _imu_gaussian()
    assert not S[9].any() and not S[:, 9].any()
    with pytest.raises(RuntimeError):
        torch.linalg.cholesky(S)  # singular: the full-rank route cannot take it
    d = ConcentratedGaussian(mean, S)
    assert int(d.rank()) == 9
    x = d.sample((N_MC,), generator=torch.Generator().manual_seed(1))
    xi = x.rminus(mean)
    assert not xi[..., 9].any()  # the known direction is exact
    nees = d.mahalanobis(x) ** 2
    # chi-square with 9 dof: mean 9, variance 18; the sample mean within 4 standard errors
    assert abs(float(nees.mean()) - 9.0) < 4 * math.sqrt(18.0 / N_MC)
    lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], 9)
    inside = float(((nees > lo) & (nees < hi)).double().mean())
    assert abs(inside - 0.95) < 4 * math.sqrt(0.95 * 0.05 / N_MC)


def test_singular_log_prob_against_scipy_and_the_full_rank_limit():
    mean, S = _imu_gaussian()
    d = ConcentratedGaussian(mean, S)
    g = torch.Generator().manual_seed(2)
    xi = 0.5 * d.sample((5,), generator=g).rminus(mean)  # on the support (time 0)
    pts = mean.rplus(xi)
    got = d.log_prob(pts)
    # scipy's degenerate normal on the supported subspace, with the group's Jacobian term
    ref = scipy.stats.multivariate_normal(np.zeros(10), S.numpy(), allow_singular=True).logpdf(xi.numpy())
    ref = torch.as_tensor(ref) - torch.linalg.slogdet(ts.SGal3.jr(xi))[1]
    assert torch.allclose(got, ref, rtol=0, atol=1e-8)
    # the limit of the full-rank density as the known direction's variance s^2 goes to 0
    for s2 in (1e-6, 1e-12):
        full = S.clone()
        full[9, 9] = s2
        lp = ConcentratedGaussian(mean, full).log_prob(pts)
        assert torch.allclose(lp + 0.5 * math.log(2 * math.pi * s2), got, rtol=0, atol=1e-9)
    # the NEES ignores nothing on the support: it is the pseudo-inverse quadratic form
    quad = (xi.unsqueeze(-2) @ torch.linalg.pinv(S) @ xi.unsqueeze(-1)).reshape(-1)
    assert torch.allclose(d.mahalanobis(pts) ** 2, quad, rtol=1e-9, atol=0)


def test_singular_covariance_rules():
    G = ts.SE3
    mean = G.random((), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    A = torch.randn(6, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    S = 0.01 * A @ A.T  # rank 4, null directions not along the axes
    with pytest.raises(ValueError, match="not positive definite.*allow_singular=True"):
        ConcentratedGaussian(mean, S)
    d = ConcentratedGaussian(mean, S, allow_singular=True)
    assert int(d.rank()) == 4
    xi = d.sample((200,), generator=torch.Generator().manual_seed(3)).rminus(mean)
    Q, _ = torch.linalg.qr(A, mode="complete")
    null = Q[:, 4:]  # the orthogonal complement of the range
    assert (xi @ null).abs().max() < 1e-12
    ref = scipy.stats.multivariate_normal(np.zeros(6), S.numpy(), allow_singular=True).logpdf(xi[:4].numpy())
    ref = torch.as_tensor(ref) - torch.linalg.slogdet(G.jr(xi[:4]))[1]
    assert torch.allclose(d.log_prob(mean.rplus(xi[:4])), ref, rtol=0, atol=1e-8)
    # derived Gaussians keep the rule
    assert d.to_side("left").allow_singular and d.inverse().allow_singular
    # a zero row with a non-definite rest, or an indefinite matrix, is refused
    S2 = torch.eye(6, dtype=torch.float64)
    S2[0, 0] = 0.0
    S2[1, 2] = S2[2, 1] = 1.0  # the rest singular, not along axes
    with pytest.raises(ValueError, match="not positive definite"):
        ConcentratedGaussian(mean, S2)
    bad = torch.diag(torch.tensor([1.0, 1.0, 1.0, 1.0, 1.0, -1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="not positive semi-definite"):
        ConcentratedGaussian(mean, bad, allow_singular=True)
    with pytest.raises(TypeError, match="allow_singular must be"):
        ConcentratedGaussian(mean, torch.eye(6, dtype=torch.float64), allow_singular="no")
    # definite covariances: the same values as before (known directions: none)
    P = _cov(6, 0.1, 5)
    a, b = ConcentratedGaussian(mean, P), ConcentratedGaussian(mean, P, allow_singular=True)
    x = a.sample((50,), generator=torch.Generator().manual_seed(4))
    assert int(a.rank()) == 6
    assert torch.allclose(a.log_prob(x), b.log_prob(x), rtol=1e-12, atol=1e-12)
    assert torch.allclose(a.mahalanobis(x), b.mahalanobis(x), rtol=1e-12, atol=0)


def test_singular_covariance_gradients_are_finite_where_eigenvalues_repeat():
    """With allow_singular=True the covariance is factored on its support (eigh's vectors held
    as constants): gradients of log_prob are those of the definite path for full-rank
    covariances, isotropic ones (repeated eigenvalues: eigh's derivatives are NaN there)
    included; for a rank-deficient one with repeated eigenvalues they are finite and pass
    gradcheck at points on the support."""
    f64 = torch.float64
    mean = ts.SE3.random((), dtype=f64, generator=torch.Generator().manual_seed(2))
    pts = mean.rplus(0.1 * torch.randn(5, 6, dtype=f64, generator=torch.Generator().manual_seed(3)))
    A = torch.randn(6, 6, dtype=f64, generator=torch.Generator().manual_seed(4))
    for P0 in (0.01 * torch.eye(6, dtype=f64), torch.diag(torch.tensor([1.0, 1, 1, 2, 2, 3], dtype=f64)),
               0.1 * A @ A.T + 0.1 * torch.eye(6, dtype=f64)):
        grads = []
        for singular in (False, True):
            P = P0.clone().requires_grad_()
            ConcentratedGaussian(mean, P, allow_singular=singular).log_prob(pts).sum().backward()
            grads.append(P.grad)
        torch.testing.assert_close(grads[1], grads[0], rtol=1e-10, atol=1e-12)
    # rank 5 with repeated eigenvalues, the null direction off the axes: S = B B^T, B (6, 5)
    R = ts.SO3.exp(torch.tensor([0.3, -0.2, 0.5], dtype=f64)).as_matrix()
    B = torch.block_diag(R, R)[:, :5] * torch.tensor([0.7, 0.7, 0.7, 0.4, 0.4], dtype=f64).sqrt()
    S = B @ B.T
    on_support = ConcentratedGaussian(mean, S, allow_singular=True).sample(
        (4,), generator=torch.Generator().manual_seed(5))
    P = S.clone().requires_grad_()
    ConcentratedGaussian(mean, P, allow_singular=True).log_prob(on_support).sum().backward()
    assert torch.isfinite(P.grad).all()

    def log_prob(B):  # of rank 5 for every B near the one above (a smooth function of B)
        return ConcentratedGaussian(mean, B @ B.mT, allow_singular=True, validate=False).log_prob(on_support)

    assert torch.autograd.gradcheck(log_prob, (B.clone().requires_grad_(),))


def test_covariance_factor_is_the_checked_square_root():
    """covariance_factor gives the Cholesky factor of a full covariance and the square-root
    diagonal of a diagonal one, refuses what check_covariance refuses (with its messages), and
    every estimator that reads a noise covariance (IMU factors, Gauss-Helmert conditions, TLS)
    applies the same tolerance: an asymmetry of 1e-12 relative passes all of them, 1e-6 none."""
    from torchsgal.estimation import graph as fg
    from torchsgal.imu.factors import sqrt_information_from_covariance
    from torchsgal.uncertainty.covariance import check_covariance, covariance_factor

    D = torch.float64
    gen = torch.Generator().manual_seed(3)
    A = torch.randn(4, 5, 5, dtype=D, generator=gen)
    S = A @ A.mT + 0.1 * torch.eye(5, dtype=D)
    diagonal, L = covariance_factor(S, "S")
    assert not diagonal
    torch.testing.assert_close(L, torch.linalg.cholesky(S), rtol=0, atol=1e-13)
    d = torch.tensor([4.0, 9.0, 0.25], dtype=D)
    diagonal, R = covariance_factor(torch.diag(d), "S")
    assert diagonal and torch.equal(R, torch.tensor([2.0, 3.0, 0.5], dtype=D))
    info = sqrt_information_from_covariance(S)
    torch.testing.assert_close(info.mT @ info, torch.linalg.inv(S), rtol=1e-10, atol=1e-10)
    assert torch.equal(sqrt_information_from_covariance(torch.diag(d)), torch.diag(1 / d.sqrt()))
    with pytest.raises(ValueError, match=r"^S is not positive definite \(1 of the batch\)$"):
        covariance_factor(torch.diag(torch.tensor([1.0, -1.0], dtype=D)), "S")
    with pytest.raises(ValueError, match=r"^S has non-finite entries$"):
        covariance_factor(torch.diag(torch.tensor([1.0, float("nan")], dtype=D)), "S")
    with pytest.raises(ValueError, match=r"^S must have shape \(\.\.\., m, m\) with m >= 1, got \(0, 0\)$"):
        covariance_factor(torch.zeros(0, 0, dtype=D), "S")
    with pytest.raises(TypeError, match=r"^S must be a tensor \(\.\.\., m, m\), got list$"):
        covariance_factor([[1.0]], "S")

    def skewed(eps):
        C = torch.eye(10, dtype=D)
        C[0, 1] = eps
        return C

    for eps, passes in ((1e-12, True), (1e-6, False)):
        C = skewed(eps)
        readers = [lambda C=C: check_covariance(C, 10), lambda C=C: covariance_factor(C),
                   lambda C=C: sqrt_information_from_covariance(C),
                   lambda C=C: fg.GaussHelmert(lambda F, e: F.log() - e,
                                               [("F", torch.zeros(1, dtype=torch.int64))], C, dim=10)]
        for read in readers:
            if passes:
                read()
            else:
                with pytest.raises(ValueError, match="is not symmetric"):
                    read()


def test_covariance_factor_of_a_differentiated_diagonal_covariance_keeps_its_derivatives():
    """At a diagonal covariance that something differentiates, the factor is the Cholesky
    factor, whose derivatives in the off-diagonal entries are not zero: the IMU factors'
    square-root information then has the gradient of cholesky + triangular solve (reverse mode,
    forward mode and torch.func alike), where the square-root diagonal would give zero to every
    off-diagonal entry (a full covariance learnt from a diagonal start would never leave it)."""
    from torch.autograd import forward_ad

    from torchsgal.imu.factors import sqrt_information_from_covariance
    from torchsgal.uncertainty.covariance import covariance_factor

    D = torch.float64
    w = torch.arange(9, dtype=D).reshape(3, 3) / 7 - 0.5

    def reference(C):
        L = torch.linalg.cholesky(C)
        return torch.linalg.solve_triangular(L, torch.eye(3, dtype=D), upper=False)

    A = torch.diag(torch.tensor([1.0, 2.0, 3.0], dtype=D)).requires_grad_()
    (sqrt_information_from_covariance(A @ A.mT) * w).sum().backward()
    A_ref = A.detach().clone().requires_grad_()
    (reference(A_ref @ A_ref.mT) * w).sum().backward()
    torch.testing.assert_close(A.grad, A_ref.grad, rtol=1e-12, atol=1e-14)
    assert A.grad[0, 1] != 0
    C = torch.diag(torch.tensor([1.0, 4.0, 9.0], dtype=D))
    diagonal, _ = covariance_factor(C.requires_grad_())
    assert not diagonal
    assert covariance_factor(C.detach())[0]
    with torch.no_grad():
        assert covariance_factor(C)[0]  # nothing records: the square-root diagonal
    E = torch.zeros(3, 3, dtype=D)
    E[0, 1] = E[1, 0] = 1.0
    with forward_ad.dual_level():
        out = sqrt_information_from_covariance(forward_ad.make_dual(C.detach(), E))
        tangent = forward_ad.unpack_dual(out).tangent
    expected = torch.func.jvp(reference, (C.detach(),), (E,))[1]
    torch.testing.assert_close(tangent, expected, rtol=1e-12, atol=1e-14)
    assert tangent[1, 0] != 0
