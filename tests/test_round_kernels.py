"""The Levenberg-Marquardt round's two operators (estimation/graph/round_update.py,
damped_solve.py; their C kernels in estimation/_native_round.h and _native_cholesky.h):

- ``torchsgal::lm_round_update``: GTSAM's verdict and the bookkeeping after a trial step, on
  problems written out by hand (one per branch: accepted, rejected with lambda raised, search
  stopped, given up, converged, out of iterations, Gauss-Newton), and the kernel against its
  tensor code bit for bit on random and non-finite inputs in both dtypes;
- ``torchsgal::damped_solve``: (H + lam D) delta = -g against ``torch.linalg.solve`` of the
  damped matrix built here, every system size the kernel takes, both dampings and dtypes,
  failed factors and non-finite systems, lanes partly filled, one or two threads;
- both: opcheck, no derivative, no argument written, bad arguments named."""
from __future__ import annotations

import contextlib

import pytest
import torch
from test_factor_kernels import needs_kernel
from torch.library import opcheck

from torchsgal.estimation import dense_solve
from torchsgal.estimation.graph import damped_solve, round_update
from torchsgal.estimation.solver import SolverStatus
from torchsgal.functional import native

f64 = torch.float64
update = torch.ops.torchsgal.lm_round_update
solve = torch.ops.torchsgal.damped_solve
RUNNING, CONVERGED = int(SolverStatus.RUNNING), int(SolverStatus.CONVERGED)
DIVERGED, MAX_IT = int(SolverStatus.DIVERGED), int(SolverStatus.MAX_ITERATIONS)
# eps, min_fidelity, lambda_factor, lambda_lower, lambda_upper, judge_tol, error_tol, rel_tol, abs_tol
PARAMS = [2.0 ** -52, 1e-3, 10.0, 0.0, 1e5, 1e-5, 0.0, 1e-5, 1e-5]


def _kernel_or_not(kernel: bool):
    return native.disabled() if not kernel else contextlib.nullcontext()


def hand_cases(dtype=f64):
    """Seven problems, one per branch, and what GTSAM's rules give each (written out):

    0. accepted: dl = 1 > 0, dc / dl = 0.9 > 1e-3 -> lambda 1e-3 / 10, iteration 3 -> 4, the cost
       10 -> 9.1 from a start of 10: decrease 0.9 > 1e-5 * 10, running;
    1. rejected: the cost rises (dc = -1): lambda 1e-3 * 10, not done, nothing else changes;
    2. search stopped: a rejected valid step whose |dc| = 1e-7 < 1e-5 * 10: done without a step,
       lambda kept; the decrease over the iteration (10 - 10 = 0 <= 1e-4): CONVERGED;
    3. given up: rejected at lambda 1e4 (1e4 * 10 >= 1e5): DIVERGED;
    4. accepted, 1e-3 -> 9e-4: a decrease of 1e-4, above both tolerances (1e-5 and 1e-5 *
       1e-3), but the 100th accepted iteration: MAX_ITERATIONS;
    5. accepted to a cost that decreased by 1e-6 <= abs_tol 1e-5: CONVERGED;
    6. not solved (a failed factor): rejected, lambda raised, running."""
    t = lambda *v: torch.tensor(v, dtype=dtype)  # noqa: E731
    cost = t(10.0, 10.0, 10.0, 10.0, 1e-3, 5.0, 10.0)
    model = t(1.0, 1.0, 1.0, 1.0, 1e-3, 1.0, 1.0)
    new_cost = t(9.1, 11.0, 10.0 - 1e-7, 11.0, 9e-4, 5.0 - 1e-6, 9.0)
    lin_change = t(1.0, 1.0, 1.0, 1.0, 2e-4, 2e-6, 1.0)
    solved = torch.tensor([True, True, True, True, True, True, False])
    lam = t(1e-3, 1e-3, 1e-3, 1e4, 1e-3, 1e-3, 1e-3)
    cost_start = t(10.0, 10.0, 10.0, 10.0, 1e-3, 5.0, 10.0)
    iterations = torch.tensor([3, 3, 3, 3, 99, 3, 3])
    status = torch.full((7,), RUNNING, dtype=torch.int64)
    want = dict(success=[True, False, False, False, True, True, False],
                lam=[1e-4, 1e-2, 1e-3, 1e5, 1e-4, 1e-4, 1e-2],
                iterations=[4, 3, 3, 3, 100, 4, 3],
                status=[RUNNING, RUNNING, CONVERGED, DIVERGED, MAX_IT, CONVERGED, RUNNING],
                cost_start=[9.1, 10.0, 10.0, 10.0, 9e-4, 5.0 - 1e-6, 10.0])
    return (cost, model, new_cost, lin_change, solved, lam, cost_start, iterations, status), want


