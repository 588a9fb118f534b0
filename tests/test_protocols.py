"""Python and PyTorch protocols of the group classes, over all seven groups: components round
trips, membership checks, iteration and truth value, equality, serialisation, pytrees (torch.func
transforms taking and returning group objects) and scalar arguments."""
from __future__ import annotations

import copy
import io
import pickle

import numpy as np
import pytest
import torch

from torchsgal import ALL_GROUPS, SGal3

IDS = lambda g: g.__name__  # noqa: E731
F64 = torch.float64


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_from_components_of_functional_components_round_trip(G):
    """The class constructor takes what the functional layer's components returns: the same
    batch shape (no extra axis broadcasting in) and the same matrix."""
    M = G.random((4,), dtype=F64, generator=torch.Generator().manual_seed(1)).as_matrix()
    parts = G._f.components(M)
    g = G.from_components(*parts)
    assert g.batch_shape == (4,)
    # Sim3 stores 1/s: the round trip through s is exact up to one rounding
    torch.testing.assert_close(g.as_matrix(), M, rtol=3e-16, atol=0)
    # and under vmap, one element at a time
    logs = torch.func.vmap(lambda m: G.from_components(*G._f.components(m)).log())(M)
    assert logs.shape == (4, G.dof)


def test_sgal3_components_time_shape():
    g = SGal3.random((4, 2), dtype=F64)
    C, v, r, tau = g._f.components(g.as_matrix())
    assert tau.shape == (4, 2) and torch.equal(tau, g.time())


@pytest.mark.parametrize("dtype", [torch.float32, F64], ids=str)
def test_sim3_from_matrix_check_accepts_small_and_large_scales(dtype):
    """M[3, 3] = 1/s is a free entry: a valid element with a tiny or huge scale passes the
    check; a non-zero in the bottom row's fixed zeros, or 1/s <= 0, does not."""
    from torchsgal import Sim3
    for inv_s in (28199.158203125, 1.2345678901e13, 3.5e-9):
        M = torch.eye(4, dtype=dtype)
        M[3, 3] = inv_s
        Sim3.from_matrix(M, check=True)
    xi = 3 * torch.randn(2000, 7, dtype=dtype, generator=torch.Generator().manual_seed(0))
    xi[:, 6] *= 3  # scales from about e^-27 to e^27
    Sim3.from_matrix(Sim3.exp(xi).as_matrix(), check=True)
    M = torch.eye(4, dtype=dtype)
    M[3, 3] = 1e6
    M[3, 1] = 1e3  # 1e-3 relative to 1/s
    with pytest.raises(ValueError, match=r"not in Sim3 .* fixed rows = 0.001 \(\|M\[3, :3\]\| relative"):
        Sim3.from_matrix(M, check=True)
    M[3, 1], M[3, 3] = 0.0, -2.0
    with pytest.raises(ValueError, match=r"M\[3, 3\] = 1/s must be positive, got -2"):
        Sim3.from_matrix(M, check=True)


