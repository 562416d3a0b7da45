r"""Bucketed factor graphs (`FactorGraph(..., buckets=True)`): one compiled loop for every graph
whose counts fall in the same buckets, for a window that grows or slides step by step.

A graph's compiled loop holds its structure as constants (index arrays, the slots of the
normal equations' blocks, the Cholesky plan's key), so a graph with one more pose traces and
compiles the whole loop again. Here each variable kind's instance count, each factor kind's
and each pair list's is padded on the host to `bucket_size` of it, and the structure becomes
operands of those fixed shapes (`Buckets.operands`): the loop is compiled once per
(kinds, bucketed counts, options) and called with each graph's operands.

- A padded factor instance repeats instance 0 of its kind (its indices, slots and data, so it
  evaluates where a real one does) and is masked (`FactorPlan.valid`): its whitened residual
  and Jacobian blocks are zero, so it adds nothing to the cost, the gradient or $H$.
- A padded variable instance repeats instance 0's value and is held fixed (an identity
  diagonal block, zero gradient and couplings, as `Var(fixed=...)`): its step is zero, and the
  solution is cut back to the real instances.
- A padded pair (off-diagonal block) is zero and repeats pair 0 (or names instance 0 of its
  kinds): the dense matrix and the products $H x$ add their blocks, adding nothing.
- The multifrontal Cholesky analyses each graph's own pattern over the bucketed blocks (the
  padded blocks are isolated: they solve to zero) and is named at run time by its key
  (`_multifrontal.cholesky_solve_keyed`), the pair blocks permuted into the plan's order by an
  operand.

The Schur complement (`eliminate=`) keeps per-structure Gram plans that are not bucketed;
bucketed graphs refuse an explicit elimination and `"auto"` eliminates nothing. The bucket
rule is `lieax.imu`'s (two buckets per doubling, at most a third of the instances padded).
"""

import types

import jax
import jax.numpy as jnp
import numpy as np

from .._bucket_sizes import bucket_size
from ._block_pattern import BlockPattern
from ._multifrontal import CholeskyPlan, cholesky_solve_keyed, keep_keyed
from ._native_cholesky import key_words
from ._structure import FactorPlan


def _padded(array, size, fill):
    """`array` (host) with `size - len(array)` rows of `fill` appended (`"first"`: its row 0,
    zeros when it is empty)."""
    array = np.asarray(array)
    extra = size - len(array)
    if fill == "first" and len(array):
        rows = np.repeat(array[:1], extra, axis=0)
    else:
        rows = np.full((extra, *array.shape[1:]), 0 if fill == "first" else fill, array.dtype)
    return np.concatenate([array, rows])


def _resized(trees, sizes, pad):
    """Each tree of `trees` with its leaves' rows padded (`pad`, repeating row 0) or cut to the
    matching entry of `sizes`: concrete leaves by NumPy and one transfer for all of them (a new
    size compiles nothing), traced ones by JAX."""
    flat = [jax.tree_util.tree_flatten(tree) for tree in trees]
    concrete = [
        (k, i) for k, (leaves, _) in enumerate(flat)
        for i, leaf in enumerate(leaves) if not isinstance(leaf, jax.core.Tracer)
    ]  # fmt: skip
    host = []
    for k, i in concrete:
        leaf = np.asarray(flat[k][0][i])
        # (a copy of the cut rows: JAX takes an array of its own in half the time of a view)
        leaf = _padded(leaf, sizes[k], "first") if pad else np.array(leaf[: sizes[k]])
        host.append(leaf.astype(jax.dtypes.canonicalize_dtype(leaf.dtype), copy=False))
    moved = dict(zip(concrete, jax.device_put(host)))
    out = []
    for k, (leaves, treedef) in enumerate(flat):
        new = []
        for i, leaf in enumerate(leaves):
            if (k, i) in moved:
                new.append(moved[(k, i)])
            elif pad:
                extra = sizes[k] - leaf.shape[0]
                new.append(jnp.concatenate([leaf, jnp.repeat(leaf[:1], extra, axis=0)]))
            else:
                new.append(leaf[: sizes[k]])
        out.append(treedef.unflatten(new))
    return tuple(out)


def _instance_shapes(value):
    """The shape and dtype of one instance of each leaf of a batched value (the loop reshapes
    steps to them: part of the loop's key)."""
    return tuple(
        (np.shape(x)[1:], np.dtype(jnp.result_type(x))) for x in jax.tree_util.tree_leaves(value)
    )


