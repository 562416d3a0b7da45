r"""Factor kinds: one residual function written for one instance, vmapped over many instances.

A `Factor` is $r_i = R\,f(x_{a_i}, x_{b_i}, \dots, d_i) \in \mathbb{R}^k$ for instances
$i = 1 \dots m$: the same `residual` function, index arrays per argument into variable kinds,
batched `data` $d_i$, a square-root information $R$ (shared `(k, k)` or per instance
`(m, k, k)`, $\Omega = R^\top R$) and an optional robust loss $\rho$ from `lieax.lstsq`. Its
cost is $\tfrac12 \sum_i \rho(\|r_i\|^2)$ and it enters the normal equations reweighted by
$w_i = \rho'(\|r_i\|^2)$ (IRLS, as GTSAM's robust noise models and Ceres' `LossFunction`
without its second-order correction; Triggs et al. 2000, Sec. 3.3).

Jacobian blocks $\partial f / \partial x_a$ (shape `(k, tangent_dim_a)`, right-local tangents)
come from `lieax.value_and_jacobian`, i.e. the groups' closed-form `custom_jvp` rules, unless a
`jacobian_fn(*xs, data) -> (residual, (J_a, J_b, ...))` is given.
"""

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Self

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._checks import check_not_foreign, foreign_conversion
from .._typing import PyTree
from ..autodiff._jacobian import value_and_jacobian
from ..lstsq import AbstractLoss
from ._variables import VarRef


class Factor:
    r"""One factor kind (see the module docstring).

    **Arguments:**

    - `residual`: `residual(x_a, x_b, ..., data) -> (k,)` for ONE instance (`data` is passed
      only when given); each `x` is one instance of its variable kind (a group, an array or a
      pytree of them).
    - `args`: one `var[index]` per argument of `residual`, `index` an integer array `(m,)`.
    - `data`: a pytree of arrays with leading axis `m` (or `None`).
    - `sqrt_information`: $R$, `(k, k)` shared or `(m, k, k)`; or `information` $\Omega$, or
      `covariance` $\Sigma = \Omega^{-1}$ (GTSAM's `noiseModel::Gaussian::Information` and
      `Covariance`; converted by `square_root_information`, `ValueError` naming the factor
      kind and the first matrix that is not symmetric positive (semi-)definite), or `sigmas`
      $\sigma$, `(k,)` shared or `(m, k)`, $R = \mathrm{diag}(1/\sigma)$ (GTSAM's
      `noiseModel::Diagonal::Sigmas`). At most one of the four; default identity.
      **Partial information** (a prior that constrains only some coordinates, as GTSAM's KITTI
      example's prior on the first pose with zero rotation precision): `sigmas` may hold `inf`
      (weight 0: that coordinate is unconstrained), `information` may be positive
      semi-definite (its zero eigenvalues' directions are unconstrained) and `sqrt_information`
      rank deficient (zero rows). The gauge check of `FactorGraph` counts only the constrained
      directions. NaN, negative or zero sigmas, an information with a negative eigenvalue, a
      non-finite or all-zero $R$ stay errors.
    - `loss`: a robust loss (`lieax.lstsq.Huber`, `Cauchy`, ...) or `None`.
    - `jacobian_fn`: optional `jacobian_fn(*xs, data) -> (residual, (J_a, ...))`, blocks
      `(k, tangent_dim)` in right-local coordinates, for one instance.
    - `name`: used in error messages (default `"factor<k>"`).
    """

    def __init__(
        self,
        residual: Callable[..., ArrayLike],
        args: Iterable[VarRef],
        data: PyTree | None = None,
        *,
        sqrt_information: ArrayLike | None = None,
        information: ArrayLike | None = None,
        covariance: ArrayLike | None = None,
        sigmas: ArrayLike | Sequence[float] | None = None,
        loss: AbstractLoss | None = None,
        jacobian_fn: Callable[..., tuple[ArrayLike, Sequence[ArrayLike]]] | None = None,
        name: str | None = None,
    ):
        self.residual = residual
        self.name = name
        args = tuple(args)
        if not args or not all(isinstance(a, VarRef) for a in args):
            raise TypeError(f"Factor {name!r}: args must be a non-empty tuple of var[index].")
        self.vars = tuple(a.var for a in args)
        self.indices = tuple(_index_array(a.index, name, k) for k, a in enumerate(args))
        counts = {len(i) for i in self.indices}
        if len(counts) != 1:
            raise ValueError(
                f"Factor {name!r}: the index arrays of its arguments have different lengths "
                f"{[len(i) for i in self.indices]}."
            )
        self.count = counts.pop()
        self.data = _data_arrays(data, name, variables_dtype(self.vars))
        given = [
            option
            for option, value in (
                ("sqrt_information", sqrt_information),
                ("information", information),
                ("covariance", covariance),
                ("sigmas", sigmas),
            )
            if value is not None
        ]
        if len(given) > 1:
            raise ValueError(
                f"Factor {name!r}: give one of sqrt_information, information, covariance and "
                f"sigmas, not {' and '.join(given)}."
            )
        if information is not None or covariance is not None:
            sqrt_information = square_root_information(
                information if covariance is None else covariance,
                f"Factor {name!r}: {given[0]}",
                covariance=covariance is not None,
                semidefinite=information is not None,
            )
        elif sigmas is not None:
            sqrt_information = sigmas_to_sqrt_information(sigmas, f"Factor {name!r}: sigmas")
        self.sqrt_information = sqrt_information
        self.loss = loss
        self.jacobian_fn = jacobian_fn
        self.residual_size = None  # k, set when a `FactorGraph` checks the kind

    @classmethod
    def make(
        cls,
        residual: Callable[..., ArrayLike],
        args: Iterable[VarRef],
        data: PyTree | None = None,
        **options: Any,
    ) -> Self:
        """`Factor(residual, args, data, **options)` (jaxls' spelling)."""
        return cls(residual, args, data, **options)

    def __repr__(self):
        names = ", ".join(str(v.name) for v in self.vars)
        return f"Factor({self.name!r}, count={self.count}, vars=({names}))"