@pytest.mark.parametrize("dtype", [torch.float32, F64], ids=str)
def test_sim3_from_matrix_check_measures_the_bottom_row_relative_to_inverse_scale(dtype):
    """The bottom row's zeros are measured relative to M[3, 3] = 1/s.  Compared absolutely, a
    row entry far larger than a tiny 1/s would pass (composing with it would give a scale of 2e9
    instead of 1e13 in float64), and a rounding-sized entry beside a huge 1/s would fail."""
    from torchsgal import Sim3
    tiny, off = (1e-13, 5e-10) if dtype == F64 else (1e-4, 9e-5)  # both under the absolute tol
    M = torch.eye(4, dtype=dtype)
    M[3, 3], M[3, 0] = tiny, off
    with pytest.raises(ValueError, match=r"not in Sim3 .* fixed rows = [0-9.e+]+ \(\|M\[3, :3\]\| relative"):
        Sim3.from_matrix(M, check=True)
    M[3, 0] = 0.0
    g = Sim3.from_matrix(M, check=True)
    h = Sim3.from_components(torch.eye(3, dtype=dtype), torch.ones(3, dtype=dtype), torch.tensor(1.0, dtype=dtype))
    torch.testing.assert_close(g.compose(h).scale(), torch.tensor(1 / tiny, dtype=dtype), rtol=1e-6, atol=0)
    huge = 1e13 if dtype == F64 else 1e6
    M = torch.eye(4, dtype=dtype)
    M[3, 3], M[3, 0] = huge, huge * 1e-3 * (1e-9 if dtype == F64 else 1e-4)  # 1e-3 of the tol
    Sim3.from_matrix(M, check=True)  # the absolute comparison refused 1e-5 beside 1e13
    for inv_s in (0.0, float("-inf")):
        M[3, 3] = inv_s
        with pytest.raises(ValueError, match=r"not in Sim3"):
            Sim3.from_matrix(M, check=True)


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_iteration_and_truth_value(G):
    """Iteration runs over the first batch axis, as for a tensor; an unbatched element cannot
    be iterated (it raises TypeError rather than iterating to nothing) and no element has a
    truth value."""
    g = G.random((3, 2), dtype=F64)
    parts = list(g)
    assert len(parts) == 3 and all(type(p) is G and p.batch_shape == (2,) for p in parts)
    assert all(torch.equal(p.as_matrix(), g.as_matrix()[i]) for i, p in enumerate(parts))
    assert [p.batch_shape for p in G.identity(0)] == []
    one = G.identity()
    with pytest.raises(TypeError, match=rf"iteration over an unbatched {G.__name__}"):
        list(one)
    for x in (one, g, G.identity(0)):
        with pytest.raises(TypeError, match=rf"truth value of a {G.__name__} is ambiguous"):
            bool(x)
    with pytest.raises(TypeError, match=r"truth value"):
        if one:
            pass


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_equality_is_identity_and_allclose_compares_values(G):
    g = G.random((4,), dtype=F64, generator=torch.Generator().manual_seed(2))
    c = g.clone()
    assert g == g and g != c and not (g == c)  # identity, documented
    assert {g: 1}[g] == 1 and c not in {g: 1}
    assert g.allclose(c) and c.allclose(g)
    assert g[:1].allclose(G.identity(3, dtype=F64)) is False
    assert g[1:2].allclose(G.stack([g[1]] * 3))  # broadcasts like torch.allclose
    nudged = G(g.as_matrix() + 1e-7)
    assert not g.allclose(nudged, rtol=0, atol=1e-8) and g.allclose(nudged, rtol=0, atol=1e-6)
    assert isinstance(g.allclose(c), bool)
    with pytest.raises(TypeError, match=rf"other must be a {G.__name__}, got Tensor"):
        g.allclose(g.as_matrix())
    with pytest.raises(TypeError, match=r"other has dtype torch.float32 but self has dtype torch.float64"):
        g.allclose(g.float())
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: self \(4,\), other \(3,\)"):
        g.allclose(g[:3])
    with pytest.raises(ValueError, match=r"rtol must be a finite number >= 0, got -1"):
        g.allclose(c, rtol=-1)
    with pytest.raises(TypeError, match=r"atol must be a finite number >= 0, got None"):
        g.allclose(c, atol=None)


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_pickle_deepcopy_and_torch_save_round_trip(G):
    """torch.save then torch.load with its default (weights_only=True since torch 2.6) does not
    raise UnpicklingError; loading rebuilds the element through its constructor."""
    g = G.random((2, 3), dtype=F64)
    buf = io.BytesIO()
    torch.save({"pose": g, "list": [g[0], g.float()]}, buf)
    buf.seek(0)
    out = torch.load(buf)
    for got, want in ((out["pose"], g), (out["list"][0], g[0]), (out["list"][1], g.float())):
        assert type(got) is G and got.dtype == want.dtype
        assert torch.equal(got.as_matrix(), want.as_matrix())
    buf.seek(0)
    assert torch.equal(torch.load(buf, weights_only=True)["pose"].as_matrix(), g.as_matrix())
    for h in (pickle.loads(pickle.dumps(g)), copy.deepcopy(g)):
        assert type(h) is G and torch.equal(h.as_matrix(), g.as_matrix())
        assert h.as_matrix().data_ptr() != g.as_matrix().data_ptr()
    # loading goes through the constructor's checks
    func, args = g.__reduce__()
    with pytest.raises(ValueError, match=r"matrix must have shape"):
        func(args[0][..., :-1])


