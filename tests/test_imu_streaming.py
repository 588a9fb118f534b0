"""Streaming preintegration (torchsgal.imu.streaming) against the window function
(torchsgal.imu.preintegrate) on the same samples, and the IMU input checks.

- every field (increment, covariance, bias Jacobian) equal to 1e-12 under seeded random
  chunkings, one-sample calls (held and folded at once) and chunks, batched IMUs;
- intermediate increments against windows of the prefixes;
- the first-order bias update against re-integration with the new bias (error O(|db|^2));
- the bias random walk's combined covariance against a per-sample recursion written here with
  the group API (Phi = [[Ad(E^-1), J_k], [0, I]]) and invariance under chunking;
- bad input: clear errors.
"""
from __future__ import annotations

import math

import pytest
import torch

from torchsgal import SGal3
from torchsgal.imu import earth_rate_vector, gravity_vector, preintegrate
from torchsgal.imu.streaming import StreamingPreintegration

F64 = torch.float64
DENS = dict(gyro_noise_density=2e-2, acc_noise_density=3e-1, time_noise_density=1e-3)


def stream(batch, K, seed, rate=2.0):
    g = torch.Generator().manual_seed(seed)
    gyro = rate * torch.randn(*batch, K, 3, generator=g, dtype=F64)
    acc = 3.0 * torch.randn(*batch, K, 3, generator=g, dtype=F64) + torch.tensor([0, 0, 9.8], dtype=F64)
    dt = 0.002 + 0.02 * torch.rand(*batch, K, generator=g, dtype=F64)
    bg = 0.05 * torch.randn(*batch, 3, generator=g, dtype=F64)
    ba = 0.2 * torch.randn(*batch, 3, generator=g, dtype=F64)
    return gyro, acc, dt, bg, ba


def random_splits(K, seed):
    g = torch.Generator().manual_seed(seed)
    cuts, i = [], 0
    while i < K:
        n = int(torch.randint(1, 9, (1,), generator=g)) if torch.rand(1, generator=g) < 0.7 else 1
        n = min(n, K - i)
        cuts.append((i, n))
        i += n
    return cuts


def feed(s, gyro, acc, dt, cuts, as_number=False):
    """Calls of one sample ((*batch, 3)) where n == 1, chunks otherwise."""
    for i, n in cuts:
        if n == 1:
            h = float(dt.reshape(-1)[0]) if as_number else dt[..., i]
            s.integrate(gyro[..., i, :], acc[..., i, :], h)
        else:
            s.integrate(gyro[..., i:i + n, :], acc[..., i:i + n, :], dt[..., i:i + n])


def assert_matches(s, pre, tol=1e-12):
    scale = pre.covariance.abs().amax(dim=(-1, -2), keepdim=True)
    assert (s.delta.as_matrix() - pre.delta.as_matrix()).abs().max() < tol
    assert ((s.covariance - pre.covariance).abs() / scale).max() < tol
    assert (s.bias_jacobian - pre.bias_jacobian).abs().max() < tol
    assert torch.equal(s.gyro_bias, pre.gyro_bias) and torch.equal(s.acc_bias, pre.acc_bias)


@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
@pytest.mark.parametrize("buffer_size", [1, 5, 256])
def test_streaming_equals_window_under_random_chunkings(batch, buffer_size):
    K = 53
    gyro, acc, dt, bg, ba = stream(batch, K, seed=len(batch) + buffer_size)
    pre = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, **DENS)
    for seed in range(3):
        s = StreamingPreintegration(batch, gyro_bias=bg, acc_bias=ba, buffer_size=buffer_size,
                                    dtype=F64, **DENS)
        feed(s, gyro, acc, dt, random_splits(K, seed))
        assert s.num_samples == K
        assert_matches(s, pre)


def test_one_sample_calls_and_large_rotations():
    """Every sample alone (the one-sample formulas (C2)), rotations per sample up to ~3 rad (the
    closed-form branch of the coefficients) and a number dt."""
    gyro, acc, dt, bg, ba = stream((3,), 30, seed=7, rate=40.0)
    dt = torch.full_like(dt, 0.03)
    pre = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, **DENS)
    assert (gyro.norm(dim=-1) * 0.03).max() > 2.5
    for buffer_size in (1, 7):  # folded at once, and held in groups of single samples
        s = StreamingPreintegration((3,), gyro_bias=bg, acc_bias=ba, buffer_size=buffer_size,
                                    dtype=F64, **DENS)
        feed(s, gyro, acc, dt, [(i, 1) for i in range(30)], as_number=True)
        assert_matches(s, pre)


