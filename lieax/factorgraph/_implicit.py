r"""Derivatives of a solution with respect to the factor data, by the implicit function theorem.

At the solution $x^*(\theta)$ the tangent gradient $g(\delta, \theta) = \nabla_\delta
f(x^* \oplus \delta, \theta)$ of the cost vanishes at $\delta = 0$, so
$\dot\delta = -H^{-1} \frac{\partial g}{\partial\theta}\dot\theta$ with the exact Hessian
$H = \partial g / \partial \delta$ over the free instances (Ceres' notes on the implicit
function theorem), by `lieax.lstsq._implicit.minimizer_tangents`, the rule of `least_squares`
too. $\theta$ is every factor
kind's `(data, sqrt_information, loss)`; fixed instances do not move. The Hessian is dense
(one forward pass per unknown over a reverse pass of the cost), so this is for problems of up to
`MAX_UNKNOWNS` unknowns; larger ones raise a `ValueError` when differentiated.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..autodiff._tangents import manifold_leaves
from ..lstsq._implicit import local_to_tangents, minimizer_tangents
from ._variables import flat_tangent_to_tree

MAX_UNKNOWNS = 2000


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def solve_implicit(graph, loop, values, data, params):
    """`(solution, summary)` of `loop(values, data, params)` (the compiled solve), differentiated
    implicitly with respect to `data`: the solution does not depend on the start `values`, and
    of the summary only the cost (its first entry) has a derivative. The loop runs on primal
    values only, so differentiating reuses its compiled program."""
    return loop(values, data, params)[:2]


@solve_implicit.defjvp
def _jvp(graph, loop, primals, tangents):
    start, data, params = primals
    values, summary, _ = loop(start, data, params)
    tangent = graph._implicit
    if tangent is None:
        tangent = graph._implicit = jax.jit(functools.partial(_tangents, graph))
    values_dot, cost_dot = tangent(values, data, tangents[1])
    summary_dot = jnp.zeros_like(summary).at[0].set(cost_dot)
    return (values, summary), (values_dot, summary_dot)


def _tangents(graph, values, data, data_dot):
    """`(values_dot, cost_dot)` at the solution `values` for the data tangent `data_dot`."""
    from ._assembly import cost as graph_cost
    from ._solve import retract

    layout = graph.layout
    n = layout.num_unknowns
    if n > MAX_UNKNOWNS:
        raise ValueError(
            f"implicit derivatives of FactorGraph.solve use a dense Hessian and support up to "
            f"{MAX_UNKNOWNS} unknowns; this graph has {n}."
        )
    splits = np.cumsum([c * d for c, d in zip(layout.counts, layout.dims)])[:-1]
    free = np.concatenate([np.repeat(f, d) for f, d in zip(layout.free, layout.dims)])

    def unflatten(flat):
        pieces = jnp.split(flat, splits)
        return [p.reshape(c, d) for p, c, d in zip(pieces, layout.counts, layout.dims)]

    def objective(delta, theta):
        delta = jnp.where(free, delta, 0.0)
        moved = retract(graph.variables, values, unflatten(delta))
        return graph_cost(graph.factors, graph.plans, moved, theta)

    dtype = jnp.result_type(*(getattr(x, "_params", x) for x in jax.tree_util.tree_leaves(values)))
    delta_dot, cost_dot = minimizer_tangents(objective, n, dtype, data, data_dot, free)
    values_dot = []
    for var, value, d in zip(graph.variables, values, unflatten(delta_dot)):
        leaves, treedef = manifold_leaves(value, "value")
        local = jax.tree_util.tree_leaves(flat_tangent_to_tree(var, d))
        values_dot.append(local_to_tangents(leaves, treedef, local))
    return tuple(values_dot), jnp.asarray(cost_dot, dtype)
