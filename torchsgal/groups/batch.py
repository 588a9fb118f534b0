"""The batch axes of group elements: ``MatrixBatch``, the part of ``LieGroup`` that treats an
element as a batch of matrices.

Shape, dtype, device and autograd state of the wrapped matrix; indexing, reshaping,
broadcasting, stacking and concatenation over the batch axes (never the matrix axes); moves
between dtypes and devices; copies.  None of it uses the group structure: every result is
built by the class's ``_new`` from the matrices' batch axes.
"""
from __future__ import annotations

import numbers
import sys
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from typing_extensions import Self

from ..functional import checks


class MatrixBatch:
    """The batch axes of ``LieGroup`` elements (module docstring); the group classes inherit it."""

    __slots__ = ()
    if TYPE_CHECKING:  # provided by LieGroup
        _matrix: torch.Tensor
        matrix_dim: int
        _group: ClassVar[type]

        @classmethod
        def _new(cls, matrix: torch.Tensor) -> Self: ...

        def _summary(self) -> str: ...

        @classmethod
        def _concrete(cls) -> None: ...

    # ------------------------------------------------------------------ properties
    @property
    def batch_shape(self) -> torch.Size:
        """The leading axes of the matrix (TypeError for a torch.func wrapper whose leaf is not
        a tensor of trailing shape (n, n), see LieGroup's docstring)."""
        m = self._matrix
        n = self.matrix_dim
        # a leaf that is not a tensor may be a group element, whose .shape is its batch shape
        if not isinstance(m, torch.Tensor) or m.dim() < 2 or m.shape[-1] != n or m.shape[-2] != n:
            raise TypeError(self._not_matrices())
        return m.shape[:-2]

    @property
    def shape(self) -> torch.Size:
        """The batch shape, the same as ``batch_shape`` (the matrix axes are not counted: an SE3
        of ``shape`` (B,) wraps a (B, 4, 4) tensor)."""
        return self.batch_shape

    @property
    def requires_grad(self) -> bool:
        """Whether autograd records operations on the wrapped matrix."""
        return self._matrix.requires_grad

    def requires_grad_(self, requires_grad: bool = True) -> Self:
        """Sets ``requires_grad`` of the wrapped matrix in place (as Tensor.requires_grad_, which
        refuses a matrix that is not a leaf of the autograd graph) and returns this element.
        The gradient then lands on ``as_matrix().grad``: a Euclidean gradient of the matrix
        entries, not a tangent vector.  To optimise an element on the group, hold it in a
        ``torchsgal.nn.ManifoldParameter``, which optimises a right perturbation."""
        requires_grad = checks.boolean(requires_grad, "requires_grad")
        self._matrix.requires_grad_(requires_grad)
        return self

    @property
    def dtype(self) -> torch.dtype:
        try:
            return self._matrix.dtype
        except AttributeError:
            raise TypeError(self._not_matrices()) from None

    @property
    def device(self) -> torch.device:
        try:
            return self._matrix.device
        except AttributeError:
            raise TypeError(self._not_matrices()) from None

    def _leaf_description(self) -> str | None:
        """None for a tensor of trailing shape (n, n), else what the pytree leaf is."""
        m = self._matrix
        if not isinstance(m, torch.Tensor):
            return f"<pytree leaf: {m._summary() if isinstance(m, MatrixBatch) else repr(m)}>"
        if m.dim() < 2 or m.shape[-2:] != (self.matrix_dim, self.matrix_dim):
            return f"<pytree leaf of shape {tuple(m.shape)}, dtype={m.dtype}, device={m.device}>"
        return None

    def _not_matrices(self) -> str:
        n = self.matrix_dim
        return (f"this {type(self).__name__} wraps {self._leaf_description()}, not matrices "
                f"(..., {n}, {n}): a torch.func result (a derivative, or vmap with out_dims), not a "
                f"group element; read it with as_matrix()")

    # ---------------------------------------------------------------- batch handling
    def __getitem__(self, index: Any) -> Self:
        """Indexes the batch axes only (ints, slices, None, Ellipsis, index or mask tensors, lists,
        tuples and numpy arrays of ints or bools).  A float index (tensor, list, tuple or array) is
        refused with IndexError (torch would truncate a sequence of floats: ``t[[0.7]]`` is ``t[[0]]``).

        As for tensors, ints, slices and None give a view of this element's matrix: it shares
        the storage (``torch.save`` of ``g[0]`` writes the whole batch; save ``g[0].clone()``),
        and in-place changes to either show in both."""
        if not isinstance(index, tuple):
            index = (index,)
        for entry in index:
            # torch truncates a list or numpy array of floats to integers (g[[0.5]] is g[[0]]);
            # refused as it refuses a float index tensor
            if (isinstance(entry, (list, tuple)) or type(entry).__name__ == "ndarray") and (
                    why := _non_integer_index(entry)):
                raise IndexError(f"{self._misfit(index)}: index lists, tuples and arrays must hold "
                                 f"integers or bools, got {why}")
        try:
            matrix = self._matrix[index + (slice(None), slice(None))]
        except (IndexError, ValueError) as err:  # ValueError: a negative slice step
            why = str(err)
            if "too many indices" in why:  # torch counts the matrix axes too
                n = len(self.batch_shape)
                why = f"too many indices for {n} batch ax{'is' if n == 1 else 'es'}"
            raise IndexError(f"{self._misfit(index)}: {why}") from None
        except TypeError as err:  # a string, say: torch's message does not name the index
            raise TypeError(f"{self._misfit(index)}: {err}") from None
        return type(self)._new(matrix)

    def _misfit(self, index: tuple) -> str:
        """The start of an indexing error (built only when one is raised: it reads the index's repr)."""
        return (f"index {index!r} does not fit the batch shape {tuple(self.batch_shape)} of this "
                f"{type(self).__name__}")

    def __len__(self) -> int:
        if not self.batch_shape:
            raise TypeError(f"len() of an unbatched {type(self).__name__}")
        return self.batch_shape[0]

    def __iter__(self) -> Iterator[Self]:
        """The elements along the first batch axis (as iterating a tensor); TypeError for an
        unbatched element, as for a 0-d tensor."""
        if not self.batch_shape:
            raise TypeError(f"iteration over an unbatched {type(self).__name__}")
        return (self[i] for i in range(self.batch_shape[0]))

    def __bool__(self) -> bool:
        raise TypeError(
            f"the truth value of a {type(self).__name__} is ambiguous: test `g is not None`, or "
            f"the batch size with g.batch_shape.numel()"
        )

    def reshape(self, *shape: Any) -> Self:
        """A new batch shape (one -1 allowed), as torch.reshape on the batch axes."""
        shape = _sizes(shape, "shape")
        n = self.matrix_dim
        try:
            return type(self)._new(self._matrix.reshape(*shape, n, n))
        except RuntimeError as err:
            raise ValueError(f"cannot reshape the batch shape {tuple(self.batch_shape)} of this "
                             f"{type(self).__name__} to {tuple(shape)}: {err}") from None

    def flatten(self) -> Self:
        """The batch axes flattened into one (an unbatched element gets batch shape (1,))."""
        return self.reshape(-1)

    def squeeze(self, dim: int | None = None) -> Self:
        """Removes batch axes of size 1: all of them, or only ``dim`` (counted over the batch
        axes) if it has size 1."""
        if dim is None:
            return self.reshape(tuple(s for s in self.batch_shape if s != 1))
        return type(self)._new(self._matrix.squeeze(_batch_axis(dim, len(self.batch_shape), "dim")))

    def expand(self, *shape: Any) -> Self:
        """The elements broadcast to the batch shape ``shape`` (a view, as Tensor.expand)."""
        shape = _sizes(shape, "shape")
        n = self.matrix_dim
        why = f"cannot expand the batch shape {tuple(self.batch_shape)} of this {type(self).__name__} to {tuple(shape)}"
        if len(shape) < len(self.batch_shape):
            raise ValueError(f"{why}: the target has fewer batch axes")
        try:
            return type(self)._new(self._matrix.expand(*shape, n, n))
        except RuntimeError as err:
            raise ValueError(f"{why}: {err}") from None

    def unsqueeze(self, dim: int) -> Self:
        """A new batch axis of size 1 at ``dim`` (counted over the batch axes only)."""
        return type(self)._new(self._matrix.unsqueeze(_batch_axis(dim, len(self.batch_shape) + 1, "dim")))

    @classmethod
    def stack(cls, elements: Sequence[MatrixBatch], dim: int = 0) -> Self:
        """Stack elements of equal batch shape along a new batch axis ``dim``."""
        mats = cls._matrices(elements, "stack")
        axis = _batch_axis(dim, mats[0].dim() - 1, "dim")
        for i, m in enumerate(mats[1:], 1):
            if m.shape != mats[0].shape:
                raise ValueError(f"{cls.__name__}.stack needs elements of equal batch shape: "
                                 f"elements[0] has {tuple(mats[0].shape[:-2])}, "
                                 f"elements[{i}] has {tuple(m.shape[:-2])}")
        return cls._new(torch.stack(mats, dim=axis))

    @classmethod
    def cat(cls, elements: Sequence[MatrixBatch], dim: int = 0) -> Self:
        """Concatenate elements along their existing batch axis ``dim``."""
        mats = cls._matrices(elements, "cat")
        if mats[0].dim() == 2:
            raise ValueError(f"{cls.__name__}.cat needs elements with a batch axis; use stack")
        axis = _batch_axis(dim, mats[0].dim() - 2, "dim")
        b0 = mats[0].shape[:-2]
        for i, m in enumerate(mats[1:], 1):
            b = m.shape[:-2]
            if len(b) != len(b0) or any(x != y for k, (x, y) in enumerate(zip(b, b0)) if k != axis):
                raise ValueError(f"{cls.__name__}.cat needs elements whose batch shapes differ only "
                                 f"along dim {dim}: elements[0] has {tuple(b0)}, elements[{i}] has {tuple(b)}")
        return cls._new(torch.cat(mats, dim=axis))

    @classmethod
    def _matrices(cls, elements: Sequence[MatrixBatch], op: str) -> list[torch.Tensor]:
        cls._concrete()  # LieGroup.stack would take elements of different groups
        if isinstance(elements, MatrixBatch):  # iterating it would stack or cat its first batch axis
            raise TypeError(f"{cls.__name__}.{op}: elements must be a sequence of elements (a list "
                            f"or tuple), got one {type(elements).__name__}; write "
                            f"{cls.__name__}.{op}([g, ...])")
        try:
            elements = list(elements)
        except TypeError:
            raise TypeError(f"{cls.__name__}.{op}: elements must be a sequence of elements (a list "
                            f"or tuple), got {type(elements).__name__}") from None
        if not elements:
            raise ValueError(f"{cls.__name__}.{op} needs at least one element")
        for i, e in enumerate(elements):
            if not isinstance(e, cls._group):
                raise TypeError(f"{cls.__name__}.{op}: elements[{i}] must be a {cls._group.__name__}, "
                                f"got {type(e).__name__}")
        # one dtype and device, as compose (no silent promotion)
        checks.same_device_dtype(**{f"elements[{i}]": e._matrix for i, e in enumerate(elements)})
        return [e._matrix for e in elements]

    def to(self, *args: Any, **kwargs: Any) -> Self:
        """As torch.Tensor.to on the matrix (dtype and/or device)."""
        return type(self)._new(self._matrix.to(*args, **kwargs))

    def float(self) -> Self:
        """The same elements in float32."""
        return self.to(torch.float32)

    def double(self) -> Self:
        """The same elements in float64."""
        return self.to(torch.float64)

    def cpu(self) -> Self:
        """The same elements on the CPU."""
        return type(self)._new(self._matrix.cpu())

    def cuda(self, device: torch.device | int | str | None = None) -> Self:
        """The same elements on a CUDA device."""
        return type(self)._new(self._matrix.cuda(device))

    def detach(self) -> Self:
        """The same elements, detached from the autograd graph."""
        return type(self)._new(self._matrix.detach())

    def clone(self) -> Self:
        """A copy with its own storage."""
        return type(self)._new(self._matrix.clone())