@pytest.mark.parametrize("buffer_size", [1, 5])
def test_one_sample_chunks_and_number_dt_held_with_tensor_dt_chunks(buffer_size):
    """Calls of (*batch, 1, 3) chunks, single samples with a number dt (one dt for the whole
    stream) and longer chunks with tensor dt, held together and folded as one chunk."""
    gyro, acc, dt, bg, ba = stream((2,), 24, seed=11)
    dt = torch.full_like(dt, 0.01)
    pre = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, **DENS)
    s = StreamingPreintegration((2,), gyro_bias=bg, acc_bias=ba, buffer_size=buffer_size,
                                dtype=F64, **DENS)
    i = 0
    for n, kind in [(1, "chunk"), (1, "number"), (3, "chunk"), (1, "number"), (1, "chunk"),
                    (4, "chunk"), (1, "number"), (1, "number"), (2, "chunk"), (1, "chunk"),
                    (5, "chunk"), (1, "number"), (2, "chunk")]:
        if kind == "number":
            s.integrate(gyro[..., i, :], acc[..., i, :], 0.01)
        else:
            s.integrate(gyro[..., i:i + n, :], acc[..., i:i + n, :], dt[..., i:i + n])
        i += n
    assert i == 24 and s.num_samples == 24
    assert_matches(s, pre)


def test_per_axis_densities_and_float32():
    gyro, acc, dt, bg, ba = stream((2,), 20, seed=3)
    dens = dict(gyro_noise_density=torch.tensor([1e-2, 2e-2, 3e-2], dtype=F64),
                acc_noise_density=torch.tensor([[0.1, 0.2, 0.3], [0.3, 0.2, 0.1]], dtype=F64))
    pre = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, **dens)
    for bs in (1, 256):
        s = StreamingPreintegration((2,), gyro_bias=bg, acc_bias=ba, buffer_size=bs, dtype=F64, **dens)
        feed(s, gyro, acc, dt, random_splits(20, 1))
        assert_matches(s, pre)
    f32 = [x.float() for x in (gyro, acc, dt, bg, ba)]
    s = StreamingPreintegration((2,), gyro_bias=f32[3], acc_bias=f32[4], dtype=torch.float32, **DENS)
    feed(s, *f32[:3], random_splits(20, 2))
    pre = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, **DENS)
    assert s.covariance.dtype == torch.float32
    assert (s.delta.as_matrix().double() - pre.delta.as_matrix()).abs().max() < 1e-5


def test_intermediate_increments_equal_windows_of_prefixes():
    gyro, acc, dt, bg, ba = stream((2,), 24, seed=11)
    s = StreamingPreintegration((2,), gyro_bias=bg, acc_bias=ba, dtype=F64, **DENS)
    got = []
    for i, n in [(0, 1), (1, 7), (8, 1), (9, 15)]:
        if n == 1:
            out = s.integrate(gyro[:, i], acc[:, i], dt[:, i], intermediate=True)
        else:
            out = s.integrate(gyro[:, i:i + n], acc[:, i:i + n], dt[:, i:i + n], intermediate=True)
        assert isinstance(out, SGal3) and out.batch_shape == (2, n)
        got.append(out.as_matrix())
    got = torch.cat(got, dim=1)
    for k in range(24):
        want = preintegrate(gyro[:, :k + 1], acc[:, :k + 1], dt[:, :k + 1], gyro_bias=bg, acc_bias=ba,
                            covariance=False, bias_jacobian=False).delta.as_matrix()
        assert (got[:, k] - want).abs().max() < 1e-12
    assert s.integrate(gyro[:, 0], acc[:, 0], dt[:, 0]) is None


def test_reset_starts_a_new_window_and_sets_biases():
    gyro, acc, dt, bg, ba = stream((), 20, seed=5)
    s = StreamingPreintegration(gyro_bias=bg, acc_bias=ba, dtype=F64, **DENS)
    s.integrate(gyro[:10], acc[:10], dt[:10])
    s.integrate(gyro[10], acc[10], dt[10])  # held, then dropped by reset
    s.reset()
    assert s.num_samples == 0
    assert torch.equal(s.delta.as_matrix(), torch.eye(5, dtype=F64))
    assert not s.covariance.any() and not s.bias_jacobian.any()
    s.integrate(gyro[10:], acc[10:], dt[10:])
    assert_matches(s, preintegrate(gyro[10:], acc[10:], dt[10:], gyro_bias=bg, acc_bias=ba, **DENS))
    s.reset(gyro_bias=2 * bg)  # the acc bias kept
    s.integrate(gyro, acc, dt)
    assert_matches(s, preintegrate(gyro, acc, dt, gyro_bias=2 * bg, acc_bias=ba, **DENS))