class _Tagged(SGal3):
    """A user subclass with instance attributes."""


class _NeedsArgument(SGal3):
    """A user subclass whose constructor takes a required extra argument."""

    def __init__(self, matrix, extra):
        super().__init__(matrix)
        self.extra = extra


class _Slotted(SGal3):
    __slots__ = ("tag",)


def test_subclass_attributes_survive_pickle_deepcopy_torch_save_and_vmap():
    """A subclass's attributes survive pickling (as cls(matrix) they would be dropped:
    deepcopy(s).tag would raise AttributeError), a subclass whose __init__ takes another argument
    is rebuilt, and the pytree unflatten keeps them too (vmap(lambda x: x.tag)).  The built-in
    classes pickle as cls(matrix), which torch.load's weights_only=True reads."""
    from torch.func import vmap

    M = SGal3.random(3, dtype=F64, generator=torch.Generator().manual_seed(8)).as_matrix()
    tagged = _Tagged(M)
    tagged.tag = {"name": "x", "weights": torch.arange(3.0)}
    slotted = _Slotted(M)
    slotted.tag = "y"
    cases = [(tagged, "tag"), (_NeedsArgument(M, 7), "extra"), (slotted, "tag")]
    for g, attr in cases:
        want = getattr(g, attr)
        copies = [pickle.loads(pickle.dumps(g)), copy.deepcopy(g)]
        buf = io.BytesIO()
        torch.save([g], buf)
        buf.seek(0)
        copies.append(torch.load(buf, weights_only=False)[0])
        buf.seek(0)
        with pytest.raises(pickle.UnpicklingError):  # a user class must be allowlisted
            torch.load(buf, weights_only=True)
        for h in copies:
            assert type(h) is type(g) and torch.equal(h.as_matrix(), M)
            assert h.as_matrix().data_ptr() != M.data_ptr()
            if attr == "tag" and isinstance(want, dict):
                assert h.tag["name"] == "x" and torch.equal(h.tag["weights"], want["weights"])
                assert h.tag is not want  # a copy, not shared
            else:
                assert getattr(h, attr) == want
        seen = []
        out = vmap(lambda a: (seen.append(getattr(a, attr)), a)[1])(g)
        assert len(seen) == 1 and seen[0] is want
        assert type(out) is type(g) and getattr(out, attr) is want and torch.equal(out.as_matrix(), M)
    # allowlisted, a subclass loads with the default weights_only=True (through _rebuild)
    with torch.serialization.safe_globals([_Slotted]):
        buf = io.BytesIO()
        torch.save(slotted, buf)
        buf.seek(0)
        assert torch.load(buf, weights_only=True).tag == "y"
    # the built-in classes: cls(matrix), no state; _rebuild checks what it is given
    assert SGal3(M).__reduce__() == (SGal3, (M,))
    from torchsgal.groups.base import _rebuild
    with pytest.raises(ValueError, match=r"matrix must have shape \(\.\.\., 5, 5\), got \(3, 4, 4\)"):
        _rebuild(_Tagged, M[..., :4, :4], None)
    with pytest.raises(TypeError, match=r"cls must be a LieGroup subclass"):
        _rebuild(torch.Tensor, M, None)
    with pytest.raises(TypeError, match=r"state must be None or a dict of attributes other than _matrix"):
        _rebuild(_Tagged, M, {"_matrix": "x"})


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_torch_func_takes_and_returns_group_objects(G):
    """Group classes are pytree nodes (one leaf, the matrix): vmap maps over and returns group
    objects (without refusing them: "must only return Tensors", "cannot vmap over non-Tensor
    arguments"), and derivatives with respect to a group argument come back in its structure."""
    from torch.func import grad, jacrev, vmap
    from torch.utils import _pytree as pytree

    xi = 0.5 * torch.randn(8, G.dof, dtype=F64, generator=torch.Generator().manual_seed(4))
    g = vmap(G.exp)(xi)  # returns a group object
    assert type(g) is G and g.batch_shape == (8,)
    # equal to rounding: under vmap the tensor code runs, eagerly SGal3's C kernels (native.py)
    torch.testing.assert_close(g.as_matrix(), G.exp(xi).as_matrix(), rtol=0, atol=1e-15)
    # takes group objects, mapping over their first batch axis, with None for a shared one
    h = G.exp(xi.flip(0))
    torch.testing.assert_close(vmap(lambda a, b: a.rminus(b))(g, h), g.rminus(h), rtol=0, atol=1e-13)
    out = vmap(lambda a, b: a.compose(b), in_dims=(0, None))(g, h[0])
    assert type(out) is G and torch.equal(out.as_matrix(), g.compose(h[0]).as_matrix())
    nested = vmap(vmap(lambda a: a.inverse()))(G.exp(xi.reshape(2, 4, G.dof)))
    assert type(nested) is G and nested.batch_shape == (2, 4)
    # reverse mode: a function returning a group (its Jacobian is matrix-shaped), and the
    # gradient with respect to a group argument (the Euclidean gradient of its matrix)
    J = jacrev(lambda x: G.exp(x))(xi[0])
    Jm = jacrev(lambda x: G.exp(x).as_matrix())(xi[0])
    assert type(J) is G and torch.equal(J.as_matrix(), Jm)
    gr = grad(lambda a: a.log().square().sum())(g[0])
    grm = grad(lambda m: G(m).log().square().sum())(g[0].as_matrix())
    assert type(gr) is G and torch.equal(gr.as_matrix(), grm)
    leaves, spec = pytree.tree_flatten({"g": g, "x": xi})
    assert len(leaves) == 2 and type(pytree.tree_unflatten(leaves, spec)["g"]) is G


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_torch_func_derivative_wrappers_and_vmap_axes(G):
    """Derivatives of group-valued functions with respect to a group are nested wrappers, read
    with as_matrix().as_matrix() (their repr must not raise AttributeError: no attribute 'shape'); a
    wrapper whose leaf is not a tensor of trailing shape (n, n) reprs as such, and its
    batch_shape raises TypeError (not (4,) for a (4, 4, 6) Jacobian).  vmap's in_dims count
    the matrix tensor's axes: -3 is the last batch axis."""
    from torch.func import hessian, jacrev, vmap

    n = G.matrix_dim
    gen = torch.Generator().manual_seed(9)
    g, h = G.random((), dtype=F64, generator=gen), G.random((), dtype=F64, generator=gen)
    J = jacrev(lambda a: a.compose(h))(g)
    want = jacrev(lambda m: G(m).compose(h).as_matrix())(g.as_matrix())
    assert type(J) is G and type(J.as_matrix()) is G and torch.equal(J.as_matrix().as_matrix(), want)
    assert repr(J).startswith(f"{G.__name__}(<pytree leaf: {G.__name__}(")
    with pytest.raises(TypeError, match=rf"this {G.__name__} wraps <pytree leaf: .*not matrices \(\.\.\., {n}, {n}\).*as_matrix\(\)"):
        J.batch_shape
    p = torch.ones(G.point_dim, dtype=F64)
    H = hessian(lambda a: a.act(p).sum())(g)
    want = hessian(lambda m: G(m).act(p).sum())(g.as_matrix())
    assert type(H.as_matrix()) is G and torch.equal(H.as_matrix().as_matrix(), want)
    assert want.shape == (n, n, n, n) and repr(H).startswith(f"{G.__name__}(<pytree leaf: ")
    xi = torch.zeros(G.dof, dtype=F64)
    Jx = jacrev(G.exp)(xi)
    assert Jx.as_matrix().shape == (n, n, G.dof)
    if G.dof != n:  # else the Jacobian is indistinguishable from a batch of n matrices
        assert repr(Jx) == f"{G.__name__}(<pytree leaf of shape ({n}, {n}, {G.dof}), dtype=torch.float64, device=cpu>)"
        with pytest.raises(TypeError, match=rf"wraps <pytree leaf of shape \({n}, {n}, {G.dof}\)"):
            Jx.batch_shape
    # in_dims / out_dims index the matrix tensor: -3 is the last batch axis, never -1
    gb = G.random((3, 7), dtype=F64, generator=gen)
    torch.testing.assert_close(vmap(lambda a: a.log(), in_dims=-3)(gb), gb.log().transpose(0, 1), rtol=0, atol=0)
    torch.testing.assert_close(vmap(lambda a: a.log(), in_dims=1)(gb), gb.log().transpose(0, 1), rtol=0, atol=0)
    out = vmap(lambda a: a.inverse(), out_dims=1)(gb)
    assert out.batch_shape == (7, 3) and torch.equal(out.as_matrix(), gb.inverse().as_matrix().transpose(0, 1))
    bad = vmap(lambda a: a.inverse(), out_dims=1)(gb[0])  # the mapped axis among the matrix axes
    assert bad.as_matrix().shape == (n, 7, n)
    assert repr(bad).startswith(f"{G.__name__}(<pytree leaf of shape ({n}, 7, {n})")
    # a normal element's repr is unchanged
    assert repr(gb) == f"{G.__name__}(batch_shape=(3, 7), dtype=torch.float64, device=cpu)"


