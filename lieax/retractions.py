r"""Retractions: ways to move a point $X$ along a tangent $\delta$ other than $X\,\mathrm{Exp}(\delta)$.

A retraction $\mathcal{R}_X(\delta)$ agrees with the exponential map to first order,
$\mathcal{R}_X(\delta) = X\,\mathrm{Exp}(\delta + O(|\delta|^2))$ (GTSAM math notes, Sec. 6.1):
its derivative at $\delta = 0$ is the identity, so Jacobians and gradients in tangent coordinates,
and the points where a solver stops (zero gradient), are the same whichever retraction moves the
state; only the path to them changes, and a step may cost less. Each retraction here comes with
its inverse (local coordinates), `rminus(Y, X)` $= \mathcal{R}_X^{-1}(Y)$, so that
`rplus(X, rminus(Y, X)) == Y` where the inverse is defined.

| retraction | SO3 | SE3 | other groups, manifolds, arrays |
|---|---|---|---|
| `exp` | $R\,\mathrm{Exp}(\omega)$ | $T\,\mathrm{Exp}(v, \omega)$ | $X \oplus \delta$, $x + \delta$ |
| `cayley` | $R\,\mathrm{cay}(\omega)$ | $(R\,\mathrm{cay}(\omega),\ t + R v)$ | as `exp` |
| `first_order` | $R\,\mathrm{Exp}(\omega)$ | $(R\,\mathrm{Exp}(\omega),\ t + R v)$ | as `exp` |

with the Cayley transform
$\mathrm{cay}(\omega) = (I - \tfrac12[\omega]_\times)^{-1}(I + \tfrac12[\omega]_\times)$,
a rotation by $2\arctan(|\omega|/2)$ about $\omega$ (GTSAM math notes Sec. 12.4,
$R\,\mathcal{C}(-\tfrac12[\omega]_\times)$; GTSAM's `Rot3::CayleyChart`, the default `Rot3`
retraction when GTSAM is built with rotation matrices). The SE3 retractions move the translation
along the body-frame $v$ in a straight line, $t + R v$ instead of $t + R\,W(\omega) v$ (notes
Sec. 13.6, Example 13; `cayley` is GTSAM's `Pose3::ChartAtOrigin` without
`GTSAM_POSE3_EXPMAP`). Tangents keep lieax's order $(v, \omega)$, translation first.

Use them in `lieax.rplus` / `lieax.rminus`, `lieax.lstsq.least_squares` and `lieax.optax` with
`retraction=lieax.retractions.cayley`. They work under `jit`, `vmap` and every differentiation
mode: the Cayley kernels carry closed-form `custom_jvp` rules like the group kernels.

Conventions: docs/conventions.md.
"""

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from ._checks import check_last_axis
from .groups import SE3, SO3, AbstractManifold, kernels

__all__ = ["Retraction", "cayley", "exp", "first_order"]


@dataclasses.dataclass(frozen=True)
class Retraction:
    r"""A retraction and its inverse, each acting on one manifold element (a group or `S2` batch)
    or one array; `lieax.rplus(tree, tangents, retraction=...)` and `lieax.rminus` apply them leaf
    by leaf to pytrees. Hashable, so solvers take it as a static argument.

    **Fields:**

    - `name`: a short name (`"exp"`, `"cayley"`, `"first_order"`).
    - `rplus`: `rplus(x, delta)` $= \mathcal{R}_x(\delta)$, `delta` of shape
      `(*batch, tangent_dim)` for a manifold element, `x.shape` for an array.
    - `rminus`: `rminus(y, x)` $= \mathcal{R}_x^{-1}(y)$, so that `rplus(x, rminus(y, x)) == y`.
    """

    name: str
    # (x: a manifold element or an array, delta) -> the moved x, of x's type
    rplus: Callable[[Any, Any], Any]
    # (y, x) -> the tangent array
    rminus: Callable[[Any, Any], jax.Array]

    def __repr__(self) -> str:
        return f"lieax.retractions.{self.name}"


# ---- the exponential map (the default) ----------------------------------------------------------


def _exp_rplus(x, delta):
    r"""$X \oplus \delta = X\,\mathrm{Exp}(\delta)$ (the manifold's own `rplus`), `x + δ` for arrays."""
    return x.rplus(delta) if isinstance(x, AbstractManifold) else x + delta


def _exp_rminus(y, x):
    r"""$Y \ominus X = \mathrm{Log}(X^{-1} Y)$ (the manifold's own `rminus`), `y - x` for arrays."""
    return y.rminus(x) if isinstance(y, AbstractManifold) else y - x


exp = Retraction("exp", _exp_rplus, _exp_rminus)  # the default everywhere


# ---- SO3 and SE3 --------------------------------------------------------------------------------


def _so3_cayley_rplus(x, omega):
    r"""$R\,\mathrm{cay}(\omega)$."""
    omega = check_last_axis(omega, 3, "SO3 tangent")
    return x.compose(kernels.element(SO3, kernels.so3_cayley(omega)))


def _so3_cayley_rminus(y, x):
    r"""$\mathrm{cay}^{-1}(R_x^\top R_y)$."""
    x._check_same_group(y, "rminus")
    return kernels.so3_cayley_inverse(kernels.carrier(x.between(y)))


def _se3_increment(rotation_q, v):
    """The SE3 element $(Q, v)$ from a quaternion kernel output and a translation."""
    return kernels.element(SE3, kernels.se3_join(rotation_q, v))


def _se3_rplus(rotation_kernel):
    def rplus(x, delta):
        r"""$(R\,Q(\omega),\ t + R v) = T \cdot (Q(\omega), v)$."""
        delta = check_last_axis(delta, 6, "SE3 tangent")
        return x.compose(_se3_increment(rotation_kernel(delta[..., 3:]), delta[..., :3]))

    return rplus


def _se3_rminus(rotation_inverse):
    def rminus(y, x):
        r"""$(v, \omega)$ with $T_x^{-1} T_y = (Q(\omega), v)$."""
        x._check_same_group(y, "rminus")
        relative = x.between(y)
        omega = rotation_inverse(relative.rotation())
        return jnp.concatenate([relative.translation(), omega], axis=-1)

    return rminus


def _dispatch(name, rules) -> Retraction:
    """A `Retraction` using `rules[type(x)]` for the listed groups and `exp` for anything else."""

    def rplus(x, delta):
        rule = rules.get(type(x))
        return _exp_rplus(x, delta) if rule is None else rule[0](x, delta)

    def rminus(y, x):
        rule = rules.get(type(y))
        return _exp_rminus(y, x) if rule is None else rule[1](y, x)

    rplus.__doc__ = f"The `{name}` retraction of one element or array (see `lieax.retractions`)."
    rminus.__doc__ = f"The inverse of the `{name}` retraction (see `lieax.retractions`)."
    return Retraction(name, rplus, rminus)


cayley = _dispatch(
    "cayley",
    {
        SO3: (_so3_cayley_rplus, _so3_cayley_rminus),
        SE3: (
            _se3_rplus(kernels.so3_cayley),
            _se3_rminus(lambda rotation: kernels.so3_cayley_inverse(kernels.carrier(rotation))),
        ),
    },
)

first_order = _dispatch(
    "first_order",
    {SE3: (_se3_rplus(kernels.so3_exp), _se3_rminus(lambda rotation: rotation.log()))},
)
