r"""The cost and the block normal equations of a factor graph at given values (traced).

For factor kind $f$ with whitened residuals $r_i = R_i f_i$, blocks $A_{is} = R_i J_{is}$ and
IRLS weights $w_i = \rho'(\|r_i\|^2)$, the cost is $\tfrac12\sum_i \rho(\|r_i\|^2)$ and
$$H_{a_s a_s} \mathrel{+}= w_i A_{is}^\top A_{is}, \qquad
H_{a_s a_t} \mathrel{+}= w_i A_{is}^\top A_{it}, \qquad
g_{a_s} \mathrel{+}= w_i A_{is}^\top r_i,$$
each a segment sum over the instances into the fixed slots of the `Layout` (the blocks of
$J^\top W J$ and $J^\top W r$, Dellaert and Kaess, "Factor graphs for robot perception", 2017,
Sec. 2.3); where an argument's instances collect long runs of terms (a camera's observations),
$[H_{a_s a_s} \mid g_{a_s}]$ is one chunked Gram sum `_gram.gram_sum` of $w_i A_{is}$ against
$[A_{is} \mid r_i]$ instead (`FactorPlan.grams`). Fixed instances get an identity diagonal
block, zero gradient and zero couplings, so their step is zero. `evaluate` computes $r_i$,
$A_{is}$ and $w_i$ (the cost with them) and `assemble` the sums, so that the solver's cost
evaluation of a trial point is, when the step is taken, the first half of its linearization;
`cost` alone (no Jacobians) serves `FactorGraph.cost` and the implicit derivatives. Factor
kinds that share a residual function are evaluated as one batch (`_per_instance`), then
whitened and weighted each with its own information and loss.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._factors import linearize_one, residual_one
from ._gram import gram_sum, small_tmatmul
from ._segments import segment_sum
from ._variables import instance


def _whiten(root, r):
    if root is None:
        return r
    if root.ndim == 2:
        return r @ root.T
    return jnp.einsum("mab,mb->ma", root, r)


def _robust(loss, s):
    if loss is None:
        return s, None
    return loss(s), loss.weight(s)


def _masked(plan, r):
    """`r` with the rows of a bucketed kind's padded instances zero (`FactorPlan.valid`; a
    `where`, so that whatever a padded instance evaluates to contributes nothing)."""
    if plan.valid is None:
        return r
    return jnp.where(plan.valid.reshape(-1, *(1,) * (r.ndim - 1)), r, 0.0)


def cost(factors, plans, values, data):
    r"""$\tfrac12 \sum \rho(\|R r\|^2)$ over every factor kind."""
    total = 0.0
    residuals = _per_instance(factors, plans, values, data, residual_one)
    for plan, r, (_, root, loss) in zip(plans, residuals, data):
        r = _masked(plan, _whiten(root, r))
        total = total + 0.5 * jnp.sum(_robust(loss, jnp.sum(r**2, axis=-1))[0])
    return total


def evaluate(factors, plans, values, data):
    """`(cost, parts)` at `values`: per factor kind `(r, blocks, w)`, the whitened residuals
    `(m, k)`, whitened Jacobian blocks `(m, k, d_s)` and IRLS weights (`None` without a loss).
    One trace of each factor kind serves both the cost of a trial step and, when the step is
    taken, its normal equations (`assemble`)."""
    total = 0.0
    parts = []
    linearized = _per_instance(factors, plans, values, data, linearize_one)
    for plan, (r, blocks), (_, root, loss) in zip(plans, linearized, data):
        if root is not None:
            r = _whiten(root, r)
            blocks = tuple(
                (root @ b) if root.ndim == 2 else jnp.einsum("mab,mbc->mac", root, b)
                for b in blocks
            )
        r, blocks = _masked(plan, r), tuple(_masked(plan, b) for b in blocks)
        rho, w = _robust(loss, jnp.sum(r**2, axis=-1))
        total = total + 0.5 * jnp.sum(rho)
        parts.append((r, blocks, w))
    return total, tuple(parts)


def _per_instance(factors, plans, values, data, one):
    """Per factor kind, `one(factor, xs, d)` vmapped over its instances. Kinds that share their
    residual (the same `residual` and `jacobian_fn` over the same variable kinds, data of one
    structure and shape) are evaluated as one batch, split afterwards: the program holds one copy
    of each residual and its Jacobian however many kinds use it (odometry and loop closures), and
    XLA's compile time grows with the copies (about 30 small kernels for a 2D between factor)."""
    groups = {}
    for j, (factor, plan, (d, _, _)) in enumerate(zip(factors, plans, data)):
        leaves, treedef = jax.tree_util.tree_flatten(d)
        shapes = tuple((jnp.shape(x)[1:], jnp.result_type(x)) for x in leaves)
        key = (factor.residual, factor.jacobian_fn, factor.data is None, plan.kinds, treedef,
               shapes)  # fmt: skip
        groups.setdefault(key, []).append(j)
    results = [None] * len(factors)
    for members in groups.values():
        factor, kinds = factors[members[0]], plans[members[0]].kinds
        xs = [
            instance(values[k], jnp.asarray(_joined([plans[j].indices[s] for j in members])))
            for s, k in enumerate(kinds)
        ]
        d = data[members[0]][0]
        if len(members) > 1:
            d = jax.tree_util.tree_map(
                lambda *a: jnp.concatenate(a), *(data[j][0] for j in members)
            )
        batch = jax.vmap(lambda *a, f=factor: one(f, a[:-1], a[-1]))(*xs, d)
        start = 0
        for j in members:
            stop = start + plans[j].indices[0].shape[0]
            results[j] = batch if len(members) == 1 else _rows(batch, start, stop)
            start = stop
    return results