def test_torch_compile_takes_and_returns_group_objects():
    """The pytree registration keeps torch.compile(fullgraph=True) of functions taking and
    returning group objects in one graph (backend="eager": dynamo's tracing is under test)."""
    G = SGal3
    g, h = G.random(5, dtype=F64), G.random(5, dtype=F64)
    f = torch.compile(lambda a, b: a.between(b), fullgraph=True, backend="eager")
    out = f(g, h)
    assert type(out) is G and torch.equal(out.as_matrix(), g.between(h).as_matrix())


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_scalar_arguments(G):
    """interpolate's alpha: any real number (numpy's float32 as well as float64),
    not a bool; from_matrix's check: a bool (check="no" raises rather than running the check)."""
    g = G.random(3, dtype=F64, generator=torch.Generator().manual_seed(5))
    h = G.random(3, dtype=F64, generator=torch.Generator().manual_seed(6))
    want = g.interpolate(h, 0.5).as_matrix()
    for alpha in (np.float32(0.5), np.float64(0.5), 0.5):
        torch.testing.assert_close(g.interpolate(h, alpha).as_matrix(), want, rtol=0, atol=1e-15)
    assert torch.equal(g.interpolate(h, np.int64(1)).as_matrix(), g.interpolate(h, 1).as_matrix())
    for bad in (True, "0.5", None):
        with pytest.raises(TypeError, match=rf"alpha must be a number or a torch.Tensor, got {type(bad).__name__}"):
            g.interpolate(h, bad)
    M = g.as_matrix().clone()
    M[0, 0, 0] += 0.1  # not in the group
    G.from_matrix(M, check=False)
    with pytest.raises(ValueError, match=rf"not in {G.__name__}"):
        G.from_matrix(M, check=True)
    for bad in ("no", 0, None, torch.tensor(False), np.int64(1)):
        with pytest.raises(TypeError, match=r"check must be True or False, got"):
            G.from_matrix(M, check=bad)


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_numpy_bools_and_huge_integers(G):
    """A numpy bool is a flag, as numpy scalars are numbers for tol, rtol and alpha (not
    refused); an integer beyond the float range is a bad value (ValueError naming the argument,
    not math.isfinite's OverflowError)."""
    M = G.random(2, dtype=F64, generator=torch.Generator().manual_seed(7)).as_matrix().clone()
    assert torch.equal(G.from_matrix(M, check=np.bool_(True)).as_matrix(), M)
    M[0, 0, 0] += 0.1
    with pytest.raises(ValueError, match=rf"not in {G.__name__}"):
        G.from_matrix(M, check=np.bool_(True))
    G.from_matrix(M, check=np.bool_(False))
    for name in ("rtol", "atol"):
        with pytest.raises(ValueError, match=rf"{name} must be a finite number >= 0, got 1000000000"):
            G.identity().allclose(G.identity(), **{name: 10**400})
    with pytest.raises(ValueError, match=r"tol must be a finite number > 0, got 1000000000"):
        G.from_matrix(M, check=True, tol=10**400)