class Buckets:
    """One graph's bucketed shapes and the operands that carry its structure (see the module
    docstring). `key` names everything a loop's trace reads from it besides the operands, so
    graphs of one key share their compiled loops; `traced(structure)` is the graph as the loop
    sees it, the structure's arrays traced."""

    def __init__(self, graph):
        layout, plans = graph.layout, graph.plans
        empty = [v.name for v in graph.variables if v.count == 0]
        if empty:
            raise ValueError(
                f"buckets=True needs at least one instance of each variable kind; {empty} have "
                "none (padded instances repeat instance 0)."
            )
        self.variables, self.factors = graph.variables, graph.factors
        self.factor_traces = graph.factor_traces  # for `_fingerprint`
        self.dims, self.real_counts = layout.dims, layout.counts
        self.counts = tuple(bucket_size(n) for n in layout.counts)
        self.keys = tuple(layout.pairs)
        self.pair_counts = tuple(bucket_size(len(layout.pairs[k][0])) for k in self.keys)
        self.factor_counts = tuple(bucket_size(f.count) for f in graph.factors)
        # a coupling's orientation across two kinds is static, within one kind an operand
        self.couplings = tuple(
            tuple((s, t, key, flipped if key[0] != key[1] else None)
                  for s, t, key, _, flipped in plan.couplings)
            for plan in plans
        )  # fmt: skip
        self.kinds = tuple(plan.kinds for plan in plans)
        self.key = (
            bool(jax.config.jax_enable_x64),
            tuple((v.treedef, v.leaf_dims, _instance_shapes(v.value)) for v in graph.variables),
            self.counts,
            tuple(zip(self.keys, self.pair_counts)),
            tuple(
                (f.residual, f.jacobian_fn, f.data is None, m)
                for f, m in zip(graph.factors, self.factor_counts)
            ),
            self.kinds,
            self.couplings,
        )
        self.operands = jax.device_put(self._operands(layout, plans))  # once, not per call
        self.layout = layout
        self._cholesky = None
        self._kept = {}

    @property
    def padded_unknowns(self):
        return sum(self.counts) * max(self.dims)

    @property
    def pattern(self):
        """The bucketed pattern's size, for `dense_threads` (its pairs are operands)."""
        return BlockPattern(sum(self.counts), max(self.dims), None, None)

    def _operands(self, layout, plans):
        """The structure's arrays at the bucketed shapes (see the module docstring)."""
        factors = []
        for plan, m, f in zip(plans, self.factor_counts, self.factors):
            couplings = tuple(
                (
                    _padded(slots, m, "first").astype(np.int32),
                    None if isinstance(flipped, bool) else _padded(flipped, m, False),
                )
                for _, _, _, slots, flipped in plan.couplings
            )
            factors.append(
                {
                    "indices": tuple(_padded(i, m, "first").astype(np.int32) for i in plan.indices),
                    "valid": _padded(np.ones(f.count, bool), m, False),
                    "couplings": couplings,
                }
            )
        pairs = [layout.pairs[k] for k in self.keys]
        return {
            "free": tuple(_padded(f, n, False) for f, n in zip(layout.free, self.counts)),
            "pairs": tuple(
                tuple(_padded(a, p, "first").astype(np.int32) for a in rc)
                for rc, p in zip(pairs, self.pair_counts)
            ),
            "pair_free": tuple(
                _padded(layout.pair_free[k], p, False) for k, p in zip(self.keys, self.pair_counts)
            ),
            "factors": tuple(factors),
        }

    def cholesky_operands(self):
        """`(key, order)` of the multifrontal solve: the plan of this graph's pattern over the
        bucketed blocks (its real pairs only; analysed once per graph) named by its key words,
        and for each of the plan's pairs its block in the bucketed pair blocks (the rest of
        `order` repeats block 0, which the solve does not read)."""
        if self._cholesky is None:
            offsets = np.concatenate([[0], np.cumsum(self.counts)])
            starts = np.concatenate([[0], np.cumsum(self.pair_counts)])
            rows, cols, where = [], [], []
            for j, (a, b) in enumerate(self.keys):
                r, c = self.layout.pairs[(a, b)]
                rows.append(offsets[a] + r)
                cols.append(offsets[b] + c)
                where.append(starts[j] + np.arange(len(r)))
            rows, cols, where = (np.concatenate(x).astype(np.int64) for x in (rows, cols, where))
            pattern, pair, _ = BlockPattern.from_edges(int(offsets[-1]), max(self.dims), rows, cols)
            order = np.zeros(int(starts[-1]), np.int32)
            order[pair] = where
            plan = CholeskyPlan.analyze(pattern)
            self._cholesky = plan, jax.device_put((key_words(keep_keyed(plan)), order))
        return self._cholesky[1]

    def runner(self, loop, method):
        """`run(values, data, params) -> (values, summary, system)`: `loop` (the bucketed loop,
        which takes the structure as its fourth operand) on the values and data padded to the
        buckets, its values cut back to the real counts (its system stays the buckets')."""
        structure = dict(self.operands)
        if method == "cholesky":
            structure["cholesky"] = self.cholesky_operands()

        def run(values, data, params):
            solution, summary, system = loop(
                self.pad_values(values), self.pad_data(data), params, structure
            )
            return self.cut(solution), summary, system

        return run

    def pad_values(self, values):
        return self._memo("values", values, lambda: _resized(values, self.counts, True))

    def pad_data(self, data):
        """Per factor kind `(data, sqrt_information, loss)` with the data's leaves and a
        per-instance `sqrt_information` padded to the bucket."""

        def padded():
            trees = [(d, root if root is not None and jnp.ndim(root) == 3 else None)
                     for d, root, _ in data]  # fmt: skip
            out = _resized(trees, self.factor_counts, True)
            return tuple(
                (d, root if padded_root is None else padded_root, loss)
                for (d, padded_root), (_, root, loss) in zip(out, data)
            )

        return self._memo("data", data, padded)

    def _memo(self, name, given, pad):
        """`pad()`, kept for the last `given` of `name` while its entries are the same objects
        and its leaves JAX arrays (a graph's own values and data, solved again, are padded
        once)."""
        kept = self._kept.get(name)
        if kept is not None and len(kept[0]) == len(given):
            if all(a is b for a, b in zip(kept[0], given)):
                return kept[1]
        result = pad()
        # kept only for JAX arrays: a NumPy array could be changed in place before the next call
        arrays = [x[:2] for x in given] if name == "data" else given  # (not the losses)
        if all(isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer)
               for x in jax.tree_util.tree_leaves(arrays)):  # fmt: skip
            self._kept[name] = (tuple(given), result)
        return result

    def cut(self, values):
        return _resized(values, self.real_counts, False)

    def traced(self, structure):
        """The graph as the bucketed loop sees it: `layout`, `plans` (their arrays from the
        `structure` operand), `factors`, `variables` (read for their functions and shapes)."""
        plans = tuple(
            FactorPlan(
                kinds,
                operands["indices"],
                tuple(
                    (s, t, key, slots, flipped if static is None else static)
                    for (s, t, key, static), (slots, flipped) in zip(
                        couplings, operands["couplings"]
                    )
                ),
                (None,) * len(kinds),
                operands["valid"],
            )
            for kinds, couplings, operands in zip(self.kinds, self.couplings, structure["factors"])
        )
        layout = TracedLayout(self, structure)
        return types.SimpleNamespace(
            layout=layout, plans=plans, factors=self.factors, variables=self.variables
        )


