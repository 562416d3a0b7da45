r"""Variable kinds: many instances of one group, array or small pytree of them, stored batched.

A `Var` holds the initial values of all its instances as one batched value (a group batched
`(n,)`, an array `(n, ...)`, or a pytree of those with the same leading `n`); factors refer to
instances by integer index arrays, `poses[i]`. Each instance has a tangent of `tangent_dim`
coordinates (the product of its leaves' tangents, right perturbation $X \oplus \delta$; see the
docs/conventions.md). Instances listed in `fixed` are held constant (GTSAM's "constant
values", Ceres' `SetParameterBlockConstant`); priors are ordinary unary factors.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..autodiff._tangents import leaf_array, leaf_tangent_shape, manifold_leaves


class Var:
    """One variable kind: `n` instances of the same type, batched along a leading axis.

    **Arguments:**

    - `value`: the initial values, a lieax group batched `(n,)` (e.g. `SE2` of parameters
      `(n, 4)`), a float array `(n, ...)`, or a pytree of such with one leading `n`.
    - `fixed`: indices (or a boolean mask `(n,)`) of instances held constant.
    - `name`: used in error messages and the verbose table (default `"var<k>"`).

    `var[index]` refers to instances (an integer array, one per factor instance) when a `Factor`
    is made.
    """

    def __init__(self, value, *, fixed=None, name=None):
        leaves, treedef = manifold_leaves(value, f"Var {name!r} value")
        sizes = {_leading(leaf) for leaf in leaves}
        if len(sizes) != 1 or None in sizes:
            raise ValueError(
                f"Var {name!r}: every leaf must have the same leading (instance) axis, got "
                f"shapes {[tuple(jnp.shape(leaf_array(x))) for x in leaves]}."
            )
        self.value = value
        self.name = name
        self.count = sizes.pop()
        self.treedef = treedef
        self.leaf_dims = tuple(math.prod(leaf_tangent_shape(x)[1:]) for x in leaves)
        self.tangent_dim = sum(self.leaf_dims)
        self.fixed = _fixed_indices(fixed, self.count, name)
        for leaf in leaves:
            array = leaf_array(leaf)
            if not isinstance(array, jax.core.Tracer) and not np.all(np.isfinite(array)):
                bad = np.flatnonzero(~np.all(np.isfinite(np.reshape(array, (self.count, -1))), 1))
                raise ValueError(f"Var {name!r}: instance {bad[0]} has non-finite values.")

    def __getitem__(self, index):
        return VarRef(self, index)

    def __repr__(self):
        return f"Var({self.name!r}, count={self.count}, tangent_dim={self.tangent_dim})"


class VarRef:
    """Instances `index` of the variable kind `var`, one per factor instance: what `var[index]`
    returns and `Factor` takes for each argument of its residual.

    **Attributes:** `var` (the `Var`) and `index` (the instances, an integer array with one entry
    per factor instance, as given). A function that builds a factor from such references (e.g.
    `lieax.graph.bearing_range_factor`) reads the variable's kind from `ref.var.value` and checks
    its arguments with `isinstance(ref, VarRef)`.
    """

    def __init__(self, var, index):
        self.var = var
        self.index = index


def _leading(leaf):
    shape = leaf_tangent_shape(leaf)
    return shape[0] if len(shape) else None


def _fixed_indices(fixed, count, name):
    if fixed is None:
        return np.zeros(0, np.int64)
    fixed = np.asarray(fixed)
    if fixed.dtype == bool:
        if fixed.shape != (count,):
            raise ValueError(f"Var {name!r}: a fixed mask must have shape ({count},).")
        return np.flatnonzero(fixed)
    if not np.issubdtype(fixed.dtype, np.integer):
        raise ValueError(f"Var {name!r}: fixed must be integer indices or a boolean mask.")
    fixed = fixed.reshape(-1).astype(np.int64)
    if np.any((fixed < 0) | (fixed >= count)):
        bad = fixed[(fixed < 0) | (fixed >= count)][0]
        raise ValueError(f"Var {name!r}: fixed index {bad} is out of range for {count} instances.")
    return np.unique(fixed)


def instance(value, index):
    """The instances `index` of a batched value (groups are indexed as groups)."""
    leaves, treedef = manifold_leaves(value, "value")
    return treedef.unflatten([leaf[index] for leaf in leaves])


def flat_tangent_to_tree(var, delta):
    """Split `(n, tangent_dim)` tangents into the pytree of per-leaf tangents of `var.value`."""
    leaves, _ = manifold_leaves(var.value, "value")
    pieces, start = [], 0
    for leaf, size in zip(leaves, var.leaf_dims):
        shape = leaf_tangent_shape(leaf)
        pieces.append(delta[:, start : start + size].reshape(delta.shape[0], *shape[1:]))
        start += size
    return var.treedef.unflatten(pieces)