def test_from_transform3d_check_flag():
    from torchsgal.kinematics import pk_interop
    M = torch.eye(4, dtype=F64).expand(2, 4, 4)
    assert pk_interop.from_transform3d(M, check=True).batch_shape == (2,)
    with pytest.raises(TypeError, match=r"check must be True or False, got 'no'"):
        pk_interop.from_transform3d(M, check="no")


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_interpolate_refuses_a_non_finite_number(G):
    """A Python or numpy alpha of nan or inf raises ValueError (it would give a NaN element
    silently); a number is read (no host sync), a tensor alpha stays checked by metadata only."""
    g, h = G.identity(2, dtype=F64), G.random(2, dtype=F64, generator=torch.Generator().manual_seed(10))
    for bad in (float("nan"), float("inf"), -np.inf, np.float32("nan"), 10**400):
        with pytest.raises(ValueError, match=r"alpha must be a finite number, got"):
            g.interpolate(h, bad)
    torch.testing.assert_close(g.interpolate(h, np.float64(1.0)).as_matrix(), h.as_matrix(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_stack_and_cat_refuse_one_element_for_the_sequence(G):
    """G.cat(g) and G.stack(g) raise TypeError: cat would iterate g's first batch axis (batch
    (3, 2) would become (6,)) and stack would return a copy, silently."""
    g = G.identity((3, 2), dtype=F64)
    for op in ("stack", "cat"):
        with pytest.raises(TypeError, match=rf"{G.__name__}\.{op}: elements must be a sequence of elements "
                                            rf"\(a list or tuple\), got one {G.__name__}"):
            getattr(G, op)(g)
    assert G.cat([g]).batch_shape == (3, 2) and G.stack((g, g)).batch_shape == (2, 3, 2)
    assert G.stack(list(g)).batch_shape == (3, 2)


@pytest.mark.parametrize("G", ALL_GROUPS, ids=IDS)
def test_allclose_equal_nan_and_subclasses_in_either_order(G):
    """allclose takes equal_nan as torch.allclose does; the binary operations take a subclass
    element in either order (sub.allclose(g) agrees with g.allclose(sub), not a TypeError,
    and so for compose), and still refuse another group."""
    Sub = type("Sub", (G,), {})
    g = G.random(3, dtype=F64, generator=torch.Generator().manual_seed(11))
    sub = Sub(g.as_matrix().clone())
    assert g.allclose(sub) and sub.allclose(g)
    assert type(sub.compose(g)) is Sub and type(g.compose(sub)) is G
    torch.testing.assert_close(sub.compose(g).as_matrix(), g.compose(g).as_matrix(), rtol=0, atol=0)
    torch.testing.assert_close(sub.rminus(g), g.rminus(sub), rtol=0, atol=1e-12)
    assert type(Sub.stack([g, sub])) is Sub and type(G.cat([sub, g])) is G
    other = next(H for H in ALL_GROUPS if H is not G)
    with pytest.raises(TypeError, match=rf"other must be a {G.__name__}, got {other.__name__}"):
        sub.allclose(other.identity(dtype=F64))
    with pytest.raises(TypeError, match=rf"Sub.stack: elements\[1\] must be a {G.__name__}, got {other.__name__}"):
        Sub.stack([g, other.identity(3, dtype=F64)])
    M = g.as_matrix().clone()
    M[1, 0, 0] = float("nan")
    n = G(M)
    assert not n.allclose(n) and n.allclose(n, equal_nan=True) and n.allclose(G(M.clone()), equal_nan=np.bool_(True))
    assert not n.allclose(g, equal_nan=True)
    with pytest.raises(TypeError, match=r"equal_nan must be True or False, got 1"):
        n.allclose(n, equal_nan=1)


def test_torch_load_checks_shape_and_dtype_not_membership():
    """As documented: loading runs the constructor's checks only; membership is the caller's
    from_matrix(check=True)."""
    from torchsgal import SE3
    buf = io.BytesIO()
    torch.save(SE3(torch.ones(4, 4, dtype=F64)), buf)
    buf.seek(0)
    g = torch.load(buf, weights_only=True)
    assert type(g) is SE3 and torch.equal(g.as_matrix(), torch.ones(4, 4, dtype=F64))
    with pytest.raises(ValueError, match=r"not in SE3"):
        SE3.from_matrix(g.as_matrix(), check=True)


def test_subclass_with_required_init_argument_goes_through_operations():
    """Every operation of a subclass whose __init__ takes another argument, its classmethod
    constructors, and the solvers and regression given such elements build their results
    without calling __init__, after the same shape and dtype checks (building them as
    type(self)(matrix) would raise TypeError: missing 'extra')."""
    from torchsgal.estimation import gauss_newton
    from torchsgal.regression import fit_polynomial

    gen = torch.Generator().manual_seed(12)
    g = _NeedsArgument(SGal3.random(4, dtype=F64, generator=gen).as_matrix(), 1)
    h = _NeedsArgument(SGal3.random(4, dtype=F64, generator=gen).as_matrix(), 2)
    plain_g, plain_h = SGal3(g.as_matrix()), SGal3(h.as_matrix())
    xi = torch.randn(4, 10, dtype=F64, generator=gen) * 0.3
    results = {
        "compose": (g @ h, plain_g @ plain_h), "inverse": (g.inverse(), plain_g.inverse()),
        "rplus": (g.rplus(xi), plain_g.rplus(xi)), "lplus": (g.lplus(xi), plain_g.lplus(xi)),
        "interpolate": (g.interpolate(h, 0.3), plain_g.interpolate(plain_h, 0.3)),
        "index": (g[1:3], plain_g[1:3]), "reshape": (g.reshape(2, 2), plain_g.reshape(2, 2)),
        "to": (g.to(torch.float32), plain_g.to(torch.float32)), "clone": (g.clone(), plain_g.clone()),
        "exp": (_NeedsArgument.exp(xi), SGal3.exp(xi)),
        "identity": (_NeedsArgument.identity(3, dtype=F64), SGal3.identity(3, dtype=F64)),
        "from_matrix": (_NeedsArgument.from_matrix(h.as_matrix(), check=True), plain_h),
        "stack": (_NeedsArgument.stack([g, h]), SGal3.stack([plain_g, plain_h])),
    }
    for name, (got, want) in results.items():
        assert type(got) is _NeedsArgument, name
        assert not hasattr(got, "extra"), name  # operations return elements without attributes
        torch.testing.assert_close(got.as_matrix(), want.as_matrix(), rtol=0, atol=0, msg=name)
    with pytest.raises(ValueError, match=r"matrix must have shape \(\.\.\., 5, 5\), got \(4, 4\)"):
        _NeedsArgument.from_matrix(torch.eye(4, dtype=F64))

    # the solvers and regression rebuild the caller's class through from_matrix
    target = plain_h
    sol = gauss_newton(lambda x: x.rminus(target), g, max_iterations=20)
    assert type(sol.x) is _NeedsArgument
    torch.testing.assert_close(sol.x.as_matrix(), target.as_matrix(), rtol=0, atol=1e-10)
    t = torch.linspace(0.0, 1.0, 5, dtype=F64)
    truth = SGal3.exp(t[:, None] * xi[0] * 0.5)
    fit = fit_polynomial(_NeedsArgument(truth.as_matrix(), 0), t, degree=1)
    torch.testing.assert_close(fit(t).as_matrix(), truth.as_matrix(), rtol=0, atol=1e-9)


def test_allclose_on_meta_says_why_it_cannot():
    """allclose on 'meta' elements says why it cannot read them; torch's 'Tensor.item() cannot
    be called on meta tensors' would not say which call or why."""
    from torchsgal import SE3
    g = SE3.identity(2, dtype=F64, device="meta")
    with pytest.raises(RuntimeError, match=r"allclose reads the matrices' values .* device 'meta' have none"):
        g.allclose(g)