def test_bias_update_is_first_order():
    """delta exp(J db) against re-integration with b + db: the error falls as |db|^2."""
    gyro, acc, dt, bg, ba = stream((), 40, seed=2)
    s = StreamingPreintegration(gyro_bias=bg, acc_bias=ba, dtype=F64, **DENS)
    feed(s, gyro, acc, dt, random_splits(40, 4))
    direction = torch.tensor([0.3, -0.2, 0.5, 1.0, -0.7, 0.4], dtype=F64)
    errors = []
    for eps in (1e-2, 5e-3, 2.5e-3):
        db = eps * direction
        fresh = preintegrate(gyro, acc, dt, gyro_bias=bg + db[:3], acc_bias=ba + db[3:],
                             covariance=False, bias_jacobian=False).delta
        moved = s.corrected(gyro_bias=bg + db[:3], acc_bias=ba + db[3:])
        assert isinstance(moved, SGal3)
        errors.append(float((moved.inverse().compose(fresh)).log().norm()))
        uncorrected = float(s.delta.inverse().compose(fresh).log().norm())
        assert errors[-1] < 0.05 * uncorrected
    for big, small in zip(errors, errors[1:]):
        assert 3.5 < big / small < 4.5  # second order


def test_predict_uses_the_corrected_increment():
    gyro, acc, dt, bg, ba = stream((), 15, seed=9)
    s = StreamingPreintegration(gyro_bias=bg, acc_bias=ba, dtype=F64)
    s.integrate(gyro, acc, dt)
    start = SGal3.random((), dtype=F64, generator=torch.Generator().manual_seed(0))
    g = gravity_vector(dtype=F64)
    pre = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba)
    want = pre.predict(start, g, gyro_bias=bg + 0.01)
    got = s.predict(start, g, gyro_bias=bg + 0.01)
    assert (got.as_matrix() - want.as_matrix()).abs().max() < 1e-12


# ----------------------------------------------------------------------- random walk
def sequential_combined(gyro, acc, dt, bg, ba, walk):
    """[eps, db] (16) propagated sample by sample: x' = Phi x + w, Phi = [[Ad(E^-1), J_k], [0, I]],
    w ~ N(0, diag(S_k, R dt_k)), with E, S_k, J_k the window function's one-sample results."""
    P = torch.zeros(16, 16, dtype=F64)
    R = torch.cat((walk[0] ** 2 * torch.ones(3, dtype=F64), walk[1] ** 2 * torch.ones(3, dtype=F64)))
    for k in range(gyro.shape[0]):
        one = preintegrate(gyro[k:k + 1], acc[k:k + 1], dt[k:k + 1], gyro_bias=bg, acc_bias=ba, **DENS)
        Phi = torch.eye(16, dtype=F64)
        Phi[:10, :10] = one.delta.inverse().adjoint()
        Phi[:10, 10:] = one.bias_jacobian
        W = torch.zeros(16, 16, dtype=F64)
        W[:10, :10] = one.covariance
        W[10:, 10:] = torch.diag(R * dt[k])
        P = Phi @ P @ Phi.T + W
    return P