@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("dtype", [f64, torch.float32])
def test_round_update_follows_gtsams_rules(kernel, dtype):
    args, want = hand_cases(dtype)
    eps = torch.finfo(dtype).eps
    with _kernel_or_not(kernel):
        success, lam, iterations, status, cost_start = update(*args, [eps, *PARAMS[1:]], [1, 100])
    assert success.tolist() == want["success"]
    assert iterations.tolist() == want["iterations"]
    assert status.tolist() == want["status"]
    tol = dict(rtol=1e-6, atol=0) if dtype is torch.float32 else dict(rtol=1e-15, atol=0)
    torch.testing.assert_close(lam, torch.tensor(want["lam"], dtype=dtype), **tol)
    # the cost at the start of the next iteration: the accepted cost where the round ended
    torch.testing.assert_close(cost_start, torch.tensor(want["cost_start"], dtype=dtype), **tol)


@pytest.mark.parametrize("kernel", [True, False])
def test_gauss_newton_takes_every_finite_solved_step(kernel):
    """Undamped: success = solved and a finite cost; otherwise DIVERGED; lambda stays 0."""
    args, _ = hand_cases()
    cost, model, new_cost, lin_change, solved, lam, cost_start, iterations, status = args
    new_cost = new_cost.clone()
    new_cost[1] = float("nan")
    with _kernel_or_not(kernel):
        success, lam, iterations, status, _ = update(cost, model, new_cost, lin_change, solved, lam,
                                                     cost_start, iterations, status, PARAMS, [0, 100])
    assert success.tolist() == [True, False, True, True, True, True, False]
    assert status[[1, 6]].tolist() == [DIVERGED, DIVERGED]
    assert torch.equal(lam, torch.zeros_like(lam))
    assert iterations.tolist() == [4, 3, 4, 4, 100, 4, 3]


def random_round(B, dtype, seed):
    """Random rounds, with every tenth step unsolved, non-finite costs, zero and negative model
    decreases, lambdas near the bounds, iterations near the limit."""
    gen = torch.Generator().manual_seed(seed)
    r = lambda: torch.rand(B, generator=gen, dtype=f64).to(dtype)  # noqa: E731
    cost = 10 * r()
    new_cost = cost * (0.5 + r())
    new_cost[::17] = float("nan")
    new_cost[3::19] = float("inf")
    lin_change = r() - 0.2
    lin_change[::13] = 0.0
    solved = torch.rand(B, generator=gen) > 0.1
    lam = 10.0 ** (10 * r() - 6)
    lam[::11] = 1e4
    cost_start = cost * (1 + r() * 1e-4)
    iterations = torch.randint(0, 12, (B,), generator=gen)
    status = torch.full((B,), RUNNING, dtype=torch.int64)
    return cost, 0.5 * cost, new_cost, lin_change, solved, lam, cost_start, iterations, status


@needs_kernel
@pytest.mark.parametrize("dtype", [f64, torch.float32])
@pytest.mark.parametrize("damped", [1, 0])
def test_round_update_kernel_equals_its_tensor_code(dtype, damped):
    """Bit for bit: the kernel rounds the parameters to the problems' dtype as torch rounds a
    Python scalar."""
    for seed in range(5):
        args = random_round(1000, dtype, seed)
        params = [torch.finfo(dtype).eps, 1e-3, 10.0, 1e-7, 1e5, 1e-5, 1e-3, 1e-5, 1e-5]
        got = update(*args, params, [damped, 10])
        with native.disabled():
            want = update(*args, params, [damped, 10])
        want2 = round_update._tensor_code(*args, params, [damped, 10])
        for a, b, c in zip(got, want, want2):
            assert a.dtype == b.dtype and torch.equal(a, b) and torch.equal(b, c)


