r"""The point-to-plane step: one Gauss-Newton step per iteration on $r_i = n_i^\top (T s_i - d_i)$,
whose $1 \times 6$ Jacobian block $n_i^\top [R, -R[s_i]_\times]$ is written out per coordinate
(`plane_rows`, checked against `lieax.jacobian` of `SE3`'s action); the $6 \times 6$ normal
equations are a reduction over the cloud, weighted by the robust loss (iteratively reweighted
least squares). Its per-point data are the target normals."""

import jax.numpy as jnp

from .._linalg import quat_to_matrix
from ..groups import SE3, kernels
from ..lstsq._normal_equations import solve_spd
from ._coordinates import row_sums, transformed_columns
from ._parts import Step


def plane_rows(params, points, normals):
    r"""$J_i = \partial\, n_i^\top (T \oplus \xi)\, s_i / \partial \xi
    = n_i^\top [R, -R[s_i]_\times] = [m_i^\top, (s_i \times m_i)^\top]$, $m_i = R^\top n_i$,
    for SE3 parameters `params`, transposed: `(6, n)`, column $i$ is $J_i$. The action's Jacobian
    $[R, -R[s]_\times]$ (Solà, Deray, Atchuthan 2018, "A micro Lie theory", appendix D, right
    perturbation) and $-m^\top [s]_\times = (s \times m)^\top$. Written out per coordinate: one
    fused kernel, where `lieax.jacobian` of the action under `vmap` compiles to eight on the CPU;
    six contiguous rows, where `(n, 6)` rows cost a strided concatenation and a transpose for the
    reduction (the step 1.5-2x slower at 160k points).
    `tests/test_icp.py` checks it against `lieax.jacobian` and finite differences."""
    rotation = quat_to_matrix(params[:4])
    m = [sum(rotation[a, j] * normals[:, a] for a in range(3)) for j in range(3)]
    s = [points[:, k] for k in range(3)]
    cross = [s[1] * m[2] - s[2] * m[1], s[2] * m[0] - s[0] * m[2], s[0] * m[1] - s[1] * m[0]]
    return jnp.stack(m + cross, axis=0)


def plane_step(params, source, source_rows, matched, normals, inliers, loss_weights):
    r"""One Gauss-Newton step $T \leftarrow T \oplus \delta$, $\delta = -(J^\top W J)^{-1} J^\top W r$,
    with rows $J_i = n_i^\top [R, -R[s_i]_\times]$ (see `plane_rows`) and `normals` the matched
    points' normals. The 21 distinct entries of $J^\top W J$ and the 6 of $J^\top W r$ are one
    reduction over the rows (`row_sums`): no `(6, n)` array is written, where the matrix
    products of the weighted rows had two. Five steps with their gathers, float64: 13 ms against
    29 at 160k rows, 0.66 against 0.79 ms at 10k, half the temporary memory (jaxlib 0.10.2, CPU).
    A rank-deficient $J^\top W J$ (a plane slides along itself) gives the step without a
    component along its null space (`lieax.lstsq._normal_equations.solve_spd`)."""
    pose = kernels.element(SE3, params)
    moved = transformed_columns(params, source)
    residuals = sum(normals[:, a] * (moved[a] - matched[:, a]) for a in range(3))
    weights = inliers.astype(params.dtype) * loss_weights(residuals * residuals)
    rows = list(plane_rows(params, source, normals))
    weighted = [row * weights for row in rows]
    upper = [(i, j) for i in range(6) for j in range(i, 6)]
    sums = row_sums(
        [weighted[i] * rows[j] for i, j in upper] + [row * residuals for row in weighted]
    )
    entries = dict(zip(upper, sums))
    hessian = jnp.stack(
        [jnp.stack([entries[min(i, j), max(i, j)] for j in range(6)]) for i in range(6)]
    )
    gradient = jnp.stack(sums[len(upper) :])
    return pose.rplus(-solve_spd(hessian, gradient)).parameters()


POINT_TO_PLANE = Step("plane", plane_step)