def test_bias_random_walk_combined_covariance():
    K = 25
    gyro, acc, dt, bg, ba = stream((), K, seed=13)
    walk = (3e-3, 4e-2)
    want = sequential_combined(gyro, acc, dt, bg, ba, walk)
    assert want[:10, 10:].abs().max() > 1e-6  # the cross terms are there
    for seed, bs in ((0, 1), (1, 256), (2, 3)):
        s = StreamingPreintegration(gyro_bias=bg, acc_bias=ba, gyro_bias_random_walk=walk[0],
                                    acc_bias_random_walk=walk[1], buffer_size=bs, dtype=F64, **DENS)
        feed(s, gyro, acc, dt, random_splits(K, seed))
        P = s.combined_covariance()
        assert P.shape == (16, 16)
        assert ((P - want).abs() / want.abs().max()).max() < 1e-12
        # covariance and result() are the window function's (no random walk: an ImuFactor next
        # to a BiasRandomWalkFactor would count it twice); the combined block adds the walk
        pre = preintegrate(gyro, acc, dt, gyro_bias=bg, acc_bias=ba, **DENS)
        scale = pre.covariance.abs().max()
        assert ((s.covariance - pre.covariance).abs().max()) < 1e-14 * scale
        assert ((s.result().covariance - pre.covariance).abs().max()) < 1e-14 * scale
        assert (P[:10, :10] - pre.covariance).abs().max() > 1e-6 * scale
        T = float(dt.sum())
        assert torch.allclose(torch.diagonal(P[10:, 10:]),
                              torch.tensor([walk[0] ** 2 * T] * 3 + [walk[1] ** 2 * T] * 3, dtype=F64),
                              rtol=1e-13, atol=0)
    no_walk = StreamingPreintegration(dtype=F64, **DENS)
    no_walk.integrate(gyro, acc, dt)
    assert not no_walk.combined_covariance()[:, 10:].any()


# ------------------------------------------------------------------------ bad input
def test_streaming_bad_input_errors():
    s = StreamingPreintegration((2,), dtype=F64)
    g = torch.zeros(2, 3, dtype=F64)
    with pytest.raises(ValueError, match=r"dt must be a finite number > 0, got 0"):
        s.integrate(g, g, 0.0)
    for bad in (-0.01, math.inf, math.nan):
        with pytest.raises(ValueError, match=r"dt must be a finite number > 0"):
            s.integrate(g, g, bad)
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match=r"dt must be finite and > 0 everywhere, got 1 other"):
            s.integrate(g, g, torch.tensor([0.01, bad], dtype=F64))
    with pytest.raises(ValueError, match=r"gyro must have shape \(\*batch_shape, 3\) \(one sample\) or"):
        s.integrate(torch.zeros(3, 3, dtype=F64), torch.zeros(3, 3, dtype=F64), 0.01)
    with pytest.raises(ValueError, match=r"gyro must have shape"):
        s.integrate(torch.zeros(2, 4, dtype=F64), torch.zeros(2, 4, dtype=F64), 0.01)
    with pytest.raises(ValueError, match=r"acc must have gyro's shape"):
        s.integrate(g, torch.zeros(2, 1, 3, dtype=F64), 0.01)
    with pytest.raises(TypeError, match=r"gyro must have dtype torch.float64"):
        s.integrate(g.float(), g.float(), 0.01)
    with pytest.raises(TypeError, match=r"dt must have gyro's dtype and device"):
        s.integrate(g, g, torch.tensor([0.01, 0.01]))
    with pytest.raises(ValueError, match=r"dt must have shape \(2, 5\)"):
        s.integrate(torch.zeros(2, 5, 3, dtype=F64), torch.zeros(2, 5, 3, dtype=F64), torch.ones(2, 4, dtype=F64))
    with pytest.raises(ValueError, match=r"gyro must hold at least one sample"):
        s.integrate(torch.zeros(2, 0, 3, dtype=F64), torch.zeros(2, 0, 3, dtype=F64), 0.01)
    with pytest.raises(TypeError, match="intermediate must be"):
        s.integrate(g, g, 0.01, intermediate="no")
    assert s.num_samples == 0  # nothing was taken from the refused calls
    with pytest.raises(TypeError, match="validate must be"):
        StreamingPreintegration(validate="no")
    with pytest.raises(TypeError, match="buffer_size must be an integer >= 1"):
        StreamingPreintegration(buffer_size=2.5)
    with pytest.raises(ValueError, match="buffer_size must be an integer >= 1"):
        StreamingPreintegration(buffer_size=0)
    with pytest.raises(ValueError, match="gyro_noise_density must be a finite number >= 0"):
        StreamingPreintegration(gyro_noise_density=math.nan)
    with pytest.raises(ValueError, match="acc_bias_random_walk must be a finite number >= 0"):
        StreamingPreintegration(acc_bias_random_walk=-1.0)
    with pytest.raises(TypeError, match="batch_shape must be a tuple of integers"):
        StreamingPreintegration(batch_shape=(2.0,))
    with pytest.raises(ValueError, match=r"gyro_bias of shape \(3, 3\) must broadcast to \(2, 3\)"):
        StreamingPreintegration((2,), gyro_bias=torch.zeros(3, 3, dtype=F64), dtype=F64)
    with pytest.raises(TypeError, match=r"acc_bias must have dtype torch.float64"):
        StreamingPreintegration((2,), acc_bias=torch.zeros(3), dtype=F64)


