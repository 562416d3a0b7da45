"""`loop_fingerprint`: what a factor graph's compiled loop is made of, named the same way in
every process, so that `lieax._executable_store` can load the loop a first process compiled
instead of tracing it again.

The loop is a function of lieax's code (the store's key holds a digest of it), of the graph's
structure (the key `FactorGraph` keeps its analysis by: variable kinds, counts, index arrays,
fixed instances; for a bucketed graph the buckets' key), of the solve's static options, and of
the factor kinds: their residual functions, and `jacobian_fn`s where given, named by the jaxpr
of one instance (`lieax._describe.jaxpr_fingerprint`) that `FactorGraph` traced when it checked
the kind, or, for lieax's own, by `lieax._describe.describe`. The loop linearizes, batches and
sums exactly that computation, so two kinds with one jaxpr make one loop."""

import jax

from .._describe import Undescribable, describe, jaxpr_fingerprint, stable_repr
from ._buckets import Buckets
from ._factors import residual_one


def loop_fingerprint(graph, options) -> str:
    """The fingerprint of `_solve.make_loop(graph, options)` (`graph` a `FactorGraph` or its
    `_buckets.Buckets`); `lieax._describe.Undescribable` where a part has no name that holds
    across processes (a retraction or loss written outside lieax, a custom derivative rule)."""
    if isinstance(graph, Buckets):  # the buckets' key, less the factor kinds' functions (below)
        structure = tuple(part[2:] if k == 4 else part for k, part in enumerate(graph.key))
    else:
        structure = graph._structure_key
    schur = options["schur"]
    parts = (
        structure,
        tuple(v.name for v in graph.variables),
        tuple(_factor(f, trace) for f, trace in zip(graph.factors, graph.factor_traces)),
        describe({k: v for k, v in options.items() if k != "schur"}),
        None if schur is None else schur.eliminated,
    )
    return stable_repr(parts)


def _factor(factor, trace):
    """Factor kind `factor`'s name and functions: lieax's own (`lieax.graph`'s, `lieax.imu`'s,
    `lieax.cameras`') by `describe` (their code and what their closures hold, with no trace),
    others by their jaxprs. `trace` is `(xs, data, jaxpr)` of one instance, the jaxpr of the
    residual, or of the `jacobian_fn` when there is one (the residual's is traced here: the cost
    evaluates it)."""
    try:
        functions = describe((factor.residual, factor.jacobian_fn))
    except Undescribable:
        xs, data, jaxpr = trace
        functions = [jaxpr_fingerprint(jaxpr)]
        if factor.jacobian_fn is not None:
            residual = jax.make_jaxpr(lambda xs, d: residual_one(factor, xs, d))(xs, data)
            functions.append(jaxpr_fingerprint(residual))
    return factor.name, factor.data is None, functions