@needs_kernel
@pytest.mark.parametrize("dtype", [f64, torch.float32])
def test_round_update_reads_strided_and_expanded_inputs_as_their_values(dtype):
    """Every input a strided view, or expanded from one element: the kernel equals the tensor
    code on the same views."""
    args = random_round(2000, dtype, seed=9)
    params = [torch.finfo(dtype).eps, 1e-3, 10.0, 1e-7, 1e5, 1e-5, 1e-3, 1e-5, 1e-5]
    strided = tuple(a[::2] for a in args)
    expanded = tuple(a[:1].expand(1000) for a in args)
    for views in (strided, expanded):
        assert not views[0].is_contiguous()
        for _ in range(3):
            got = update(*views, params, [1, 10])
            want = round_update._tensor_code(*views, params, [1, 10])
            assert all(torch.equal(a, b) for a, b in zip(got, want))


def test_round_update_checks_its_arguments():
    args, _ = hand_cases()
    with pytest.raises(ValueError, match="params must be finite numbers within the range of torch.float64, got nan"):
        update(*args, [*PARAMS[:3], float("nan"), *PARAMS[4:]], [1, 10])
    args32, _ = hand_cases(torch.float32)
    with pytest.raises(ValueError, match="within the range of torch.float32, got 1e"):
        update(*args32, [*PARAMS[:4], 1e300, *PARAMS[5:]], [1, 10])
    with pytest.raises(TypeError, match=r"solved must be a torch.bool tensor of shape \(7,\)"):
        update(*args[:4], args[4].long(), *args[5:], PARAMS, [1, 10])
    with pytest.raises(TypeError, match=r"lam must be a torch.float64 tensor of shape \(7,\)"):
        update(*args[:5], args[5][:3], *args[6:], PARAMS, [1, 10])
    with pytest.raises(TypeError, match="iterations must be a torch.int64"):
        update(*args[:7], args[7].int(), args[8], PARAMS, [1, 10])
    with pytest.raises(ValueError, match="params must have 9 entries"):
        update(*args, PARAMS[:3], [1, 10])


@pytest.mark.parametrize("kernel", [True, False])
def test_round_update_writes_no_argument_and_has_no_derivative(kernel):
    args, _ = hand_cases()
    before = [a.clone() for a in args]
    with _kernel_or_not(kernel):
        out = update(*args, PARAMS, [1, 100])
        assert all(torch.equal(a, b) for a, b in zip(args, before))
        cost = args[0].clone().requires_grad_()
        with pytest.raises(RuntimeError, match="no autograd formula"):
            update(cost, *args[1:], PARAMS, [1, 100])[4].sum().backward()
    assert all(o.data_ptr() != a.data_ptr() for o in out for a in args)


def test_round_update_opcheck():
    args, _ = hand_cases()
    opcheck(update.default, (*args, PARAMS, [1, 100]))
    args32, _ = hand_cases(torch.float32)
    opcheck(update.default, (*args32, PARAMS, [0, 100]))


# ---------------------------------------------------------------------------- damped_solve
def spd_systems(B, D, dtype, seed, scale=1.0):
    """B symmetric positive semi-definite H = J^T J (J of D - 1 rows where D > 2: singular, so
    that the damping decides), g and lam."""
    gen = torch.Generator().manual_seed(seed)
    J = torch.randn(B, max(D - 1, 1), D, generator=gen, dtype=f64) * scale
    H = J.mT @ J
    g = torch.randn(B, D, generator=gen, dtype=f64)
    lam = 10.0 ** (4 * torch.rand(B, generator=gen, dtype=f64) - 3)
    return H.to(dtype), g.to(dtype), lam.to(dtype)


def written_out(H, g, lam, diagonal):
    """delta by torch.linalg.solve of H + lam D built here, quad = delta^T H delta, in float64."""
    H, g, lam = H.double(), g.double(), lam.double()
    d = H.diagonal(dim1=-2, dim2=-1)
    D = d.clamp(1e-6, 1e32) if diagonal else torch.ones_like(d)
    A = H + torch.diag_embed(lam[:, None] * D)
    delta = torch.linalg.solve(A, -g)
    quad = torch.einsum("bi,bij,bj->b", delta, H, delta)
    return delta, quad