def test_streaming_does_not_hold_references_to_inputs():
    """A caller reusing one buffer for every sample: the held samples are copies."""
    gyro, acc, dt, bg, ba = stream((), 10, seed=1)
    s = StreamingPreintegration(dtype=F64, **DENS)
    g_buf, a_buf = torch.empty(3, dtype=F64), torch.empty(3, dtype=F64)
    for k in range(10):
        g_buf.copy_(gyro[k])
        a_buf.copy_(acc[k])
        s.integrate(g_buf, a_buf, dt[k])
    assert_matches(s, preintegrate(gyro, acc, dt, **DENS))


# ------------------------------------------------------------ window function inputs
def test_preintegrate_refuses_non_finite_dt_in_tensors():
    gyro, acc, dt, _, _ = stream((2,), 5, seed=1)
    for bad in (math.inf, math.nan):
        d = dt.clone()
        d[1, 2] = bad
        for kw in ({}, dict(covariance=False, bias_jacobian=False), dict(gyro_noise_density=1e-3)):
            with pytest.raises(ValueError, match=r"dt must be finite and >= 0 everywhere, got 1 "
                                                 r"negative, infinite or NaN"):
                preintegrate(gyro, acc, d, **kw)
    with pytest.raises(ValueError, match=r"gyro_noise_density must be finite and >= 0 everywhere"):
        preintegrate(gyro, acc, dt, gyro_noise_density=torch.tensor([1e-3, math.inf, 0.0], dtype=F64))


def test_gravity_and_earth_rate_refuse_non_finite_numbers():
    for bad in (math.nan, math.inf):
        with pytest.raises(ValueError, match="magnitude must be a finite number"):
            gravity_vector("ned", bad)
        with pytest.raises(ValueError, match="latitude must be a finite number"):
            earth_rate_vector(bad)
        with pytest.raises(ValueError, match="rate must be a finite number"):
            earth_rate_vector(0.5, rate=bad)
    with pytest.raises(TypeError, match="magnitude must be a finite number"):
        gravity_vector("z_up", "9.8")
    assert torch.equal(gravity_vector("ned", 9.0, dtype=F64), torch.tensor([0.0, 0.0, 9.0], dtype=F64))


def test_preintegrate_flags_are_booleans():
    gyro, acc, dt, _, _ = stream((), 4, seed=1)
    for flag in ("covariance", "bias_jacobian"):
        for bad in ("no", 0, 1, None, torch.tensor(True)):
            with pytest.raises(TypeError, match=f"{flag} must be"):
                preintegrate(gyro, acc, dt, **{flag: bad})


def test_gradients_equal_the_window_functions():
    """Autograd through the one-sample formulas, the chunk composition and the held samples:
    the gradients of a scalar of every field equal the window function's (zero rotation
    included: no NaN from the series at theta = 0)."""
    gyro, acc, dt, bg, ba = stream((2,), 12, seed=4)
    gyro[0, 3] = bg[0]  # a sample with no rotation
    weights = [torch.randn(5, 5, dtype=F64), torch.randn(10, 10, dtype=F64), torch.randn(10, 6, dtype=F64)]

    def scalar(delta, cov, jac):
        return sum((w * x).sum() for w, x in zip(weights, (delta, cov / cov.abs().max().detach(), jac)))

    grads = []
    for use_stream in (False, True):
        g = gyro.clone().requires_grad_(True)
        a = acc.clone().requires_grad_(True)
        if use_stream:
            s = StreamingPreintegration((2,), gyro_bias=bg, acc_bias=ba, buffer_size=4, dtype=F64, **DENS)
            feed(s, g, a, dt, [(0, 1), (1, 1), (2, 5), (7, 1), (8, 4)])
            value = scalar(s.delta.as_matrix(), s.covariance, s.bias_jacobian)
        else:
            pre = preintegrate(g, a, dt, gyro_bias=bg, acc_bias=ba, **DENS)
            value = scalar(pre.delta.as_matrix(), pre.covariance, pre.bias_jacobian)
        grads.append(torch.autograd.grad(value, (g, a)))
    for want, got in zip(*grads):
        assert torch.isfinite(got).all()
        assert (got - want).abs().max() < 1e-10 * want.abs().max()
