r"""Closed-form least-squares alignment of corresponding point sets (Kabsch; Umeyama with scale): the
kernel behind `SE3.align`, `Sim3.align` and `lieax.align`, differentiable with respect to the
points and weights by the implicit function theorem.

Problem: $\min_{R, t, s} \tfrac12 \sum_i w_i |a_i - (s R b_i + t)|^2$ ($s = 1$ without scale), the
pose $T_{ab}$ that maps points given in frame b onto their correspondents in frame a (GTSAM's
`Pose3::Align` / `Similarity3::Align` convention, `a = aTb * b`).

Solution (GTSAM math notes, Sec. 19; Umeyama, "Least-squares estimation of transformation
parameters between two point patterns", PAMI 1991). With normalized weights, centroids
$\bar a, \bar b$, the correlation $\Sigma = \sum_i w_i (a_i - \bar a)(b_i - \bar b)^\top$ and
$\sigma_b^2 = \sum_i w_i |b_i - \bar b|^2$: $\Sigma = U D V^\top$,
$R = U S V^\top$ with $S = \mathrm{diag}(1, 1, \det U \det V)$ (a proper rotation even when the
best orthogonal matrix is a reflection), $s = \mathrm{tr}(R^\top \Sigma) / \sigma_b^2 = \mathrm{tr}(DS)/\sigma_b^2$,
$t = \bar a - s R \bar b$.

Derivatives. Only the rotation needs a rule (`rotation`, a `custom_jvp` kernel from $\Sigma$ to SO3
parameters); the moments, $s$ and $t$ are differentiated by JAX through SO3's kernels. The SVD's
own derivative divides by differences of singular values (it is undefined for repeated ones, e.g.
symmetric point sets), although the rotation itself is well defined. So the rule differentiates
the optimality condition instead: $R$ maximizes $\mathrm{tr}(R^\top\Sigma)$, so $M = R^\top \Sigma$
is symmetric, $F(\Sigma, R) = \mathrm{vee}(\mathrm{skew}(R^\top\Sigma)) = 0$. Perturbing
$R \to R\,\mathrm{Exp}(\delta)$ and $\Sigma \to \Sigma + \dot\Sigma$ and using
$[\delta]_\times M + M [\delta]_\times = [(\mathrm{tr}(M) I - M)\delta]_\times$ for symmetric $M$ gives
$$\delta = 2\,(\mathrm{tr}(M) I - M)^{-1}\,\mathrm{vee}(\mathrm{skew}(R^\top \dot\Sigma)),$$
whose matrix has eigenvalues $d_i \pm d_j$ (signed singular values): it is singular exactly when
the rotation is not unique (points on a line, or a degenerate reflection case), not when singular
values repeat. In $\dot s = \mathrm{tr}(\dot R^\top \Sigma + R^\top \dot\Sigma)/\sigma_b^2 - \dots$ the term
in $\delta$ is $\mathrm{tr}([\delta]_\times^\top M) = 0$ for symmetric $M$, so JAX's derivative of the
formula for $s$ is the derivative of the optimal scale. The rule is linear in $\dot\Sigma$ (reverse
mode by transposition) and evaluates $R$ through SO3's `as_matrix` kernel, so derivatives of every
order are exact.
"""

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import broadcast_batch, check_last_axis, common_float_arrays, match_dtype
from .._linalg import unskew
from . import _so3 as so3

MINIMUM_POINTS = 3  # the rotation is unique only for 3 or more points not on a line


def _check_concrete(points_a, points_b, weights, what):
    """Finite points and nonnegative finite weights, not all zero (concrete values only)."""
    if any(isinstance(x, jax.core.Tracer) for x in (points_a, points_b, weights)):
        return
    for name, x in (("points_a", points_a), ("points_b", points_b)):
        if not np.all(np.isfinite(np.asarray(x))):
            raise ValueError(f"{what}: {name} has non-finite entries.")
    w = np.asarray(weights)
    if not np.all(np.isfinite(w) & (w >= 0)):
        raise ValueError(f"{what}: weights must be nonnegative and finite.")
    if np.any(np.sum(w, axis=-1) == 0):
        raise ValueError(f"{what}: the weights of a point set are all zero.")