@pytest.mark.parametrize("kernel", [True, False])
@pytest.mark.parametrize("dtype", [f64, torch.float32])
@pytest.mark.parametrize("diagonal", [False, True])
def test_damped_solve_solves_the_damped_system(kernel, dtype, diagonal):
    """Every size the kernel takes (1 to KERNEL_MAX_SIZE, here 1-17 and the largest), batches
    that fill the lanes partly (B = 13)."""
    tol = dict(rtol=1e-9, atol=1e-9) if dtype is f64 else dict(rtol=2e-3, atol=2e-3)
    for D in [*range(1, 18), dense_solve.KERNEL_MAX_SIZE]:
        H, g, lam = spd_systems(13, D, dtype, seed=D)
        lam = lam + 0.5  # well conditioned in float32 too
        with _kernel_or_not(kernel):
            delta, solved, quad = solve(H, g, lam, diagonal)
        want_delta, want_quad = written_out(H, g, lam, diagonal)
        assert solved.all() and delta.dtype == dtype and quad.dtype == dtype
        torch.testing.assert_close(delta.double(), want_delta, **tol)
        torch.testing.assert_close(quad.double(), want_quad, **tol)


@pytest.mark.parametrize("kernel", [True, False])
def test_damped_solve_reports_failed_and_non_finite_systems(kernel):
    """An indefinite H without damping, an infinite entry, a NaN: solved False, delta 0, quad 0;
    the other systems of the batch solved as alone."""
    H, g, lam = spd_systems(9, 4, f64, seed=1)
    lam[0] = 0.0
    H[0] = -torch.eye(4, dtype=f64)
    H[1, 2, 2] = float("inf")
    H[2, 1, 0] = H[2, 0, 1] = float("nan")
    g[3, 1] = float("inf")
    with _kernel_or_not(kernel):
        delta, solved, quad = solve(H, g, lam, False)
    assert solved.tolist() == [False, False, False, False, True, True, True, True, True]
    assert torch.equal(delta[:4], torch.zeros(4, 4, dtype=f64)) and torch.equal(quad[:4], torch.zeros(4, dtype=f64))
    want_delta, want_quad = written_out(H[4:], g[4:], lam[4:], False)
    torch.testing.assert_close(delta[4:], want_delta, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(quad[4:], want_quad, rtol=1e-10, atol=1e-10)


@needs_kernel
def test_damped_solve_kernel_against_its_tensor_code_and_threads():
    H, g, lam = spd_systems(20003, 6, f64, seed=3)  # enough work for the kernel to split it
    lam = lam + 0.5  # condition numbers below ~1e2: the two factorisations agree to ~1e-13
    got = solve(H, g, lam, True)
    want = damped_solve._tensor_code(H, g, lam, True)
    assert torch.equal(got[1], want[1])
    torch.testing.assert_close(got[0], want[0], rtol=1e-11, atol=1e-11)
    torch.testing.assert_close(got[2], want[2], rtol=1e-11, atol=1e-11)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1 if threads > 1 else 2)
        again = solve(H, g, lam, True)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(got, again))


def test_damped_solve_checks_its_arguments():
    H, g, lam = spd_systems(5, 3, f64, seed=0)
    with pytest.raises(ValueError, match=r"H must have shape \(B, D, D\), got \(5, 3, 2\)"):
        solve(H[..., :2], g, lam, False)
    with pytest.raises(ValueError, match=r"g must have shape \(5, 3\) and lam \(5,\)"):
        solve(H, g[:, :2], lam, False)
    with pytest.raises(TypeError, match="share a dtype"):
        solve(H, g.float(), lam, False)


@pytest.mark.parametrize("kernel", [True, False])
def test_damped_solve_writes_no_argument_and_has_no_derivative(kernel):
    H, g, lam = spd_systems(8, 5, f64, seed=2)
    before = [t.clone() for t in (H, g, lam)]
    with _kernel_or_not(kernel):
        solve(H, g, lam, True)
        Hg = H.clone().requires_grad_()
        with pytest.raises(RuntimeError, match="no autograd formula"):
            solve(Hg, g, lam, False)[0].sum().backward()
    assert all(torch.equal(a, b) for a, b in zip(before, (H, g, lam)))


def test_damped_solve_opcheck():
    H, g, lam = spd_systems(8, 5, f64, seed=4)
    opcheck(solve.default, (H, g, lam, True))
    opcheck(solve.default, (H.float(), g.float(), lam.float(), False))
