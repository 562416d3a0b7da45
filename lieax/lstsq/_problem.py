r"""The residual specification: how a residual pytree, a loss and a state become a cost and the
normal equations in tangent coordinates.

`residual_fn(x, args)` returns an array or a pytree of arrays. A leaf of shape `(*batch, k)` with
two or more axes is a batch of `k`-dimensional residual blocks (one per data element, as
`jax.vmap` over the data produces them); a leaf with one axis or none is a batch of scalar
blocks. A robust loss acts on each block's squared norm $s_i = \|r_i\|^2$, and the cost is
$\tfrac12 \sum_i \rho(s_i)$ ($\rho(s) = s$ without a loss).

`loss` is `None`, one loss for every leaf, or a pytree prefix of the residual with a loss or
`None` at each of its leaves (e.g. `(Huber(0.1), None)` for `(data_residuals, prior_residual)`).
"""

import math

import jax
import jax.numpy as jnp

from ..autodiff._jacobian import value_and_jacobian
from ..autodiff._tangents import manifold_leaves
from ..groups import AbstractManifold
from ._losses import AbstractLoss
from ._normal_equations import normal_equations


def _is_loss_leaf(node) -> bool:
    return node is None or isinstance(node, AbstractLoss)


def residual_leaves(residuals) -> list:
    """The residual's array leaves, checked: floating arrays only, no group elements."""
    with_paths, _ = jax.tree_util.tree_flatten_with_path(
        residuals, is_leaf=lambda node: isinstance(node, AbstractManifold)
    )
    leaves = []
    for path, leaf in with_paths:
        where = f"residual_fn(x, args){jax.tree_util.keystr(path)}"
        if isinstance(leaf, AbstractManifold):
            raise TypeError(
                f"{where} is a {type(leaf).__name__}; residuals must be arrays (for an error "
                "between group elements return a tangent, e.g. `lieax.rminus(X, Y)` or `.log()`)."
            )
        leaf = jnp.asarray(leaf)
        if not jnp.issubdtype(leaf.dtype, jnp.floating):
            raise TypeError(f"{where} has dtype {leaf.dtype}; residuals must be floating arrays.")
        leaves.append(leaf)
    if not leaves:
        raise ValueError("residual_fn(x, args) returned no residuals.")
    return leaves


def losses_per_leaf(loss, residuals) -> list:
    """The loss (or `None`) of each residual leaf, broadcasting `loss` as a pytree prefix."""
    leaves = residual_leaves(residuals)
    if _is_loss_leaf(loss):
        return [loss] * len(leaves)
    loss_leaves, loss_def = jax.tree_util.tree_flatten(loss, is_leaf=_is_loss_leaf)
    for leaf in loss_leaves:
        if not _is_loss_leaf(leaf):
            raise TypeError(f"loss must hold lieax.lstsq losses or None, got {leaf!r}.")
    try:
        subtrees = loss_def.flatten_up_to(residuals)
    except ValueError as error:
        raise ValueError(
            "loss must be one loss, None, or a pytree prefix of the residual with a loss or None "
            f"at each leaf: {error}"
        ) from None
    return [
        leaf_loss
        for leaf_loss, subtree in zip(loss_leaves, subtrees)
        for _ in jax.tree_util.tree_leaves(subtree)
    ]


def _block_squared_norms(leaf):
    return jnp.sum(leaf**2, axis=-1) if leaf.ndim >= 2 else leaf**2


def cost(residuals, loss) -> jax.Array:
    r"""$\tfrac12 \sum_i \rho(\|r_i\|^2)$ over every block of every residual leaf."""
    total = 0.0
    for leaf, leaf_loss in zip(residual_leaves(residuals), losses_per_leaf(loss, residuals)):
        squared = _block_squared_norms(leaf)
        total = total + jnp.sum(squared if leaf_loss is None else leaf_loss(squared))
    return 0.5 * total


def _leaf_row_weights(leaf, leaf_loss):
    r"""$\rho'(s_i)$ repeated over each block's rows of one residual leaf, raveled like it;
    `None` without a loss."""
    if leaf_loss is None:
        return None
    weight = leaf_loss.weight(_block_squared_norms(leaf))
    if leaf.ndim >= 2:
        weight = jnp.broadcast_to(weight[..., None], leaf.shape)
    return jnp.ravel(weight).astype(leaf.dtype)


def linearize(residual_fn, x, args, loss):
    r"""At `x`: the cost, $H = J^\top W J$ and $g = J^\top W r$ in flattened tangent coordinates
    (layout of `lieax.flatten_tangents`), with $W$ the loss's weights. The Jacobian comes from
    `lieax.value_and_jacobian` (forward mode when there are more residuals than unknowns).

    $H$ and $g$ are sums over the residual leaves, $\sum_\ell J_\ell^\top W_\ell J_\ell$, each
    leaf's rows reduced on their own: no Jacobian of all residuals is ever assembled, so a leaf
    split over devices along its rows (`lieax.sharding.shard_residuals`) is reduced where it
    lies and summed by one all-reduce."""
    residuals, jac_tree = value_and_jacobian(lambda state: residual_fn(state, args))(x)
    leaves = residual_leaves(residuals)
    losses = losses_per_leaf(loss, residuals)
    state_leaves, _ = manifold_leaves(x, "x")
    blocks = jax.tree_util.tree_leaves(jac_tree)
    hessian = gradient = 0.0
    for i, (leaf, leaf_loss) in enumerate(zip(leaves, losses)):
        row_blocks = blocks[i * len(state_leaves) : (i + 1) * len(state_leaves)]
        jac = jnp.concatenate(
            [
                jnp.reshape(block, (leaf.size, math.prod(block.shape[leaf.ndim :])))
                for block in row_blocks
            ],
            axis=1,
        )
        leaf_hessian, leaf_gradient = normal_equations(
            jac, jnp.ravel(leaf), _leaf_row_weights(leaf, leaf_loss)
        )
        hessian, gradient = hessian + leaf_hessian, gradient + leaf_gradient
    return cost(residuals, loss), hessian, gradient