def variables_dtype(variables):
    """The floating dtype of the values of `variables` (their leaves' common dtype)."""
    leaves = jax.tree_util.tree_leaves(tuple(v.value for v in variables))
    return np.result_type(*(jnp.result_type(x) for x in leaves))


def _data_arrays(data, name, dtype):
    """`data` with each nested Python list of numbers made a NumPy array of the variables'
    `dtype` (`[[x, y], ...]` is one `(m, 2)` leaf, not `2m` scalars); `TypeError` naming the
    factor kind for a jaxlie group or an Open3D cloud (`lieax._checks.check_not_foreign`)."""

    def numbers(x):
        return isinstance(x, list) and all(
            numbers(y) or (isinstance(y, (int, float)) and not isinstance(y, bool)) for y in x
        )

    def convert(path, leaf):
        if numbers(leaf):
            return np.asarray(leaf, dtype=dtype)
        check_not_foreign(leaf, f"Factor {name!r}: data{jax.tree_util.keystr(path)}")
        return leaf

    return jax.tree_util.tree_map_with_path(
        convert, data, is_leaf=lambda x: numbers(x) or foreign_conversion(x) is not None
    )


def _index_array(index, name, position):
    index = np.asarray(index)
    if index.ndim == 0:
        index = index.reshape(1)
    if index.ndim != 1 or not np.issubdtype(index.dtype, np.integer):
        raise ValueError(
            f"Factor {name!r}: argument {position}'s index must be a 1-D integer array, got "
            f"dtype {index.dtype} shape {index.shape}."
        )
    return index.astype(np.int64)


def sigmas_to_sqrt_information(sigmas, what="sigmas"):
    r"""$R = \mathrm{diag}(1/\sigma)$ of standard deviations `(..., k)` (numpy float64; GTSAM's
    `noiseModel::Diagonal::Sigmas`): $\sigma = \infty$ gives weight 0, an unconstrained
    coordinate. `ValueError` naming `what` and the first bad entry for a NaN, zero or negative
    sigma, or a row with no finite sigma (it constrains nothing)."""
    sigmas = np.asarray(sigmas, dtype=np.float64)
    if sigmas.ndim < 1:
        raise ValueError(f"{what} must have shape (..., k), got {sigmas.shape}.")
    flat = sigmas.reshape(-1, sigmas.shape[-1])
    bad = ~(flat > 0)  # NaN, zero or negative
    if np.any(bad):
        first = np.argwhere(bad)[0]
        raise ValueError(
            f"{what} {int(first[0])} has sigma {flat[tuple(first)]} at coordinate "
            f"{int(first[1])}: sigmas must be positive (inf for an unconstrained coordinate)."
        )
    if np.any(np.all(np.isinf(flat), axis=1)):
        first = int(np.argmax(np.all(np.isinf(flat), axis=1)))
        raise ValueError(f"{what} {first} is all inf: it constrains nothing (drop it).")
    weights = 1.0 / sigmas
    return weights[..., :, None] * np.eye(sigmas.shape[-1])


