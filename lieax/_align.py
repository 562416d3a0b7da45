"""Closed-form least-squares alignment of corresponding point sets (Kabsch; Umeyama with scale),
differentiable with respect to the points and weights by the implicit function theorem.

Problem: $\\min_{R, t, s} \\tfrac12 \\sum_i w_i |a_i - (s R b_i + t)|^2$ ($s = 1$ without scale), the
pose $T_{ab}$ that maps points given in frame b onto their correspondents in frame a (GTSAM's
`Pose3::Align` / `Similarity3::Align` convention, `a = aTb * b`).

Solution (GTSAM math notes, Sec. 19; Umeyama, "Least-squares estimation of transformation
parameters between two point patterns", PAMI 1991). With normalized weights, centroids
$\\bar a, \\bar b$, the correlation $\\Sigma = \\sum_i w_i (a_i - \\bar a)(b_i - \\bar b)^\\top$ and
$\\sigma_b^2 = \\sum_i w_i |b_i - \\bar b|^2$: $\\Sigma = U D V^\\top$,
$R = U S V^\\top$ with $S = \\mathrm{diag}(1, 1, \\det U \\det V)$ (a proper rotation even when the
best orthogonal matrix is a reflection), $s = \\mathrm{tr}(R^\\top \\Sigma) / \\sigma_b^2 = \\mathrm{tr}(DS)/\\sigma_b^2$,
$t = \\bar a - s R \\bar b$.

Derivatives. The SVD's own derivative divides by differences of singular values (it is undefined
for repeated ones, e.g. symmetric point sets), although the rotation itself is well defined. So
the rule differentiates the optimality condition instead: $R$ maximizes $\\mathrm{tr}(R^\\top\\Sigma)$,
so $M = R^\\top \\Sigma$ is symmetric, $F(\\Sigma, R) = \\mathrm{vee}(\\mathrm{skew}(R^\\top\\Sigma)) = 0$.
Perturbing $R \\to R\\,\\mathrm{Exp}(\\delta)$ and $\\Sigma \\to \\Sigma + \\dot\\Sigma$ and using
$[\\delta]_\\times M + M [\\delta]_\\times = [(\\mathrm{tr}(M) I - M)\\delta]_\\times$ for symmetric $M$ gives
$$\\delta = 2\\,(\\mathrm{tr}(M) I - M)^{-1}\\,\\mathrm{vee}(\\mathrm{skew}(R^\\top \\dot\\Sigma)),$$
whose matrix has eigenvalues $d_i \\pm d_j$ (signed singular values): it is singular exactly when
the rotation is not unique (points on a line, or a degenerate reflection case), not when singular
values repeat. Then $\\dot s = (\\mathrm{tr}(R^\\top\\dot\\Sigma) - s\\,\\dot{\\sigma_b^2}) / \\sigma_b^2$ (the term in
$\\delta$ vanishes since $M$ is symmetric) and $t = \\bar a - s R \\bar b$ is differentiated directly.
$\\dot\\Sigma, \\dot{\\bar a}, \\dot{\\bar b}, \\dot{\\sigma_b^2}$ come from JAX's derivative of the moments.
The rule is linear in the input tangents (reverse mode by transposition) and evaluates $R$ and $s$
through kernels, so second derivatives are right as well.
"""

import functools

import jax
import jax.numpy as jnp

from ._checks import as_float_array, broadcast_batch, check_last_axis
from ._linalg import cross, matvec, rotate_back, unskew
from .groups import _se3 as se3
from .groups import _sim3 as sim3
from .groups import _so3 as so3
from .groups._se3 import SE3
from .groups._sim3 import Sim3


def _moments(points_a, points_b, weights):
    """Centroids $\\bar a, \\bar b$, correlation $\\Sigma$ and spread $\\sigma_b^2$ with normalized weights."""
    w = weights / jnp.sum(weights, axis=-1, keepdims=True)
    mean_a = jnp.sum(w[..., None] * points_a, axis=-2)
    mean_b = jnp.sum(w[..., None] * points_b, axis=-2)
    centered_a = points_a - mean_a[..., None, :]
    centered_b = points_b - mean_b[..., None, :]
    correlation = jnp.einsum("...n,...ni,...nj->...ij", w, centered_a, centered_b)
    spread_b = jnp.sum(w * jnp.sum(centered_b * centered_b, axis=-1), axis=-1)
    return mean_a, mean_b, correlation, spread_b