def prepare(points_a, points_b, weights, what):
    """Point sets `(*batch, N, 3)` broadcast together, and weights `(*batch, N)` (ones by default),
    in one dtype (a `TypeError` naming both for arrays of two float dtypes; Python and NumPy
    numbers take the points'); a `ValueError` naming `what` for fewer than 3 points, mismatched
    shapes, non-finite points or weights, negative weights, or all-zero weights (the last three
    checked on concrete values only: under `jit`, all-zero weights give NaN in every output)."""
    points_a, points_b = common_float_arrays(f"{what} points", points_a, points_b)
    points_a = check_last_axis(points_a, 3, f"{what} points_a", "3D points")
    points_b = check_last_axis(points_b, 3, f"{what} points_b", "3D points")
    if points_a.ndim < 2 or points_b.ndim < 2:
        raise ValueError(
            f"{what} needs point sets of shape (*batch, N, 3), got {points_a.shape} and "
            f"{points_b.shape}."
        )
    shape = broadcast_batch(f"{what} points", points_a.shape, points_b.shape)
    if shape[-2] < MINIMUM_POINTS:
        raise ValueError(
            f"{what} needs at least {MINIMUM_POINTS} corresponding points (not on a line), "
            f"got {shape[-2]}."
        )
    dtype = points_a.dtype
    if weights is None:
        weights = jnp.ones(shape[:-1], dtype=dtype)
    else:
        weights = match_dtype(weights, dtype, f"{what} weights", "the points")
        batch = broadcast_batch(f"{what} weights", weights.shape, shape[:-1])
        shape = (*batch, 3)
        weights = jnp.broadcast_to(weights, batch)
    points_a = jnp.broadcast_to(points_a, shape)
    points_b = jnp.broadcast_to(points_b, shape)
    _check_concrete(points_a, points_b, weights, what)
    return points_a, points_b, weights


def moments(points_a, points_b, weights):
    r"""Centroids $\bar a, \bar b$, correlation $\Sigma$ and spread $\sigma_b^2$ with normalized weights."""
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


@jax.custom_jvp
def rotation(correlation):
    r"""SO3 parameters of $R = U S V^\top$, $S = \mathrm{diag}(1, 1, \det U \det V)$, the proper
    rotation maximizing $\mathrm{tr}(R^\top \Sigma)$ (module docstring)."""
    u, _, vt = jnp.linalg.svd(correlation)
    flip = jnp.linalg.det(u) * jnp.linalg.det(vt) < 0.0
    last = jnp.where(flip, -1.0, 1.0)[..., None]
    signs = jnp.concatenate([jnp.ones_like(last), jnp.ones_like(last), last], axis=-1)
    return so3.from_matrix((u * signs[..., None, :]) @ vt)


@rotation.defjvp
def _rotation_jvp(primals, tangents):
    r"""$\delta = 2\,(\mathrm{tr}(M) I - M)^{-1}\,\mathrm{vee}(\mathrm{skew}(R^\top \dot\Sigma))$,
    $M = R^\top\Sigma$ (symmetrized), in SO3's carrier."""
    (correlation,), (correlation_dot,) = primals, tangents
    q = rotation(correlation)
    rotation_t = jnp.swapaxes(so3.as_matrix(q), -1, -2)
    m = rotation_t @ correlation
    m = 0.5 * (m + jnp.swapaxes(m, -1, -2))
    stiffness = _trace(m)[..., None, None] * jnp.eye(3, dtype=m.dtype) - m
    omega = 2.0 * jnp.linalg.solve(stiffness, unskew(rotation_t @ correlation_dot)[..., None])
    return q, so3.from_local(q, omega[..., 0])


def solve(points_a, points_b, weights, *, with_scale, what):
    r"""`(q, t, sigma)`: SO3 parameters, translation and log-scale `(*batch)` (`None` without
    `with_scale`) of the least-squares $T_{ab}$ with $a_i \approx s R b_i + t$; inputs checked by
    `prepare` (errors name `what`)."""
    points_a, points_b, weights = prepare(points_a, points_b, weights, what)
    mean_a, mean_b, correlation, spread_b = moments(points_a, points_b, weights)
    q = rotation(correlation)
    if not with_scale:
        return q, mean_a - so3.act(q, mean_b), None
    rotation_t = jnp.swapaxes(so3.as_matrix(q), -1, -2)
    scale = _trace(rotation_t @ correlation) / spread_b
    return q, mean_a - scale[..., None] * so3.act(q, mean_b), jnp.log(scale)
