r"""The shared base of every lieax group: a frozen pytree around one parameter array.

Conventions (fixed for the whole library, see docs/conventions.md):
right perturbation $X \oplus \xi = X\,\mathrm{Exp}(\xi)$, $X \ominus Y = \mathrm{Log}(Y^{-1} X)$,
adjoint $X\,\mathrm{Exp}(\xi)\,X^{-1} = \mathrm{Exp}(\mathrm{Ad}_X \xi)$, and
$\mathrm{Exp}(\xi + \delta) \approx \mathrm{Exp}(\xi)\,\mathrm{Exp}(J_r(\xi)\,\delta)$.

The group protocol. A concrete group's kernel namespace is the module that defines its class:
array functions on parameters and tangents named as in `KERNELS`, bound to the class when it is
created, so a missing kernel is a `TypeError` at import. A group writes the values of its
operations and a few kernels (`ad`, `right_jacobian`, `right_jacobian_inverse`, `hat`, `vee`, the
carrier maps below) and `lieax.groups._generic.local_rules` turns them into `jax.custom_jvp`
functions with the rules that are the same for every group (`compose`, `inverse`, `exp`, `log`,
`adjoint`, `as_matrix`, `from_matrix`, `normalize`, `to_parameters`, `from_parameters`); a group
keeps a hand-written rule where its closed form is cheaper (SO3's, SE3's and Sim3's compose and
inverse, which avoid the adjoint matrix; SO3's exp and log, which avoid the 3×3 Jacobian; what
`benchmarks/chain.py` times) or exact where the generic one is not (SO2's and SE2's `from_matrix`
off the group), and writes its action on points (`act`) itself. This base class validates inputs
once, at trace time, and implements `between`, `rplus`, `rminus`, `interpolate` and the operators
from the kernels, so their derivatives compose from the kernels' closed-form blocks.

The tangent carrier (one convention for every group). JAX gives the parameter leaf a tangent of
the leaf's shape; each group fills it with its *local carrier*: the right-local tangent itself,
laid out in the parameter slots, plus the radial part of the unit rotation parameters (a quaternion
derivative $\dot q = q \otimes (\rho, \omega/2)$, a complex one $\dot z = z\,(\rho + i\theta)$). Rules
read and write local tangents with `to_local(params, carrier)` / `from_local(params, local)`, which
only pick entries, so no rule converts anything and the generic rules hold for every group. The
derivative of the raw parameters appears only where raw arrays cross the API (`G(params)`,
`parameters()`, constructors from raw arrays), through `to_parameters` / `from_parameters`
(identity on values), whose rules are the group's `raw_from_carrier(params, carrier)` and
`carrier_from_raw(params, raw)`; inside rules, anything that depends on the parameters goes through
kernels or `to_parameters`, so derivatives of every order stay consistent with the carrier.
The manifold S2 (not a group) keeps the raw carrier, its tangent the derivative $\dot p$ of the
unit vector: its operations are rational functions of $p$ with no `custom_jvp` rules, which JAX
differentiates exactly only on raw derivatives, so a local carrier would need a hand-written rule
on every one of them, and `to_local` / `from_local` ($B_p^\top \dot p$, $B_p \xi$) serve only
`lieax.jacobian` and the solvers.
"""

import sys
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, Self, overload

import jax
import numpy as np
from jax.typing import ArrayLike, DTypeLike

from .._checks import (
    broadcast_batch,
    check_last_axis,
    check_matrix,
    check_same_dtype,
    is_concrete,
    match_dtype,
    to_device,
)
from .._eager import compiled_when_eager
from . import _host

# The kernel namespace of a group: these names, bound to the class as `_exp`, `_log`, ...
# (`to_local` as `_local_from_tangent`, `from_local` as `_tangent_from_local`).
KERNELS = (
    "exp", "log", "compose", "inverse", "act", "adjoint", "as_matrix", "from_matrix", "normalize",
    "hat", "vee", "ad", "right_jacobian", "right_jacobian_inverse", "to_local", "from_local",
    "raw_from_carrier", "carrier_from_raw", "to_parameters", "from_parameters", "sample_uniform",
)  # fmt: skip
_ATTRIBUTES = {"to_local": "_local_from_tangent", "from_local": "_tangent_from_local"}