def square_root_information(
    matrix: ArrayLike,
    what: str = "information matrix",
    *,
    covariance: bool = False,
    semidefinite: bool = False,
) -> np.ndarray:
    r"""The square-root information $R$, $R^\top R = \Omega$, of a batch `(..., d, d)` of
    information matrices $\Omega$ or, with `covariance=True`, of covariances
    $\Sigma = \Omega^{-1}$ (numpy float64; the one conversion of `Factor`, `lieax.graph` and the
    IMU factors).

    - information: $R = L^\top$, upper triangular, for the Cholesky factorization
      $\Omega = L L^\top$ (GTSAM's `noiseModel::Gaussian::Information`).
    - covariance: $R = L^{-1}$, lower triangular, for $\Sigma = L L^\top$:
      $R^\top R = L^{-\top} L^{-1} = \Sigma^{-1}$ without forming $\Sigma^{-1}$ ($R$'s
      condition number is the square root of $\Sigma$'s; GTSAM's
      `noiseModel::Gaussian::Covariance` inverts $\Sigma$ first). Either way
      $\|R r\|^2 = r^\top \Omega r$.

    Each matrix must be finite, symmetric to $10^{-9}$ of its largest entry (its symmetric part
    is factored) and positive definite; else `ValueError`: "`what` `i` is not symmetric
    positive definite (eigenvalues ...)", `i` the first bad one in the flattened batch.

    With `semidefinite=True` an information matrix may be positive semi-definite (a prior that
    leaves some directions free): one that Cholesky refuses is factored by its eigenvalues,
    $\Omega = V \Lambda V^\top$, $R = \Lambda^{1/2} V^\top$ with the eigenvalues at most
    $10^{-9}$ of the largest (rounding) set to 0, so $R^\top R = \Omega$ and $R$ has a zero row
    per free direction. An eigenvalue below $-10^{-9}$ of the largest is still an error.
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.ndim < 2 or matrix.shape[-1] != matrix.shape[-2]:
        raise ValueError(f"{what} must have shape (..., d, d), got {matrix.shape}.")
    batch = matrix.reshape(-1, *matrix.shape[-2:])
    transposed = np.swapaxes(batch, 1, 2)
    finite = np.all(np.isfinite(batch), axis=(1, 2))
    scale = np.max(np.abs(batch), axis=(1, 2), initial=0.0)
    symmetric = finite & np.all(np.abs(batch - transposed) <= 1e-9 * scale[:, None, None], (1, 2))
    batch = 0.5 * (batch + transposed)
    try:
        if not np.all(symmetric):
            raise np.linalg.LinAlgError
        lower = np.linalg.cholesky(batch)  # raises unless every matrix is positive definite
    except np.linalg.LinAlgError:
        semidefinite = semidefinite and not covariance
        eigenvalues, vectors = np.linalg.eigh(np.where(finite[:, None, None], batch, 0.0))
        rounding = 1e-9 * np.abs(eigenvalues).max(axis=1, initial=0.0)
        lowest = eigenvalues[:, 0]
        bad = ~symmetric | ((lowest < -rounding) if semidefinite else (lowest <= 0))
        if np.any(bad) or not semidefinite:
            first = int(np.argmax(bad))
            kind = "semi-definite" if semidefinite else "definite"
            raise ValueError(
                f"{what} {first} is not symmetric positive {kind} (eigenvalues "
                f"{np.array2string(eigenvalues[first], precision=3)})."
            ) from None
        kept = np.where(eigenvalues > rounding[:, None], eigenvalues, 0.0)
        return (np.sqrt(kept)[:, :, None] * np.swapaxes(vectors, 1, 2)).reshape(matrix.shape)
    root = np.linalg.inv(lower) if covariance else np.swapaxes(lower, 1, 2)
    return root.reshape(matrix.shape)


# forward mode for the blocks while the arguments' tangents have at most this many coordinates
# per residual entry: vmapped over thousands of instances, forward mode's extra directions cost
# less than reverse mode's transposed program (a 2D between factor, 6 tangent coordinates for 3
# residuals, 10k instances: XLA CPU compiled the linearization in 1.8 s instead of 2.7 s, 28
# kernels instead of 43, and it ran in 10 ms instead of 15 ms)
_FORWARD_RATIO = 2


def linearize_one(factor, xs, data):
    """`(residual (k,), blocks)` for one instance: `blocks` a tuple of `(k, tangent_dim)`
    (`lieax.value_and_jacobian`, forward mode unless the tangents outnumber the residual
    entries by more than `_FORWARD_RATIO`)."""
    extra = () if factor.data is None else (data,)
    if factor.jacobian_fn is not None:
        value, blocks = factor.jacobian_fn(*xs, *extra)
        return value, tuple(blocks)
    argnums = tuple(range(len(xs)))
    residual_size = factor.residual_size
    if residual_size is None:
        shapes = jax.tree_util.tree_leaves(jax.eval_shape(factor.residual, *xs, *extra))
        residual_size = sum(math.prod(leaf.shape) for leaf in shapes)
    tangent_size = sum(v.tangent_dim for v in factor.vars)
    mode = "fwd" if tangent_size <= _FORWARD_RATIO * residual_size else "rev"
    value, jac = value_and_jacobian(factor.residual, argnums, mode=mode)(*xs, *extra)
    k = value.shape[0]
    blocks = tuple(
        jnp.concatenate([jnp.reshape(b, (k, -1)) for b in jax.tree_util.tree_leaves(j)], axis=1)
        for j in jac
    )
    return value, blocks


def residual_one(factor, xs, data):
    extra = () if factor.data is None else (data,)
    return factor.residual(*xs, *extra)
