"""Thin group classes over the functional layer.

A group element wraps one tensor, its homogeneous matrix (..., n, n).  It is not a Tensor
subclass, so torch.func and torch.compile see plain tensors.  Every method calls the
group's functional module (``_f``), the one place its maths lives.
"""
from __future__ import annotations

import copyreg
from collections.abc import Sequence
from numbers import Real
from typing import Any, ClassVar

import torch
from typing_extensions import Self

from .. import _compat
from ..functional import blocks, checks
from ..functional._blocking import values_readable
from .batch import MatrixBatch

REPR_ELEMENTS = 4  # repr shows the matrices of batches up to this size


class _AbstractModule:
    """``LieGroup._f``: the base class has no group; any use says so."""

    def __getattr__(self, name: str) -> Any:
        raise TypeError(_ABSTRACT)


_ABSTRACT = "LieGroup is the abstract base class: use SO2, SE2, SO3, SE3, SE23, SGal3 or Sim3"


class LieGroup(MatrixBatch):
    """Base of the group classes (SO2, SE2, SO3, SE3, SE23, SGal3, Sim3); subclasses set
    ``dof``, ``matrix_dim`` and ``_f``.

    ``==``, ``!=`` and ``hash`` are Python's identity comparison (``g == g.clone()`` is False),
    so that elements can be dictionary keys; compare values with ``g.allclose(h)`` or on the
    matrices (``torch.equal(g.as_matrix(), h.as_matrix())``).

    The binary operations (compose, between, rminus, lminus, interpolate, allclose) and
    stack/cat take elements of one group: instances of its class or of subclasses of it, in
    either order (a subclass of SE3 composes with an SE3 and an SE3 with it); the result has
    the class of ``self`` (of ``cls`` for stack/cat).

    Each class is a pytree node whose one leaf is the matrix (..., n, n), so torch.func
    transforms (vmap, grad, jacrev, jacfwd, hessian) take and return group objects.

    - vmap's ``in_dims`` and ``out_dims`` count the axes of that matrix tensor, batch axes first
      and the two matrix axes last: for batch shape (B1, B2), 0 or -4 maps over B1 and 1 or -3
      over B2 (-3 is always the last batch axis); -1 and -2 map over the matrix's columns or
      rows and give nonsense.  An ``out_dims`` must leave the matrix axes last (0 up to the
      number of batch axes of one result); otherwise the wrapped tensor is not a batch of
      matrices, which nothing can detect when the sizes coincide (a batch of 4 SE3).
    - A derivative comes back in torch.func's pytree structure: the class of a group argument
      wraps the derivative with respect to its matrix, the class of a group-valued output wraps
      the derivative of its matrix, and both nest when both are groups.  The leaf is a
      Euclidean derivative, never a group element.  With M the argument's matrix:

      * ``grad(f)(g)``, f scalar-valued: ``G(dF/dM)``, of M's shape;
      * ``jacrev(f)(g)`` (or jacfwd), f tensor-valued: ``G(J)``, J of shape
        ``f(g).shape + M.shape``;
      * ``jacrev(f)(x)``, x a tensor, f group-valued: ``G(J)``, J of shape ``(*shape of f(x)'s
        matrix, *x.shape)``, e.g. (4, 4, 6) for ``SE3.exp`` of a (6,) vector;
      * ``jacrev(f)(g)``, f group-valued: nested, the output's class around the input's,
        ``G_out(G_in(J))``, J of shape ``(*shape of f(g)'s matrix, *M.shape)``; read it with
        ``J.as_matrix().as_matrix()``;
      * ``hessian(f)(g)``, f scalar-valued: nested, ``G(G(H))``, H of shape ``M.shape + M.shape``.

      ``as_matrix()`` returns the leaf.  The repr of a wrapper whose leaf is not a tensor of
      trailing shape (n, n) says so (``SE3(<pytree leaf: SE3(...)>)``, ``SE3(<pytree leaf of
      shape (4, 4, 6), ...>)``) and its ``batch_shape`` raises TypeError; a derivative of
      matrix shape (from grad, or where the sizes coincide) looks like an element, and the
      group methods compute meaningless values from it.

    Acting on points: ``g.act(x, point_axes=k)`` (and ``act_direction``, ``act_velocity``) for g
    of batch shape S and x of shape (*T, d):

    - k = 0 (the default): S and T broadcast as torch's elementwise ops (aligned on the right);
      g (B,) with x (B, d) maps each point by its own element, x (N, B, d) gives (N, B, d).
    - k > 0: the last k axes of x before the coordinates are sets of points that every element
      maps whole: x (*T', N1, ..., Nk, d), S and T' broadcast, and the result is
      (*broadcast(S, T'), N1, ..., Nk, d).  With k = 1, g (B,) maps x (B, N, d) (a set per
      element) or x (N, d) (one set for all) to (B, N, d).  The same as
      ``g.reshape(*S, 1, ..., 1).act(x)`` (k ones).

    k is never guessed from the shapes: under k = 0, g (B,) with x (B, B, d) already means
    ``out[i, j] = g[j] x[i, j]``.

    Elements pickle, deepcopy and ``torch.save`` as ``cls(matrix)``; ``torch.load`` reads the
    seven classes with its default ``weights_only=True`` (they are registered as safe globals).
    Loading runs only the constructor's checks, the matrix's shape and dtype, not membership:
    a saved matrix that is not in the group (an "SE3" of ``torch.ones(4, 4)``) loads as it is;
    check what you load with ``G.from_matrix(g.as_matrix(), check=True)``.
    Indexing gives views, as for tensors: ``torch.save(g[0])`` writes the storage of the whole
    batch; save ``g[0].clone()`` to write one element.
    The attributes of a subclass's instances (its ``__dict__`` and extra ``__slots__``) travel
    with them through pickle, deepcopy and torch.save, and as the pytree context (torch.func
    transforms keep them on the elements they pass through; the group operations and the
    constructors return new elements of the subclass without them, and without calling its
    ``__init__``, which may take other arguments).  Such an element, or one of a subclass that defines its own
    ``__init__``, is rebuilt by ``_rebuild``: the constructor's shape and dtype checks, then the
    attributes, without calling ``__init__`` (as pickle does for other objects).  torch.load
    reads it with ``weights_only=False``, or with the default after
    ``torch.serialization.add_safe_globals([YourSubclass])``.
    """

    dof: int
    matrix_dim: int
    point_dim: int  # size of the points (events for SGal3) that act() takes
    rotation_dim: int = 3  # 2 for the planar groups
    _f: Any = _AbstractModule()  # functional module of the group (set by each group)
    _fixed_note = ""  # how _fixed_deviation measures, for the membership error
    # set by __init_subclass__ (see there)
    _group: ClassVar[type[LieGroup]]
    _state_slots: ClassVar[tuple[str, ...]]
    _has_state: ClassVar[bool]

    __slots__ = ("_matrix",)

    def __init__(self, matrix: torch.Tensor) -> None:
        """Wraps a group matrix, checking its shape and dtype but not that it is in the group:
        ``from_matrix(M, check=True)`` checks that too (``check=False`` is its default, for
        matrices known to be in the group)."""
        type(self)._concrete()
        checks.matrix(matrix, self.matrix_dim, "matrix")
        self._matrix = matrix

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # the group: the nearest class that sets _f (SE3 for a user subclass of SE3); binary
        # operations and stack/cat take any instance of it, so they are symmetric in subclasses
        cls._group = cls if "_f" in cls.__dict__ else getattr(cls, "_group", cls)
        # a subclass's instance attributes besides the matrix: its __dict__ (if its instances
        # have one) and slots; the seven built-in classes have neither (__slots__ = ())
        slots = copyreg._slotnames(cls)  # type: ignore[attr-defined]  # pickle's own slot list
        cls._state_slots = tuple(n for n in slots if n != "_matrix")
        cls._has_state = bool(cls._state_slots) or bool(cls.__dictoffset__)
        _register_pytree(cls)

    def _state(self) -> dict | None:
        """The instance's attributes besides the matrix (a subclass's), or None if it has none:
        what pickle, deepcopy and the pytree context carry."""
        if not self._has_state:
            return None
        state = dict(getattr(self, "__dict__", ()))
        for name in self._state_slots:
            if hasattr(self, name):
                state[name] = getattr(self, name)
        return state or None

    @classmethod
    def _concrete(cls) -> None:
        """TypeError for the abstract base class (and its subclasses that name no group)."""
        if cls._group is LieGroup:
            raise TypeError(_ABSTRACT)

    @classmethod
    def _new(cls, matrix: torch.Tensor) -> Self:
        """How every operation and constructor builds its result: the constructor's shape and
        dtype checks, then an element of ``cls`` without calling ``__init__``, so that a
        subclass whose ``__init__`` takes other arguments still composes, inverts, indexes..."""
        cls._concrete()
        checks.matrix(matrix, cls.matrix_dim, "matrix")
        g = object.__new__(cls)
        g._matrix = matrix
        return g

    @classmethod
    def _from_leaf(cls, leaf: Any, state: dict | None = None) -> Self:
        """The pytree unflatten: wraps ``leaf`` unchecked, since torch.func and torch's pytree
        utilities rebuild the structure around whatever leaves they computed (Jacobians of other shapes,
        in_dims, sizes), then sets the attributes ``state`` (the context) without calling
        ``__init__``."""
        g = object.__new__(cls)
        g._matrix = leaf
        if state:
            for name, value in state.items():
                object.__setattr__(g, name, value)
        return g

    # ---------------------------------------------------------------- constructors
    @classmethod
    def exp(cls, xi: torch.Tensor) -> Self:
        """exp(xi^) for tangent vectors (..., dof); differentiable w.r.t. xi (custom backward)."""
        return cls._new(cls._f.exp(xi))

    @classmethod
    def from_matrix(cls, matrix: torch.Tensor, check: bool = False, tol: float | None = None) -> Self:
        """From homogeneous matrices (..., n, n).  With ``check=True`` raises ValueError if any
        matrix is not in the group (orthonormal rotation with det +1, fixed rows), within
        ``tol`` (None or a finite number > 0; default 1e-4 for float32, 1e-9 for float64).
        Checking reads the values (one host sync), so, as everywhere in the library, it is
        skipped where they cannot be read: on 'meta', inside a torch.func transform (vmap, grad,
        jacrev) and while torch.compile traces; shape and dtype are always checked."""
        cls._concrete()
        checks.matrix(matrix, cls.matrix_dim, "matrix")
        check = checks.boolean(check, "check")
        tol = _tol_arg(tol)
        if check and matrix.numel() and values_readable(matrix):
            cls._check_membership(matrix, tol)
        return cls._new(matrix)

    @classmethod
    def _check_membership(cls, M: torch.Tensor, tol: float | None) -> None:
        if tol is None:
            tol = 1e-4 if M.dtype == torch.float32 else 1e-9
        k = cls.rotation_dim
        C = M[..., :k, :k]
        eye = blocks.eye(k, M)
        orth = (C.transpose(-1, -2) @ C - eye).abs().amax(dim=(-1, -2))
        det = (torch.linalg.det(C) - 1).abs()
        rows = cls._fixed_deviation(M)
        finite = torch.isfinite(M).all().to(M.dtype)
        # every measure in one read (the check's one host sync)
        finite, o, d, r, *extra = torch.stack(
            (finite, orth.max(), det.max(), rows.max(), *cls._extra_measures(M))).tolist()
        if not finite:
            raise ValueError(f"matrix is not in {cls.__name__}: it has non-finite entries")
        if max(o, d, r) > tol:
            fixed = (f", max deviation of the fixed rows = {r:.3g}{cls._fixed_note}"
                     if cls.matrix_dim > cls.rotation_dim else "")  # SO2, SO3: no fixed rows
            raise ValueError(
                f"matrix is not in {cls.__name__} (tol {tol:g}): max |C^T C - I| = {o:.3g}, "
                f"max |det C - 1| = {d:.3g}{fixed}"
            )
        cls._check_extra_measures(extra)

    @classmethod
    def _extra_measures(cls, M: torch.Tensor) -> tuple:
        """Scalars besides orthonormality, det and the fixed rows that a group's membership
        check reads (in the same host sync); see Sim3."""
        return ()

    @classmethod
    def _check_extra_measures(cls, values: list) -> None:
        """Raises ValueError if the values of ``_extra_measures`` (Python floats) are out of the group."""

    @classmethod
    def _fixed_deviation(cls, M: torch.Tensor) -> torch.Tensor:
        """The largest deviation (...) of the fixed entries of M from their values: the matrix
        rebuilt from its free entries, compared with M."""
        rebuilt = cls._f.from_components(*cls._f.components(M))
        return (M - rebuilt).abs().amax(dim=(-1, -2))

    @classmethod
    def identity(cls, batch_shape: Sequence[int] | int = (), dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None) -> Self:
        """The identity element, repeated over ``batch_shape`` (an int n means (n,); default
        dtype: torch's default)."""
        cls._concrete()
        batch_shape = checks.shape(batch_shape, "batch_shape")
        dtype = checks.dtype_arg(dtype or torch.get_default_dtype())
        eye = torch.eye(cls.matrix_dim, dtype=dtype, device=device)
        return cls._new(eye.expand(*batch_shape, cls.matrix_dim, cls.matrix_dim).clone())

    @classmethod
    def random(cls, batch_shape: Sequence[int] | int = (), dtype: torch.dtype | None = None,
               device: torch.device | str | None = None,
               generator: torch.Generator | None = None) -> Self:
        """Uniform rotations; translations, velocities, times and Sim3's log-scale standard normal.
        ``batch_shape`` as in ``identity``; ``generator`` None or a torch.Generator."""
        batch_shape = checks.shape(batch_shape, "batch_shape")
        dtype = checks.dtype_arg(dtype or torch.get_default_dtype())
        if generator is not None and not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be None or a torch.Generator, got {type(generator).__name__}")
        return cls._new(cls._f.random(batch_shape, dtype, device, generator))

    # ------------------------------------------------------------------ the matrix
    def as_matrix(self) -> torch.Tensor:
        """The homogeneous matrices (..., matrix_dim, matrix_dim) (the wrapped tensor, not a copy)."""
        return self._matrix

    def rotation(self) -> torch.Tensor:
        """Rotation matrix C (..., 3, 3) (2 x 2 for the planar groups) (a view of the matrix)."""
        k = self.rotation_dim
        return self._matrix[..., :k, :k]

    # ------------------------------------------------------------------ operations
    def _same_type(self, other: LieGroup, name: str) -> LieGroup:
        """other: an element of the same group (an instance of its class or of a subclass, in
        either order), dtype and device, with a broadcasting batch."""
        if not isinstance(other, self._group):
            raise TypeError(f"{name} must be a {self._group.__name__}, got {type(other).__name__}")
        checks.binary(self._matrix, 2, other._matrix, 2, "self", name)
        return other

    def log(self) -> torch.Tensor:
        """Principal logarithm (..., dof), rotation angle in [0, pi] (custom backward)."""
        return self._f.log(self._matrix)

    def compose(self, other: LieGroup) -> Self:
        """g h, the same as ``g @ h``.  Inside torch.compile(fullgraph=True) write
        ``g.compose(h)``: dynamo (torch 2.13) traces ``+`` and ``*`` of objects that are
        not tensors through their ``__add__``/``__mul__``, but its object protocol has no matrix
        multiplication slot, so ``__matmul__`` is never inlined and ``@`` is a graph break (an
        error under fullgraph; without it ``@`` works, but dynamo does not resume the function
        after it: the rest runs eagerly, with only the methods it calls compiled one by one).
        The methods below use ``compose``."""
        self._same_type(other, "other")
        return type(self)._new(self._f.compose(self._matrix, other._matrix))

    def __matmul__(self, other: LieGroup) -> Self:
        if not isinstance(other, LieGroup):
            return NotImplemented
        return self.compose(other)

    def inverse(self) -> Self:
        """g^-1, in closed form (no general matrix inverse)."""
        return type(self)._new(self._f.inverse(self._matrix))

    def adjoint(self) -> torch.Tensor:
        """Ad(g) (..., dof, dof): Ad(g) xi = vee(g hat(xi) g^-1); a new tensor (SO(3)'s is its
        matrix C, copied: writing to it leaves the element alone)."""
        Ad = self._f.adjoint(self._matrix)
        return Ad.clone() if Ad is self._matrix else Ad

    def _delta(self, delta: torch.Tensor) -> torch.Tensor:
        """Checks a tangent-vector argument (..., dof) against self before exp is applied."""
        checks.vector(delta, self.dof, "delta")
        checks.binary(self._matrix, 2, delta, 1, "self", "delta")
        return delta

    def rplus(self, delta: torch.Tensor) -> Self:
        """g exp(delta)."""
        return self.compose(type(self).exp(self._delta(delta)))

    def lplus(self, delta: torch.Tensor) -> Self:
        """exp(delta) g."""
        return type(self).exp(self._delta(delta)).compose(self)

    def rminus(self, other: LieGroup) -> torch.Tensor:
        """log(other^-1 g)."""
        return self._same_type(other, "other").between(self).log()

    def lminus(self, other: LieGroup) -> torch.Tensor:
        """log(g other^-1)."""
        return self.compose(self._same_type(other, "other").inverse()).log()

    def between(self, other: LieGroup) -> Self:
        """g^-1 other."""
        return self.inverse().compose(self._same_type(other, "other"))

    def interpolate(self, other: LieGroup, alpha: float | torch.Tensor) -> Self:
        """Geodesic g exp(alpha log(g^-1 h)); alpha a finite number or a tensor broadcasting with
        the batch (0 gives g, 1 gives h; a tensor's values are not checked).  Broadcasting is
        torch's: alpha (N, 1) against a batch (N,) gives (N, N); pass alpha (N,) for one value per
        element."""
        if isinstance(alpha, torch.Tensor):
            checks.floating(alpha, "alpha")
            checks.same_device_dtype(self=self._matrix, alpha=alpha)
        elif not isinstance(alpha, Real) or isinstance(alpha, bool):  # numpy scalars are Real
            raise TypeError(f"alpha must be a number or a torch.Tensor, got {type(alpha).__name__}")
        else:  # a number is read here; a tensor's values are not (no host sync)
            alpha = checks.finite_number(alpha, "alpha")
        delta = self.between(other).log()
        if not isinstance(alpha, torch.Tensor):  # a number scales delta as it is (no host copy)
            return self.rplus(delta * alpha)
        checks.broadcast_batch(batch=delta.shape[:-1], alpha=alpha.shape)
        return self.rplus(alpha.unsqueeze(-1) * delta)

    def allclose(self, other: LieGroup, rtol: float = 1e-5, atol: float = 1e-8, equal_nan: bool = False) -> bool:
        """True if every matrix of g is close to the matching (broadcast) matrix of ``other``, as
        torch.allclose on the homogeneous matrices: |g - h| <= atol + rtol |h| entrywise, NaNs
        equal only with ``equal_nan=True``.  A Python bool (one host sync; RuntimeError on
        'meta', which has no values); ``other`` of the same group (either may be a subclass),
        dtype and device."""
        self._same_type(other, "other")
        rtol = checks.finite_number(rtol, "rtol", ">= 0")
        atol = checks.finite_number(atol, "atol", ">= 0")
        equal_nan = checks.boolean(equal_nan, "equal_nan")
        a, b = torch.broadcast_tensors(self._matrix, other._matrix)
        if a.device.type == "meta":
            raise RuntimeError("allclose reads the matrices' values to return a Python bool, and "
                               "tensors on device 'meta' have none")
        return bool(torch.allclose(a, b, rtol=rtol, atol=atol, equal_nan=equal_nan))

    def act(self, x: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """The group's action on points (..., point_dim) (events (x, t) for SGal3), in homogeneous
        coordinates; each group's ``act`` gives its formula.  ``point_axes``: how many axes of
        points before the coordinates every element maps whole (see "Acting on points" above)."""
        return self._f.act(self._acting(x, "x", point_axes, self.point_dim), x)

    def act_jacobians(self, x: torch.Tensor, /, point_axes: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """The Jacobians of ``act(x)`` (..., rows): J_g (..., rows, dof) with respect to the
        right perturbation, d/dxi act(g exp(xi^), x) at 0, and J_x (..., rows, k) with respect
        to x (..., k); ``point_axes`` as in ``act``.  The action is linear in the matrix
        (M [x, tail], rows of it), so column j of J_g is the action of M hat(e_j)
        (``functional.blocks.act_homogeneous_jacobian``) and J_x is the block of M that
        multiplies x (Sim3, whose action divides by M[3, 3], gives its own).

        J_x is a copy of each element's block (writing to it leaves the element alone); where
        one element acts on many points, it is that copy expanded over the points (one block per
        element in memory, as ``expand`` gives: ``clone()`` it to write in place)."""
        M = self._acting(x, "x", point_axes, self.point_dim)
        J_g = self._f.act_jacobian(M, x)
        rows, k = J_g.shape[-2], x.shape[-1]
        # always a copy: where the block is the whole matrix (SO(3), SO(2)) and nothing
        # broadcasts, a reshape would give the element's own storage back
        J_x = M[..., :rows, :k].clone(memory_format=torch.contiguous_format)
        return J_g, J_x.expand(J_g.shape[:-1] + (k,))

    @classmethod
    def _right_products(cls, M: torch.Tensor) -> torch.Tensor:
        """M hat(e_j) for j < dof: (dof, *M.shape), as one matrix product (M's rows against the
        basis matrices side by side)."""
        n, dof = M.shape[-1], cls.dof
        hats = blocks.generators(cls._f.hat, dof, M)  # (dof, n, n)
        prod = M.reshape(-1, n) @ hats.permute(1, 0, 2).reshape(n, dof * n)  # (rows, dof * n)
        return prod.reshape(M.shape[:-1] + (dof, n)).movedim(-2, 0)

    def act_direction(self, d: torch.Tensor, point_axes: int = 0) -> torch.Tensor:
        """Directions (..., 3) (or (..., 2) for the planar groups), homogeneous [d, 0, ...]: C d.
        ``point_axes`` as in ``act``."""
        return self._f.act_direction(self._acting(d, "d", point_axes, self.rotation_dim), d)

    def _acting(self, x: torch.Tensor, name: str, point_axes: int, size: int) -> torch.Tensor:
        """The matrix that acts on ``x`` in ``act(x, point_axes)``, act_direction and
        act_velocity (the rule is in the class docstring): with ``point_axes`` = k > 0, a view with
        k axes of size 1 between the batch and matrix axes."""
        if type(point_axes) is int and point_axes == 0:  # the default, without the checks' cost
            return self._matrix
        k = checks.integer(point_axes, "point_axes", 0)
        if k == 0 or not isinstance(x, torch.Tensor):  # the functional layer names a non-tensor
            return self._matrix
        if x.dim() < k + 1:
            raise ValueError(f"{name} must have shape (..., {', '.join(['N'] * k)}, {size}) "
                             f"with point_axes={k}, got {tuple(x.shape)}")
        batch = self.batch_shape
        outer = x.shape[: x.dim() - 1 - k]
        try:
            checks.broadcast_shapes(batch, outer)
        except RuntimeError:
            raise ValueError(
                f"the batch shape {tuple(batch)} of this {type(self).__name__} does not broadcast "
                f"with the axes {tuple(outer)} of {name} {tuple(x.shape)} before its {k} point "
                f"ax{'is' if k == 1 else 'es'} (point_axes={k})") from None
        index = (Ellipsis,) + (None,) * k + (slice(None), slice(None))
        return self._matrix[index]  # a view

    # ----------------------------------------------------------- static algebra maps
    @classmethod
    def hat(cls, xi: torch.Tensor) -> torch.Tensor:
        """The Lie algebra matrix (..., matrix_dim, matrix_dim) of tangent vectors xi (..., dof)."""
        return cls._f.hat(xi)

    @classmethod
    def vee(cls, X: torch.Tensor) -> torch.Tensor:
        """The tangent vectors (..., dof) of Lie algebra matrices X: the inverse of hat."""
        return cls._f.vee(X)

    @classmethod
    def ad(cls, xi: torch.Tensor) -> torch.Tensor:
        """ad(xi) (..., dof, dof): ad(xi) eta = vee([hat xi, hat eta])."""
        return cls._f.ad(xi)

    @classmethod
    def jl(cls, xi: torch.Tensor) -> torch.Tensor:
        """Left Jacobian: exp(xi + d) ~ exp(J_l d) exp(xi)."""
        return cls._f.jl(xi)

    @classmethod
    def jr(cls, xi: torch.Tensor) -> torch.Tensor:
        """Right Jacobian J_l(-xi): exp(xi + d) ~ exp(xi) exp(J_r d)."""
        return cls._f.jr(checks.vector(xi, cls.dof, "xi"))

    @classmethod
    def jl_inv(cls, xi: torch.Tensor) -> torch.Tensor:
        """J_l(xi)^-1 (..., dof, dof), in closed form (block back-substitution, no general inverse)."""
        return cls._f.jl_inv(xi)

    @classmethod
    def jr_inv(cls, xi: torch.Tensor) -> torch.Tensor:
        """J_r(xi)^-1 = J_l(-xi)^-1 (..., dof, dof)."""
        return cls._f.jr_inv(checks.vector(xi, cls.dof, "xi"))

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        """Pickles (and torch.save's, deepcopies) as ``cls(matrix)``: loading goes through the
        constructor's shape and dtype checks (not a membership check), and torch.load's default
        weights_only unpickler accepts it (the group classes are registered with
        torch.serialization.add_safe_globals).  An element with attributes besides the matrix,
        or of a subclass with its own ``__init__``, pickles as ``_rebuild(cls, matrix, state)``
        (see the class docstring)."""
        cls = type(self)
        state = self._state()
        if state is None and cls.__init__ is LieGroup.__init__:
            return cls, (self._matrix,)
        return _rebuild, (cls, self._matrix, state)

    def _summary(self) -> str:
        """Class, batch shape, dtype and device (or what a torch.func wrapper holds)."""
        leaf = self._leaf_description()
        if leaf is not None:  # a torch.func wrapper, see the class docstring
            return f"{type(self).__name__}({leaf})"
        return (f"{type(self).__name__}(batch_shape={tuple(self.batch_shape)}, dtype={self.dtype}, "
                f"device={self.device})")

    def __repr__(self) -> str:
        """The summary; up to REPR_ELEMENTS elements also show their matrices, read as torch
        prints tensors (a host sync on CUDA; never on 'meta', in a torch.func transform or while
        compiling)."""
        head = self._summary()
        if (self._leaf_description() is None and self.batch_shape.numel() <= REPR_ELEMENTS
                and values_readable(self._matrix)):
            return f"{head} with matrix\n{self._matrix.detach()!r}"
        return head


LieGroup._group = LieGroup  # abstract: no group of its own (_new and __init__ refuse it)


def _rebuild(cls: type[LieGroup], matrix: torch.Tensor, state: dict | None = None) -> LieGroup:
    """Unpickles an element with attributes besides its matrix, or of a subclass with its own
    ``__init__`` (LieGroup.__reduce__): checks the matrix's shape and dtype as the constructor
    does, then sets the attributes without calling ``__init__`` (as pickle does for other
    objects).  Registered as a torch.load safe global, with the classes."""
    if not (isinstance(cls, type) and issubclass(cls, LieGroup)):
        raise TypeError(f"cls must be a LieGroup subclass, got {cls!r}")
    checks.matrix(matrix, cls.matrix_dim, "matrix")
    if state is not None and (not isinstance(state, dict) or "_matrix" in state):
        raise TypeError(f"state must be None or a dict of attributes other than _matrix, got {type(state).__name__}")
    return cls._from_leaf(matrix, state)


def _register_pytree(cls: type[LieGroup]) -> None:
    """Registers a group class as a pytree node with one leaf, its matrix, so that torch.func
    transforms (vmap, grad, jacrev, ...) take and return group objects; the context is the
    instance's other attributes (None for the built-in classes).  Through ``_compat``: where
    torch has no pytree registry, the transforms take the elements' matrices instead."""
    _compat.register_pytree_node(cls, lambda g: ([g._matrix], g._state()),
                                 lambda leaves, context: cls._from_leaf(leaves[0], context), "_matrix")


def _tol_arg(tol: float | None) -> float | None:
    """``tol``: None or a finite number > 0."""
    return None if tol is None else checks.finite_number(tol, "tol", "> 0")