class TracedLayout:
    """The `_structure.Layout` of a bucketed graph inside its loop: the bucketed counts, the
    pairs (`(rows, cols)` per kind pair), masks and pattern traced, one uniform pattern of the
    pair lists one after another (`slots` consecutive), and the keyed Cholesky solve."""

    def __init__(self, buckets, structure):
        self.dims, self.counts = buckets.dims, buckets.counts
        self.block_size = max(self.dims)
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64)
        self.pairs = dict(zip(buckets.keys, structure["pairs"]))
        self.free = structure["free"]
        self.pair_free = dict(zip(buckets.keys, structure["pair_free"]))
        self.slots, start = {}, 0
        for key, p in zip(buckets.keys, buckets.pair_counts):
            self.slots[key] = np.arange(start, start + p)
            start += p
        global_rows = [self.offsets[a] + r for (a, _), (r, _) in self.pairs.items()]
        global_cols = [self.offsets[b] + c for (_, b), (_, c) in self.pairs.items()]
        empty = jnp.zeros(0, jnp.int32)
        self.pattern = BlockPattern(
            int(self.offsets[-1]),
            self.block_size,
            jnp.concatenate(global_rows) if global_rows else empty,
            jnp.concatenate(global_cols) if global_cols else empty,
        )
        self._cholesky = structure.get("cholesky")

    def cholesky_solve(self, diag, off, rhs):
        """The multifrontal solve by the plan named by the `cholesky` operand, the pair blocks
        taken into its order (`Buckets.cholesky_operands`)."""
        key, order = self._cholesky
        return cholesky_solve_keyed(key, diag, off[order], rhs)
