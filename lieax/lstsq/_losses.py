r"""Robust losses $\rho(s)$ of the squared norm $s = \|r_i\|^2$ of one residual block.

The cost of a problem is $\tfrac12 \sum_i \rho(\|r_i\|^2)$. Every loss here has
$\rho(s) \approx s$ near zero ($\rho'(0) = 1$), so inliers cost what they cost without a loss,
and a `scale` $c$: the residual norm where the loss starts to discount a block. The solvers apply
a loss by reweighting (iteratively reweighted least squares): block $i$ enters the normal
equations with the weight $w_i = \rho'(s_i)$, $J^\top W J\,\delta = -J^\top W r$, whose right
side is the exact gradient of the robust cost (Triggs et al., "Bundle adjustment: a modern
synthesis", Sec. 3.3; Ceres' `LossFunction` without its second-order correction). Near a
solution this converges linearly, at a rate set by how much the loss bends.

Losses are pytrees whose one leaf is `scale`: it may be traced, batched under `vmap` and
differentiated (implicit derivatives of a solution include the loss's scale). A concrete scale
(a Python number or an array) must be positive and finite, or the constructor raises
`ValueError`; a traced one cannot be checked when it is traced, so a loss whose scale is not
positive and finite evaluates to NaN (value and weight), and a solve that uses it ends
`Status.NONFINITE` at its start instead of minimizing another loss than the one asked for.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike


class AbstractLoss:
    r"""A robust loss with a positive `scale` $c$; subclasses give $\rho(s)$ and $\rho'(s)$ (each
    passed through `_checked`, so that a traced scale that is not positive gives NaN)."""

    scale: ArrayLike  # a positive number, or a traced array
    __slots__ = ("scale",)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        jax.tree_util.register_pytree_node(
            cls, lambda loss: ((loss.scale,), None), lambda _, leaves: cls._unchecked(leaves[0])
        )

    def __init__(self, scale: ArrayLike = 1.0) -> None:
        if not isinstance(scale, jax.core.Tracer):
            value = np.asarray(scale)
            if not np.issubdtype(value.dtype, np.number) or np.iscomplexobj(value):
                raise TypeError(
                    f"{type(self).__name__} scale must be a real number, got {scale!r}."
                )
            if not (np.all(np.isfinite(value)) and np.all(value > 0)):
                raise ValueError(
                    f"{type(self).__name__} scale must be positive and finite, got {scale!r}."
                )
        object.__setattr__(self, "scale", scale)

    @classmethod
    def _unchecked(cls, scale):
        """A loss rebuilt from a pytree leaf, unchecked: JAX's transformations fill the leaf with
        cotangents, zeros, shapes or sentinels that are no scale."""
        loss = object.__new__(cls)
        object.__setattr__(loss, "scale", scale)
        return loss

    def _checked(self, value):
        """`value` where the scale is positive and finite, NaN elsewhere (a traced scale is
        checked here, at run time; a Python number was checked by the constructor)."""
        if isinstance(self.scale, (int, float)):
            return value
        valid = jnp.all(jnp.isfinite(self.scale) & (jnp.asarray(self.scale) > 0))
        return jnp.where(valid, value, jnp.nan)

    def __setattr__(self, name, value):
        raise AttributeError(f"{type(self).__name__} is immutable.")

    def __repr__(self):
        return f"{type(self).__name__}(scale={self.scale!r})"

    def __call__(self, s: jax.Array) -> jax.Array:
        r"""$\rho(s)$ for squared norms `s`."""
        raise NotImplementedError

    def weight(self, s: jax.Array) -> jax.Array:
        r"""$\rho'(s)$, the weight of a block in the normal equations."""
        raise NotImplementedError


class Huber(AbstractLoss):
    r"""$\rho(s) = s$ for $s \le c^2$, $2c\sqrt s - c^2$ beyond: quadratic, then linear in
    $\|r\|$. Weight $\min(1, c/\|r\|)$. Convex: it bounds the influence of outliers without
    rejecting them."""

    def __call__(self, s: jax.Array) -> jax.Array:
        c2 = self.scale**2
        inside = s <= c2
        safe_s = jnp.where(inside, c2, s)
        return self._checked(jnp.where(inside, s, 2.0 * self.scale * jnp.sqrt(safe_s) - c2))

    def weight(self, s: jax.Array) -> jax.Array:
        inside = s <= self.scale**2
        safe_s = jnp.where(inside, self.scale**2, s)
        return self._checked(jnp.where(inside, jnp.ones_like(s), self.scale / jnp.sqrt(safe_s)))


class Cauchy(AbstractLoss):
    r"""$\rho(s) = c^2 \log(1 + s/c^2)$, weight $1 / (1 + s/c^2)$: the influence of a residual
    decays like $1/\|r\|$ (Lorentzian)."""

    def __call__(self, s: jax.Array) -> jax.Array:
        c2 = self.scale**2
        return self._checked(c2 * jnp.log1p(s / c2))

    def weight(self, s: jax.Array) -> jax.Array:
        return self._checked(1.0 / (1.0 + s / self.scale**2))


class Tukey(AbstractLoss):
    r"""Tukey's biweight: $\rho(s) = \tfrac{c^2}{3}\,(1 - (1 - s/c^2)^3)$ for $s \le c^2$ and
    $c^2/3$ beyond; weight $(1 - s/c^2)^2$, zero beyond $c$: outliers are rejected outright.
    Not convex: start near the answer (a block beyond $c$ everywhere pulls on nothing)."""

    def __call__(self, s: jax.Array) -> jax.Array:
        c2 = self.scale**2
        u = jnp.minimum(s / c2, 1.0)
        # c²/3 (1 - (1 - u)³) without cancellation
        return self._checked(c2 * u * (1.0 - u + u**2 / 3.0))

    def weight(self, s: jax.Array) -> jax.Array:
        u = jnp.minimum(s / self.scale**2, 1.0)
        return self._checked((1.0 - u) ** 2)


class GemanMcClure(AbstractLoss):
    r"""$\rho(s) = c^2 s / (c^2 + s)$, weight $c^4 / (c^2 + s)^2$: bounded like Tukey's and
    smooth everywhere (Geman and McClure 1987; Black and Rangarajan 1996). Not convex."""

    def __call__(self, s: jax.Array) -> jax.Array:
        c2 = self.scale**2
        return self._checked(c2 * s / (c2 + s))

    def weight(self, s: jax.Array) -> jax.Array:
        c2 = self.scale**2
        return self._checked((c2 / (c2 + s)) ** 2)