def _trace(m):
    return m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _align_kernel(points_a, points_b, weights, with_scale):
    """SE3 (or Sim3 with `with_scale`) parameters of the least-squares alignment."""
    mean_a, mean_b, correlation, spread_b = _moments(points_a, points_b, weights)
    u, _, vt = jnp.linalg.svd(correlation)
    flip = jnp.linalg.det(u) * jnp.linalg.det(vt) < 0.0
    last = jnp.where(flip, -1.0, 1.0)[..., None]
    signs = jnp.concatenate([jnp.ones_like(last), jnp.ones_like(last), last], axis=-1)
    rotation = (u * signs[..., None, :]) @ vt  # U S Vᵀ, S = diag(1, 1, det U det V)
    q = so3.from_matrix(rotation)
    if with_scale:
        scale = _trace(jnp.swapaxes(rotation, -1, -2) @ correlation) / spread_b
        t = mean_a - scale[..., None] * matvec(rotation, mean_b)
        return jnp.concatenate([q, t, jnp.log(scale)[..., None]], axis=-1)
    t = mean_a - matvec(rotation, mean_b)
    return jnp.concatenate([q, t], axis=-1)


@_align_kernel.defjvp
def _align_kernel_jvp(with_scale, primals, tangents):
    """Implicit derivative of the optimality conditions (module docstring), in the carrier of SE3
    or Sim3."""
    params = _align_kernel(*primals, with_scale)
    (_, mean_b, correlation, spread_b), (mean_a_dot, mean_b_dot, correlation_dot, spread_b_dot) = (
        jax.jvp(_moments, primals, tangents)
    )
    rotation = so3.as_matrix(params[..., :4])
    rotation_t = jnp.swapaxes(rotation, -1, -2)
    m = rotation_t @ correlation
    m = 0.5 * (m + jnp.swapaxes(m, -1, -2))
    stiffness = _trace(m)[..., None, None] * jnp.eye(3, dtype=m.dtype) - m
    projected_dot = rotation_t @ correlation_dot
    omega = 2.0 * jnp.linalg.solve(stiffness, unskew(projected_dot)[..., None])[..., 0]
    if with_scale:
        scale = jnp.exp(sim3.to_parameters(params)[..., 7:])
        scale_dot = (_trace(projected_dot)[..., None] - scale * spread_b_dot[..., None]) / spread_b[
            ..., None
        ]
    else:
        scale, scale_dot = 1.0, 0.0
    # t = ā - s R b̄:  ṫ = ā' - ṡ R b̄ - s R (ω × b̄ + b̄'),  local v = Rᵀ ṫ / s.
    t_dot = mean_a_dot - matvec(
        rotation, scale_dot * mean_b + scale * (cross(omega, mean_b) + mean_b_dot)
    )
    v = rotate_back(rotation, t_dot) / scale
    if with_scale:
        local = jnp.concatenate([v, omega, scale_dot / scale], axis=-1)
        return params, sim3.from_local(params, local)
    return params, se3.from_local(params, jnp.concatenate([v, omega], axis=-1))


def align(points_a, points_b, weights=None, *, with_scale=False):
    """The least-squares alignment $T_{ab}$ of corresponding points, $a_i \\approx T_{ab}\\,b_i$.

    **Arguments:**
    - `points_a`, `points_b`: corresponding points, shape `(*batch, N, 3)` (batch shapes broadcast),
      at least 3 of them not on a line (at least 2 distinct with `with_scale`, 3 for the rotation).
    - `weights`: nonnegative weights `(*batch, N)` (default: all 1), not all zero.
    - `with_scale`: also estimate the scale (Umeyama); the result is then a `Sim3`.

    **Returns:** `SE3` $T_{ab}$ minimizing $\\sum_i w_i |a_i - T_{ab} b_i|^2$ (a `Sim3` with
    `with_scale`), batch shape `(*batch)`. Differentiable with respect to the points and weights
    (forward and reverse mode, any order) through the implicit function theorem on the optimality
    conditions, never through the SVD; where the rotation is not unique (collinear points) the
    derivative is not finite.
    """
    points_a = check_last_axis(points_a, 3, "align points_a", "3D points")
    points_b = check_last_axis(points_b, 3, "align points_b", "3D points")
    if points_a.ndim < 2 or points_b.ndim < 2:
        raise ValueError(
            f"align needs point sets of shape (*batch, N, 3), got {points_a.shape} and {points_b.shape}."
        )
    shape = broadcast_batch("align points", points_a.shape, points_b.shape)
    dtype = jnp.result_type(points_a, points_b)
    points_a = jnp.broadcast_to(points_a, shape).astype(dtype)
    points_b = jnp.broadcast_to(points_b, shape).astype(dtype)
    if weights is None:
        weights = jnp.ones(shape[:-1], dtype=dtype)
    else:
        weights = as_float_array(weights, "align weights")
        broadcast_batch("align weights", weights.shape, shape[:-1])
        weights = jnp.broadcast_to(weights, shape[:-1]).astype(dtype)
    params = _align_kernel(points_a, points_b, weights, bool(with_scale))
    return (Sim3 if with_scale else SE3)._wrap(params)
