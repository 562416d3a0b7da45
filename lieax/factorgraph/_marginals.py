r"""Marginal covariances: blocks of $H^{-1}$ at a solution (GTSAM's
`Marginals.marginalCovariance`, Ceres' `Covariance`).

$H = J^\top W J$ is the Gauss-Newton matrix of the whitened, reweighted residuals at the given
values, so the covariance of instance $a$ is the diagonal block $(H^{-1})_{aa}$ in its right-local
tangent coordinates (translation first for poses, as everywhere in lieax; GTSAM orders Pose3's
rotation first). Small graphs invert the dense $H$; larger ones factor it once with the
multifrontal `CholeskyPlan` and solve for the unit right-hand sides of the requested blocks.
"""

import numpy as np

from .. import _cpu_emitters as cpu_emitters
from ._assembly import linearize
from ._block_pattern import dense_matrix
from ._linear import to_padded

_DENSE_LIMIT = 2000


def marginal_covariances(graph, values, var, indices=None, *, data=None, method="auto"):
    """The marginal covariances of instances `indices` (default all) of `var` at `values`.

    **Arguments:**

    - `graph`: the `FactorGraph`.
    - `values`: the values (a `SolveResult.values` tuple), in the order of `graph.variables`.
    - `var`: the `Var` whose instances are wanted.
    - `indices`: instance indices (default all).
    - `data`: factor data as `FactorGraph.solve` takes it (default the factors').
    - `method`: `"dense"`, `"cholesky"` or `"auto"` (dense up to 2000 padded unknowns).

    **Returns:** a numpy array `(len(indices), d, d)`; zero for fixed instances.
    """
    layout = graph.layout
    k = graph.index(var)
    indices = np.arange(var.count) if indices is None else np.asarray(indices).reshape(-1)
    if np.any((indices < 0) | (indices >= var.count)):
        raise ValueError(f"indices out of range for {var.name!r} with {var.count} instances.")
    if method not in ("auto", "dense", "cholesky"):
        raise ValueError(f"method must be 'auto', 'dense' or 'cholesky', got {method!r}.")
    if method == "auto":
        method = "dense" if layout.padded_unknowns <= _DENSE_LIMIT else "cholesky"
    system = padded_system(graph, method == "dense")(tuple(values), graph._data(data))
    D, d = layout.block_size, layout.dims[k]
    blocks = layout.offsets[k] + indices
    if method == "dense":
        inverse = np.linalg.inv(np.asarray(system))
        rows = blocks[:, None] * D + np.arange(d)[None, :]
        result = inverse[rows[:, :, None], rows[:, None, :]]
    else:
        plan = layout.plan()
        factors = plan.factor(*(np.asarray(a) for a in system))
        result = np.empty((len(indices), d, d))
        for m, block in enumerate(blocks):
            for c in range(d):
                rhs = np.zeros((layout.pattern.num_blocks, D))
                rhs[block, c] = 1.0
                result[m, :, c] = plan.solve_factored(factors, rhs)[block, :d]
    result[~layout.free[k][indices]] = 0.0
    return result


def padded_system(graph, dense):
    """The compiled `(values, data) ->` normal equations of `graph` on its padded pattern, the
    dense matrix (`dense`) or `(diag, off)`: one program per graph and form (the linearization,
    the padding and the dense matrix together; op by op they were some 40 small compilations on
    a first call). XLA's classic CPU emitters (`lieax._cpu_emitters`) compile it in about half
    the time; it runs once per call."""
    graph._check_x64()
    program = graph._programs.get(("padded_system", dense))
    if program is None:
        layout = graph.layout

        def system(values, data):
            _, diag, off, grad = linearize(layout, graph.factors, graph.plans, values, data)
            diag, off, _ = to_padded(layout, diag, off, grad)
            return dense_matrix(layout.pattern, diag, off) if dense else (diag, off)

        program = graph._programs[("padded_system", dense)] = cpu_emitters.jit(system)
    return program
