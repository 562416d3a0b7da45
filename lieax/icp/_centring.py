r"""Centring clouds for the ICP solves: the loop and the implicit derivatives work on the source
about its centroid and the target about its own, with the pose conjugated to match, so that their
results do not depend on where the clouds sit (georeferenced scans lie 1e4-1e6 m from the
origin).

About the origin, the Jacobian rows $[R, -R[s_i]_\times]$ of points $s_i$ a distance $L$ away
make the rotation block of the 6x6 normal equations $L^2$ times the translation block: at
$L = 10^4$ m a ridge at rounding level relative to the largest diagonal entry (ICP's own solve
before it used `lieax.lstsq._normal_equations.solve_spd`) swamps the rotation about the centroid, and the iterations stop short of it.
"""

import jax
import jax.numpy as jnp

from .._linalg import quat_to_matrix


def centroid(points, mask):
    """The mean of the rows of `points` `(n, 3)` where `mask` `(n,)` (the origin for none), in the
    points' dtype. Any centre near the cloud serves: the solves map back with the same one."""
    count = jnp.maximum(jnp.sum(mask.astype(points.dtype)), 1)  # (a float sum: one kernel)
    return jnp.sum(jnp.where(mask[:, None], points, 0.0), axis=0) / count


def centred_pose(params, source_centre, target_centre):
    r"""$\mathrm{Tr}(-c_t)\,T\,\mathrm{Tr}(c_s)$ for the SE3 parameters `(w, x, y, z, tx, ty, tz)`
    of $T = (R, t)$: the same rotation, translation $R c_s + t - c_t$. It maps the source about
    $c_s$ into the target about $c_t$; the negated centres map back."""
    rotation = quat_to_matrix(params[:4])
    shift = jnp.matmul(rotation, source_centre, precision=jax.lax.Precision.HIGHEST)
    return params.at[4:].set(params[4:] + (shift - target_centre))


def uncentred_tangent(tangent, source_centre):
    r"""The right tangent $\delta$ of $T$ for a right tangent $\delta'$ of the centred pose
    $T' = \mathrm{Tr}(-c_t)\,T\,\mathrm{Tr}(c_s)$: $T' \mathrm{Exp}(\delta') =
    \mathrm{Tr}(-c_t)\,T\,\mathrm{Exp}(\delta)\,\mathrm{Tr}(c_s)$ gives
    $\delta = \mathrm{Ad}_{\mathrm{Tr}(c_s)}\,\delta'$, i.e. $(v' + c_s \times \omega', \omega')$
    for $\delta' = (v', \omega')$ (the adjoint $[[R, [t]_\times R], [0, R]]$ of SE(3), Solà et al. 2018, appendix D, at
    $R = I$, $t = c_s$)."""
    v, omega = tangent[..., :3], tangent[..., 3:]
    return jnp.concatenate([v + jnp.cross(source_centre, omega), omega], axis=-1)