def _non_integer_index(entry: Any) -> str | None:
    """What makes a list, tuple or numpy array index non-integer (a float or complex item or dtype),
    None for integer and bool ones and for other entries (ints, slices, None, Ellipsis, tensors:
    torch checks those).  Pure Python: no tensor is made, so nothing is traced or synced."""
    if isinstance(entry, (list, tuple)):  # a tuple inside the index is a sequence index too
        for item in entry:
            why = _non_integer_index(item)
            if why is None and isinstance(item, (float, complex)):
                why = f"{item!r}"
            if why is not None:
                return why
        return None
    np = sys.modules.get("numpy")  # a numpy value can only come from an imported numpy
    if np is not None and isinstance(entry, (np.ndarray, np.floating, np.complexfloating)):
        if entry.dtype.kind in "fc":
            return f"dtype {entry.dtype}" if isinstance(entry, np.ndarray) else f"{entry!r}"
    return None


def _sizes(shape: tuple, name: str) -> tuple:
    """The sizes of ``reshape(*shape)`` / ``reshape(shape)`` (ints, -1 among them; bool refused)."""
    if len(shape) == 1 and not isinstance(shape[0], (numbers.Integral, torch.SymInt)):
        try:
            shape = tuple(shape[0])
        except TypeError:
            raise TypeError(f"{name} must be ints or one sequence of ints, got {shape[0]!r}") from None
    for size in shape:
        if isinstance(size, bool) or not isinstance(size, (numbers.Integral, torch.SymInt)):
            raise TypeError(f"{name} must be ints or one sequence of ints, got {size!r} in {shape!r}")
    return shape


def _batch_axis(dim: int, n_axes: int, name: str) -> int:
    """``dim`` in [-n_axes, n_axes) as a non-negative axis; the matrix axes are never counted."""
    dim = checks.integer(dim, name)
    if n_axes == 0:  # "must be in [0, -1]" would make no sense
        raise IndexError(f"{name} must index a batch axis, but an unbatched element has none, got {dim}")
    if not -n_axes <= dim < n_axes:
        raise IndexError(f"{name} must be in [{-n_axes}, {n_axes - 1}] (batch axes only), got {dim}")
    return dim % n_axes