class AbstractManifold:
    r"""A batch of points of one manifold, stored as `parameters()` of shape
    `(*batch_shape, parameters_dim)`; a JAX pytree with that one array as its leaf.

    A concrete manifold supplies `rplus(tangent)`, `rminus(other)` and the carrier maps
    `_local_from_tangent(params, tangent)` / `_tangent_from_local(params, local)` between the JAX
    tangent of the parameter leaf and the local tangent of shape `(*batch_shape, tangent_dim)`;
    that is all `lieax.rplus`, `lieax.jacobian` and the solvers use. Groups (`AbstractGroup`) are
    manifolds whose $\oplus$ is $X\,\mathrm{Exp}(\xi)$; `S2` is a manifold that is not a group."""

    tangent_dim: ClassVar[int]
    parameters_dim: ClassVar[int]
    parameters_layout: ClassVar[str]
    _params: jax.Array  # the parameter leaf, in the tangent carrier's form (module docstring)

    __slots__ = ("_params",)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if not cls.__name__.startswith("Abstract"):
            jax.tree_util.register_pytree_node(
                cls, _flatten, lambda _, leaves: cls._wrap(leaves[0])
            )

    def __init__(self, parameters: ArrayLike) -> None:
        """Wraps parameters as given (after checking shape and dtype); see `normalize()`."""
        name = f"{type(self).__name__} parameters"
        params = check_last_axis(parameters, self.parameters_dim, name, self.parameters_layout)
        if isinstance(params, jax.core.Tracer):  # a concrete array has no derivative to convert
            params = self._from_parameters(params)
        object.__setattr__(self, "_params", params)

    @classmethod
    def _wrap(cls, params):
        """An element around `params` without checks (pytree unflattening, kernel outputs)."""
        element = object.__new__(cls)
        object.__setattr__(element, "_params", params)
        return element

    def __setattr__(self, name, value):
        raise AttributeError(f"{type(self).__name__} is immutable.")

    def __repr__(self):
        return f"{type(self).__name__}({self._params!r})"

    # The maps between the parameter leaf's JAX tangent and raw derivatives (the module docstring):
    # the identity for a manifold whose carrier is the raw derivative (S2); groups bind their own.
    _from_parameters = staticmethod(lambda params: params)
    _to_parameters = staticmethod(lambda params: params)

    def parameters(self) -> jax.Array:
        """The parameter array, layout `parameters_layout` (differentiable as a raw array)."""
        params = self._params
        # the conversion is the identity on values, and a concrete array has no derivative to
        # convert: skipping it saves an eager custom_jvp call (~0.2 ms) outside jit
        return self._to_parameters(params) if isinstance(params, jax.core.Tracer) else params

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self._params.shape[:-1])

    @property
    def dtype(self) -> np.dtype:
        return self._params.dtype

    def __getitem__(self, index: Any) -> Self:
        index = index if isinstance(index, tuple) else (index,)
        return self._wrap(self._params[(*index, slice(None))])

    def rplus(self, tangent: ArrayLike) -> Self:
        r"""$X \oplus \xi$ for tangents of shape `(*batch, tangent_dim)`."""
        raise NotImplementedError

    def rminus(self, other: Self) -> jax.Array:
        r"""$X \ominus Y$, so that `Y.rplus(X.rminus(Y)) == X`."""
        raise NotImplementedError


