r"""First-order optimization on manifolds with any optax optimizer.

Gradients are taken in right-local tangent coordinates (`lieax.grad`: group leaves get
$\nabla_\delta f(X \oplus \delta)|_{\delta = 0}$, shape `(*batch, tangent_dim)`), the optimizer
turns them into tangent updates, and the updates are applied by retraction,
$X \leftarrow X \oplus u$ (`x + u` for array leaves), or by another retraction from
`lieax.retractions` (`retraction=lieax.retractions.cayley`: the gradients are the same, since every
retraction's derivative at zero is the identity; pass the same one to `on_manifold` and
`apply_updates`).

The wrapped optimizer works in the chart centered at the current point: its `params` are the
array leaves as they are and zero tangents for the group leaves, so transformations that read
`params` (weight decay, line searches) act on arrays as usual and see each group element at the
origin of its chart. Optimizer state (momenta, second moments) is kept in the body-frame
coordinates of the right perturbation and carried from one point to the next unchanged, which
identifies the tangent spaces by left translation (exact for arrays; the usual first-order
approximation for groups, as in Riemannian Adam without vector transport).

Use `minimize` for a whole run compiled as one `lax.scan`, or `on_manifold` + `apply_updates` in
your own loop:
```python
optimizer = lieax.optax.on_manifold(optax.adam(1e-2))
state = optimizer.init(x)
for _ in range(steps):
    value, grad = lieax.value_and_grad(loss)(x)
    updates, state = optimizer.update(grad, state, x)
    x = lieax.optax.apply_updates(x, updates)
```
"""

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax  # the optax package (absolute import; this module is lieax.optax)
from jax.typing import ArrayLike

from ._typing import PyTree
from .autodiff._jacobian import value_and_grad
from .autodiff._tangents import check_retraction, manifold_leaves, rplus, zero_tangents
from .groups import AbstractManifold
from .retractions import Retraction, exp

__all__ = ["MinimizeResult", "apply_updates", "minimize", "on_manifold"]


def _chart_params(params):
    """`params` in the chart centered at themselves: arrays as they are, groups as zero tangents."""
    leaves, treedef = manifold_leaves(params, "params")
    return treedef.unflatten(
        [
            jnp.zeros((*leaf.batch_shape, leaf.tangent_dim), leaf.dtype)
            if isinstance(leaf, AbstractManifold)
            else leaf
            for leaf in leaves
        ]
    )


def _from_chart(params, chart, retraction: Retraction):
    r"""The point of chart coordinates `chart` around `params`: $\mathcal{R}_X(u)$ for groups
    ($X \oplus u$ by default), `u` for arrays (whose chart coordinates are their values)."""
    leaves, treedef = manifold_leaves(params, "params")
    coordinates = treedef.flatten_up_to(chart)
    return treedef.unflatten(
        [
            retraction.rplus(leaf, u) if isinstance(leaf, AbstractManifold) else u
            for leaf, u in zip(leaves, coordinates)
        ]
    )


def on_manifold(
    optimizer: optax.GradientTransformation, *, retraction: Retraction = exp
) -> optax.GradientTransformationExtraArgs:
    """Wraps an optax optimizer to act on pytrees of lieax groups and arrays.

    **Arguments:**

    - `optimizer`: any `optax.GradientTransformation` (`optax.adam(1e-2)`, a `chain`, ...).
    - `retraction`: the chart a `value_fn` is re-expressed in (`lieax.retractions.exp` by
      default); use the same one in `apply_updates`.

    **Returns:** a `GradientTransformationExtraArgs` whose `init(params)` takes the manifold
    point and whose `update(grads, state, params, **extra)` takes tangent-space gradients (from
    `lieax.grad`) and returns tangent updates, to be applied with `apply_updates`. A `value_fn`
    passed as an extra argument (line searches, e.g. `optax.lbfgs`) is called on manifold points
    (it is re-expressed in the chart at `params`).
    """
    inner = optax.with_extra_args_support(optimizer)
    retraction = check_retraction(retraction)

    def init(params):
        return inner.init(zero_tangents(params))

    def update(updates, state, params=None, **extra_args):
        if params is None:
            return inner.update(updates, state, None, **extra_args)
        if "value_fn" in extra_args:
            value_fn = extra_args["value_fn"]
            extra_args["value_fn"] = lambda chart, **kw: value_fn(
                _from_chart(params, chart, retraction), **kw
            )
        return inner.update(updates, state, _chart_params(params), **extra_args)

    return optax.GradientTransformationExtraArgs(init, update)


def apply_updates(params: PyTree, updates: PyTree, *, retraction: Retraction = exp) -> PyTree:
    r"""$X \oplus u$ leaf by leaf (the manifold version of `optax.apply_updates`), or
    $\mathcal{R}_X(u)$ with another `retraction` from `lieax.retractions`; updates are cast to
    each leaf's dtype."""
    leaves, treedef = manifold_leaves(params, "params")
    cast = [
        jnp.asarray(u).astype(leaf.dtype) for leaf, u in zip(leaves, treedef.flatten_up_to(updates))
    ]
    return rplus(params, treedef.unflatten(cast), retraction)


class MinimizeResult(NamedTuple):
    """The result of `minimize`: the final point `value`, its `loss`, and `loss_history` of shape
    `(steps + 1,)` (the loss at every iterate, the start first)."""

    value: PyTree
    loss: jax.Array
    loss_history: jax.Array


def minimize(
    loss: Callable[[PyTree, PyTree], ArrayLike],
    x0: PyTree,
    optimizer: optax.GradientTransformation,
    steps: int,
    args: PyTree = None,
    *,
    retraction: Retraction = exp,
) -> MinimizeResult:
    """Runs `steps` iterations of `optimizer` on `loss(x, args)` from `x0`, compiled as one
    `lax.scan`.

    **Arguments:**

    - `loss`: `loss(x, args)` returns a scalar; `x` is a pytree of lieax groups and arrays.
    - `x0`: the start.
    - `optimizer`: an optax optimizer (wrapped with `on_manifold` here; do not wrap it yourself).
    - `steps`: the number of updates.
    - `args`: data passed to `loss`.
    - `retraction`: how updates move the point (`lieax.retractions.exp` by default, or `cayley`,
      `first_order`).

    **Returns:** a `MinimizeResult`. Compiled once per `(loss, optimizer, steps,
    retraction)`: build the optimizer once and reuse it to reuse the compilation.
    """
    if not isinstance(steps, int) or steps < 0:
        raise ValueError(f"steps must be a non-negative int, got {steps!r}.")
    return _minimize(loss, optimizer, steps, check_retraction(retraction), x0, args)


@jax.jit(static_argnums=(0, 1, 2, 3))
def _minimize(loss, optimizer, steps, retraction, x0, args):
    transformation = on_manifold(optimizer, retraction=retraction)
    value_and_gradient = value_and_grad(loss)

    def step(carry, _):
        x, state = carry
        value, gradient = value_and_gradient(x, args)
        updates, state = transformation.update(
            gradient, state, x, value=value, grad=gradient, value_fn=lambda y: loss(y, args)
        )
        return (apply_updates(x, updates, retraction=retraction), state), value

    (x, _), history = jax.lax.scan(step, (x0, transformation.init(x0)), None, length=steps)
    final = loss(x, args)
    return MinimizeResult(value=x, loss=final, loss_history=jnp.append(history, final))