def _joined(arrays):
    """`arrays` concatenated: by NumPy when they are host arrays (a constant of the program), by
    JAX when a bucketed graph passes them as operands (`_buckets`)."""
    if all(isinstance(a, np.ndarray) for a in arrays):
        return np.concatenate(arrays)
    return jnp.concatenate(arrays)


def _all(mask):
    """Whether the host mask `mask` holds everywhere (an operand's, `_buckets`, may not)."""
    return isinstance(mask, np.ndarray) and bool(mask.all())


def _rows(tree, start, stop):
    return jax.tree_util.tree_map(lambda a: a[start:stop], tree)


def linearize(layout, factors, plans, values, data):
    """`(cost, diag, off, grad)` at `values` (see the module docstring)."""
    total, parts = evaluate(factors, plans, values, data)
    return (total, *assemble(layout, plans, parts))


def assemble(layout, plans, parts):
    """`(diag, off, grad)` from `evaluate`'s parts (see the module docstring)."""
    dtype = parts[0][0].dtype
    keys = list(layout.pairs)
    diag = [jnp.zeros((n, d, d), dtype) for n, d in zip(layout.counts, layout.dims)]
    grad = [jnp.zeros((n, d), dtype) for n, d in zip(layout.counts, layout.dims)]
    off = [
        jnp.zeros((len(layout.pairs[k][0]), layout.dims[k[0]], layout.dims[k[1]]), dtype)
        for k in keys
    ]
    # every factor kind's [H_aa | g_a] blocks of one variable kind, and its H_ab blocks of one
    # pair of kinds, go into one segment sum each (fewer, larger scatters)
    per_kind = [([], []) for _ in layout.dims]
    per_pair = [([], []) for _ in keys]
    summed = [[] for _ in layout.dims]
    for plan, (r, blocks, w) in zip(plans, parts):
        weighted = blocks if w is None else tuple(w[:, None, None] * b for b in blocks)
        for s, (k, index, gram) in enumerate(zip(plan.kinds, plan.indices, plan.grams)):
            if gram is not None:  # long runs: [A^T W A | A^T W r] by chunks
                summed[k].append(
                    gram_sum(gram, weighted[s], jnp.concatenate([blocks[s], r[..., None]], -1))
                )
                continue
            both = small_tmatmul(weighted[s], jnp.concatenate([blocks[s], r[..., None]], -1))
            per_kind[k][0].append(both)
            per_kind[k][1].append(index)
        for s, t, key, slots, flipped in plan.couplings:
            block = small_tmatmul(weighted[s], blocks[t])
            if not isinstance(flipped, bool):  # per instance, within one kind
                block = jnp.where(flipped[:, None, None], jnp.swapaxes(block, 1, 2), block)
            elif flipped:
                block = jnp.swapaxes(block, 1, 2)
            j = keys.index(key)
            per_pair[j][0].append(block)
            per_pair[j][1].append(slots)
    for k, (pieces, indices) in enumerate(per_kind):
        if pieces:
            summed[k].append(
                segment_sum(jnp.concatenate(pieces), _joined(indices), layout.counts[k])
            )
        if summed[k]:
            both = sum(summed[k][1:], summed[k][0])
            diag[k], grad[k] = both[..., :-1], both[..., -1]
    for j, (pieces, slots) in enumerate(per_pair):
        off[j] = segment_sum(jnp.concatenate(pieces), _joined(slots), off[j].shape[0])
    for k, free in enumerate(layout.free):
        if not _all(free):
            eye = jnp.eye(layout.dims[k], dtype=dtype)
            diag[k] = jnp.where(free[:, None, None], diag[k], eye)
            grad[k] = jnp.where(free[:, None], grad[k], 0.0)
    for j, key in enumerate(keys):
        pair_free = layout.pair_free[key]
        if not _all(pair_free):
            off[j] = jnp.where(pair_free[:, None, None], off[j], 0.0)
    return tuple(diag), tuple(off), tuple(grad)
