r"""Tangent spaces of pytrees that mix groups and arrays.

A pytree's manifold is the product of its leaves': a group leaf contributes its tangent space
(shape `(*batch, tangent_dim)`), a floating array leaf its own shape (for arrays $\oplus$ is $+$).
`rplus`, `rminus`, `zero_tangents`, `tangent_dim` and `flatten_tangents` / `unflatten_tangents`
act leaf by leaf; the solvers and `lieax.jacobian` are built on them.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_not_foreign, foreign_conversion, to_device
from .._typing import PyTree
from ..groups import AbstractManifold, kernels
from ..retractions import Retraction, exp


def _is_leaf(x) -> bool:
    return isinstance(x, AbstractManifold) or x is None or foreign_conversion(x) is not None


def manifold_leaves(tree, what: str = "argument"):
    """The leaves of `tree` (groups count as leaves) and its structure, every leaf checked:
    groups and floating arrays are accepted; anything else raises a `TypeError` naming its path."""
    with_paths, treedef = jax.tree_util.tree_flatten_with_path(tree, is_leaf=_is_leaf)
    leaves = []
    for path, leaf in with_paths:
        where = f"{what}{jax.tree_util.keystr(path)}"
        if leaf is None:
            raise TypeError(f"{where} is None; lieax differentiates groups and float arrays only.")
        check_not_foreign(leaf, where)
        if not isinstance(leaf, AbstractManifold):
            dtype = getattr(leaf, "dtype", None) or jnp.asarray(leaf).dtype
            if not jnp.issubdtype(dtype, jnp.floating):
                raise TypeError(
                    f"{where} has dtype {dtype}; lieax differentiates groups and float arrays "
                    "only (pass integer data through a non-differentiated argument)."
                )
            # a host array is transferred (`jnp.asarray` would compile a conversion)
            leaf = to_device(leaf) if isinstance(leaf, np.ndarray) else jnp.asarray(leaf)
        leaves.append(leaf)
    return leaves, treedef


def leaf_tangent_shape(leaf) -> tuple:
    if isinstance(leaf, AbstractManifold):
        return (*leaf.batch_shape, leaf.tangent_dim)
    return tuple(jnp.shape(leaf))


def leaf_local_from_tangent(leaf, tangent):
    """Right-local tangent of the JAX tangent of `leaf_array(leaf)` (see `AbstractGroup`)."""
    if isinstance(leaf, AbstractManifold):
        return leaf._local_from_tangent(kernels.carrier(leaf), tangent)
    return tangent


def leaf_tangent_from_local(leaf, local):
    """The JAX tangent of `leaf_array(leaf)` that moves `leaf` along a right-local tangent."""
    if isinstance(leaf, AbstractManifold):
        return leaf._tangent_from_local(kernels.carrier(leaf), local)
    return local


def leaf_array(leaf):
    """The array that carries a leaf's derivatives: a group's parameter leaf, or the array."""
    return kernels.carrier(leaf) if isinstance(leaf, AbstractManifold) else leaf


def check_retraction(retraction) -> Retraction:
    """`retraction`, or a `TypeError` saying what is expected."""
    if not isinstance(retraction, Retraction):
        raise TypeError(
            "retraction must be a lieax.retractions.Retraction (lieax.retractions.exp, cayley or "
            f"first_order), got {retraction!r}."
        )
    return retraction


def rplus(tree: PyTree, tangents: PyTree, retraction: Retraction = exp) -> PyTree:
    r"""$X \oplus \delta$ leaf by leaf: `X.rplus(δ)` for groups, `x + δ` for arrays; with a
    `retraction` from `lieax.retractions` (e.g. `cayley`), $\mathcal{R}_X(\delta)$ instead."""
    retract = check_retraction(retraction).rplus
    leaves, treedef = manifold_leaves(tree, "tree")
    deltas = treedef.flatten_up_to(tangents)
    return treedef.unflatten([retract(leaf, d) for leaf, d in zip(leaves, deltas)])


def rminus(tree_a: PyTree, tree_b: PyTree, retraction: Retraction = exp) -> PyTree:
    r"""$A \ominus B$ leaf by leaf (`a.rminus(b)` for groups, `a - b` for arrays), so that
    `rplus(tree_b, rminus(tree_a, tree_b)) == tree_a`; with a `retraction`, its inverse
    $\mathcal{R}_B^{-1}(A)$ (the same identity holds with the same `retraction` in `rplus`)."""
    local = check_retraction(retraction).rminus
    leaves_a, treedef = manifold_leaves(tree_a, "tree_a")
    leaves_b = treedef.flatten_up_to(tree_b)
    return treedef.unflatten([local(a, b) for a, b in zip(leaves_a, leaves_b)])


def zero_tangents(tree: PyTree) -> PyTree:
    """Zero tangents shaped like `tree`'s tangent space (groups become `(*batch, tangent_dim)`)."""
    leaves, treedef = manifold_leaves(tree, "tree")
    return treedef.unflatten(
        [jnp.zeros(leaf_tangent_shape(leaf), dtype=leaf_array(leaf).dtype) for leaf in leaves]
    )


def tangent_dim(tree: PyTree) -> int:
    """The total number of tangent coordinates of `tree`."""
    leaves, _ = manifold_leaves(tree, "tree")
    return sum(math.prod(leaf_tangent_shape(leaf)) for leaf in leaves)


def flatten_tangents(tangents: PyTree) -> jax.Array:
    """One vector of all tangent coordinates, leaves in pytree order, each raveled row-major."""
    leaves = jax.tree_util.tree_leaves(tangents)
    if not leaves:
        return jnp.zeros((0,))
    return jnp.concatenate([jnp.ravel(t) for t in leaves])


def unflatten_tangents(tree: PyTree, vector: jax.Array | np.ndarray) -> PyTree:
    """Tangents of `tree` from one vector laid out as `flatten_tangents` lays it out."""
    leaves, treedef = manifold_leaves(tree, "tree")
    shapes = [leaf_tangent_shape(leaf) for leaf in leaves]
    total = sum(math.prod(shape) for shape in shapes)
    if vector.shape[-1] != total:
        raise ValueError(
            f"unflatten_tangents: expected a vector of {total} entries, got {vector.shape}."
        )
    pieces, start = [], 0
    for shape in shapes:
        size = math.prod(shape)
        pieces.append(jnp.reshape(vector[start : start + size], shape))
        start += size
    return treedef.unflatten(pieces)