class AbstractGroup(AbstractManifold):
    """A batch of elements of one matrix Lie group, stored as `parameters()` of shape
    `(*batch_shape, parameters_dim)`; a JAX pytree with that one array as its leaf."""

    space_dim: ClassVar[int]
    matrix_dim: ClassVar[int]
    # NumPy versions of `exp` and `from_matrix` for concrete inputs (`lieax.groups._host`), where a
    # group has them: constructors then compile nothing.
    _host_exp: ClassVar[Callable[[np.ndarray], np.ndarray] | None] = None  # a staticmethod
    _host_from_matrix: ClassVar[Callable[[np.ndarray], np.ndarray] | None] = None

    __slots__ = ()

    def __init_subclass__(cls, **kwargs):
        """Binds the kernel namespace (the class's `kernels` attribute, by default the module that
        defines the class; see `KERNELS`) to a concrete group; a subclass of a concrete group
        inherits its kernels. A missing kernel is a `TypeError` here, at class creation."""
        super().__init_subclass__(**kwargs)
        inherits = any(hasattr(base, "_exp") for base in cls.__mro__[1:])
        if cls.__name__.startswith("Abstract") or (inherits and "kernels" not in cls.__dict__):
            return
        kernels = cls.__dict__.get("kernels", sys.modules[cls.__module__])
        missing = [name for name in KERNELS if not callable(getattr(kernels, name, None))]
        if missing:
            raise TypeError(
                f"{cls.__name__} lacks the group kernels {', '.join(missing)}: its kernel "
                f"namespace ({getattr(kernels, '__name__', kernels)!r}) must define every name of "
                "lieax.groups._base.KERNELS."
            )
        for name in KERNELS:
            kernel = getattr(kernels, name)
            if name != "sample_uniform":  # (its shape and dtype arguments are static)
                kernel = compiled_when_eager(kernel)
            setattr(cls, _ATTRIBUTES.get(name, f"_{name}"), staticmethod(kernel))

    # ---- construction ------------------------------------------------------------------------
    @classmethod
    def identity(cls, batch_shape: Sequence[int] = (), dtype: DTypeLike | None = None) -> Self:
        """The identity element, repeated over `batch_shape`."""
        dtype = jax.dtypes.canonicalize_dtype(float if dtype is None else dtype)
        params = _host.identity(cls.parameters_dim, tuple(batch_shape), dtype)
        return cls._wrap(to_device(params))

    @classmethod
    def exp(cls, tangent: ArrayLike) -> Self:
        r"""$\mathrm{Exp}(\xi)$ for tangents of shape `(*batch, tangent_dim)`."""
        tangent = check_last_axis(tangent, cls.tangent_dim, f"{cls.__name__}.exp tangent")
        if cls._host_exp is not None and is_concrete(tangent):  # no compilation
            return cls._wrap(to_device(cls._host_exp(np.asarray(tangent))))
        return cls._wrap(cls._exp(tangent))

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> Self:
        """The element nearest to a homogeneous matrix (rotations are re-orthogonalized)."""
        matrix = check_matrix(matrix, cls.matrix_dim, f"{cls.__name__}.from_matrix matrix")
        if cls._host_from_matrix is not None and is_concrete(matrix):  # no compilation
            return cls._wrap(to_device(cls._host_from_matrix(np.asarray(matrix))))
        return cls._wrap(cls._from_matrix(matrix))

    @classmethod
    def sample_uniform(
        cls, key: ArrayLike, batch_shape: Sequence[int] = (), dtype: DTypeLike | None = None
    ) -> Self:
        """Random elements: rotations uniform (Haar), translations uniform in [-1, 1]."""
        return cls._wrap(cls._sample_uniform(key, tuple(batch_shape), dtype))

    # ---- group operations --------------------------------------------------------------------
    def log(self) -> jax.Array:
        r"""$\mathrm{Log}(X)$, the tangent of shape `(*batch, tangent_dim)`."""
        return self._log(self._params)

    def inverse(self) -> Self:
        """$X^{-1}$."""
        return self._wrap(self._inverse(self._params))

    def compose(self, other: Self) -> Self:
        r"""$X \cdot Y$, broadcasting batch shapes."""
        self._check_same_group(other, "compose")
        broadcast_batch(f"{type(self).__name__} compose", self.batch_shape, other.batch_shape)
        return self._wrap(self._compose(self._params, other._params))

    def act(self, points: ArrayLike) -> jax.Array:
        r"""$X \cdot p$ for points of shape `(*batch, space_dim)`, broadcasting against the group's
        batch shape (a single element acts on a whole cloud)."""
        name = f"{type(self).__name__} acting on points"
        points = match_dtype(points, self.dtype, name, f"the {type(self).__name__}")
        points = check_last_axis(points, self.space_dim, name, f"{self.space_dim}D points")
        broadcast_batch(name, self.batch_shape, points.shape[:-1])
        return self._act(self._params, points)

    @overload
    def __matmul__(self, other: Self) -> Self: ...
    @overload
    def __matmul__(self, other: ArrayLike) -> jax.Array: ...
    def __matmul__(self, other):
        if isinstance(other, AbstractGroup):
            return self.compose(other)
        return self.act(other)

    def between(self, other: Self) -> Self:
        """$X^{-1} Y$: `other` expressed in the frame of `self`."""
        return self.inverse().compose(other)

    def adjoint(self) -> jax.Array:
        r"""$\mathrm{Ad}_X$, shape `(*batch, tangent_dim, tangent_dim)`, with
        $X\,\mathrm{Exp}(\xi)\,X^{-1} = \mathrm{Exp}(\mathrm{Ad}_X \xi)$."""
        return self._adjoint(self._params)

    def as_matrix(self) -> jax.Array:
        """The homogeneous matrix, shape `(*batch, matrix_dim, matrix_dim)`."""
        return self._as_matrix(self._params)

    def normalize(self) -> Self:
        """The nearest valid element (unit rotation parameters); parameters given to the
        constructor are used as given, so call this on data that may have drifted."""
        return self._wrap(self._normalize(self._params))

    def rplus(self, tangent: ArrayLike) -> Self:
        r"""$X \oplus \xi = X\,\mathrm{Exp}(\xi)$."""
        name = type(self).__name__
        tangent = match_dtype(tangent, self.dtype, f"{name}.rplus tangent", f"the {name}")
        return self.compose(type(self).exp(tangent))

    def rminus(self, other: Self) -> jax.Array:
        r"""$X \ominus Y = \mathrm{Log}(Y^{-1} X)$, so that `Y.rplus(X.rminus(Y)) == X`."""
        self._check_same_group(other, "rminus")
        return other.between(self).log()

    def interpolate(self, other: Self, t: ArrayLike) -> Self:
        r"""$X \oplus t\,(Y \ominus X)$: `self` at `t = 0`, `other` at `t = 1`, along the geodesic;
        `t` of shape `(*batch,)` broadcasts against both batch shapes (a Python or NumPy number
        takes the group's dtype)."""
        name = f"{type(self).__name__}.interpolate"
        self._check_same_group(other, "interpolate")
        t = match_dtype(t, self.dtype, f"{name} t", f"the {type(self).__name__}")
        broadcast_batch(name, self.batch_shape, other.batch_shape, t.shape)
        return self.rplus(other.rminus(self) * t[..., None])

    # ---- tangent-space maps ------------------------------------------------------------------
    @classmethod
    def hat(cls, tangent: ArrayLike) -> jax.Array:
        """The Lie algebra matrix of a tangent, shape `(*batch, matrix_dim, matrix_dim)`."""
        return cls._hat(check_last_axis(tangent, cls.tangent_dim, f"{cls.__name__}.hat tangent"))

    @classmethod
    def vee(cls, algebra: ArrayLike) -> jax.Array:
        """The tangent of a Lie algebra matrix; inverse of `hat`."""
        return cls._vee(check_matrix(algebra, cls.matrix_dim, f"{cls.__name__}.vee matrix"))

    @classmethod
    def right_jacobian(cls, tangent: ArrayLike) -> jax.Array:
        r"""$J_r(\xi)$ with $\mathrm{Exp}(\xi + \delta) \approx \mathrm{Exp}(\xi)\,\mathrm{Exp}(J_r\delta)$."""
        return cls._right_jacobian(cls._check_tangent(tangent))

    @classmethod
    def right_jacobian_inverse(cls, tangent: ArrayLike) -> jax.Array:
        r"""$J_r(\xi)^{-1}$, the derivative of Log: $\mathrm{Log}(X\,\mathrm{Exp}(\delta)) \approx
        \mathrm{Log}(X) + J_r^{-1}\delta$."""
        return cls._right_jacobian_inverse(cls._check_tangent(tangent))

    @classmethod
    def left_jacobian(cls, tangent: ArrayLike) -> jax.Array:
        r"""$J_l(\xi) = J_r(-\xi)$, with $\mathrm{Exp}(\xi + \delta) \approx \mathrm{Exp}(J_l\delta)\,\mathrm{Exp}(\xi)$."""
        return cls._right_jacobian(-cls._check_tangent(tangent))

    @classmethod
    def left_jacobian_inverse(cls, tangent: ArrayLike) -> jax.Array:
        r"""$J_l(\xi)^{-1} = J_r(-\xi)^{-1}$."""
        return cls._right_jacobian_inverse(-cls._check_tangent(tangent))

    # ---- helpers -----------------------------------------------------------------------------
    @classmethod
    def _check_tangent(cls, tangent):
        return check_last_axis(tangent, cls.tangent_dim, f"{cls.__name__} tangent")

    def _check_same_group(self, other, operation):
        if type(other) is not type(self):
            raise TypeError(
                f"{type(self).__name__}.{operation} needs another {type(self).__name__}, "
                f"got {type(other).__name__}."
            )
        check_same_dtype(f"{type(self).__name__}.{operation}", self.dtype, other.dtype)


def _flatten(element):
    return (element._params,), None
