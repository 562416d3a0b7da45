r"""The point-to-point step: the closed-form weighted Kabsch / Umeyama update (Arun, Huang,
Blostein 1987), as Open3D's `TransformationEstimationPointToPoint`; no per-point data."""

import jax
import jax.numpy as jnp

from ..groups import SE3, kernels
from ._coordinates import squared_norms, transform_points
from ._parts import Step


def point_step(params, source, source_rows, matched, matched_rows, inliers, loss_weights):
    r"""The rigid motion $\Delta T$ that best maps the moved source $T s_i$ onto its matches $d_i$
    with the weights $w_i$ (inliers, times the IRLS weights), composed on the left:
    $T \leftarrow \Delta T \cdot T$. With the weighted centroids $\bar m, \bar d$ and the
    correlation $\Sigma = \sum_i w_i (d_i - \bar d)(T s_i - \bar m)^\top$, $\Delta R$ is the
    proper rotation maximizing $\mathrm{tr}(\Delta R^\top \Sigma)$ (the library's one Kabsch,
    `lieax.groups.kernels.kabsch_rotation`) and $\Delta t = \bar d - \Delta R\,\bar m$."""
    dtype = params.dtype
    moved = transform_points(params, source)
    weights = inliers.astype(dtype) * loss_weights(squared_norms(moved - matched))
    total = jnp.maximum(jnp.sum(weights), jnp.finfo(dtype).tiny)
    mean_moved = jnp.sum(weights[:, None] * moved, axis=0) / total
    mean_matched = jnp.sum(weights[:, None] * matched, axis=0) / total
    correlation = jnp.einsum(
        "n,ni,nj->ij", weights, matched - mean_matched, moved - mean_moved,
        precision=jax.lax.Precision.HIGHEST,
    )  # fmt: skip
    rotation = kernels.kabsch_rotation(correlation)
    turned = jnp.matmul(
        kernels.so3_as_matrix(rotation), mean_moved, precision=jax.lax.Precision.HIGHEST
    )
    delta = kernels.element(SE3, jnp.concatenate([rotation, mean_matched - turned]))
    return (delta @ kernels.element(SE3, params)).parameters()


POINT_TO_POINT = Step("point", point_step)
