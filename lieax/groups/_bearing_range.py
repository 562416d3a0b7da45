r"""Range and bearing of a point in a frame: the kernels behind `SE2.range` / `SE3.range` and
`SE3.bearing` (with `lieax.groups._so2.relative_bearing`, `SE2.bearing`'s), each a
`jax.custom_jvp` function of the point $d$ in the frame ($d = X^{-1} p$, the `transform_to`
kernels of `_se2` and `_se3`, whose rules carry the pose's local tangent to $\dot d$).

With $u = d / |d|$:

- range $r = |d|$, $\dot r = u^\top \dot d$ (GTSAM's `norm2` / `norm3`, Point2.cpp / Point3.cpp);
- planar bearing, the SO2 $(c, s) = u$ of angle $\theta = \mathrm{atan2}(d_y, d_x)$,
  $\dot\theta = (J u)^\top \dot d / |d|$ (GTSAM's `Rot2::relativeBearing`, Rot2.cpp:
  $H = (-d_y, d_x) / |d|^2$);
- spatial bearing, the unit vector $b = u$ (an `S2`, whose carrier is the raw derivative),
  $\dot b = (I - u u^\top)\,\dot d / |d|$ (GTSAM's `Unit3::FromPoint3`, Unit3.cpp, gives
  $B^\top$ times this in its own basis $B$).

At $d = 0$ (a point at the frame's origin) none of them is differentiable; each takes a
documented value with a zero derivative, never NaN: range 0, bearing the frame's x axis (SO2's
identity, $(1, 0, 0)$). GTSAM's `Rot2::relativeBearing` returns the identity with a zero
Jacobian as well (below $|d| = 10^{-5}$; lieax only at $d = 0$, exact elsewhere), its `norm2`
writes the Jacobian $(1, 1)$ there, and `norm3` and `Unit3` divide by zero. The "double where":
$d$ is divided by its largest magnitude $m = \max_i |d_i|$ before it is squared (no underflow or
overflow at any scale, float32 included), and where $m = 0$ every division sees the x axis
instead, so values and derivatives of any order stay finite.

`target_points` checks the targets of `SE2` and `SE3`'s bearing and range, in one place.
"""

import jax
import jax.numpy as jnp

from .._checks import broadcast_batch, check_last_axis, match_dtype
from .._linalg import dot
from ._base import AbstractGroup


def unit_and_length(d):
    r"""`(u, length, nonzero)` for vectors $d$ `(*batch, n)`: $u = d / |d|$ and $|d|$ where
    $d \ne 0$; $u = e_0$ (the x axis) and length 1 where $d = 0$ (`nonzero` `(*batch, 1)` false),
    so both are safe to divide by and to differentiate. Scaled by $\max_i |d_i|$ first."""
    largest = jnp.max(jnp.abs(d), axis=-1, keepdims=True)
    nonzero = largest > 0
    x_axis = jnp.zeros_like(d).at[..., 0].set(1)
    scaled = jnp.where(nonzero, d / jnp.where(nonzero, largest, 1), x_axis)
    size = jnp.sqrt(dot(scaled, scaled))[..., None]  # in [1, sqrt(n)]
    return scaled / size, jnp.where(nonzero, largest, 1) * size, nonzero


@jax.custom_jvp
def norm(d):
    r"""$|d|$ on the last axis, 0 at $d = 0$ (the range; module docstring)."""
    _, length, nonzero = unit_and_length(d)
    return jnp.where(nonzero, length, 0)[..., 0]


@norm.defjvp
def _norm_jvp(primals, tangents):
    r"""$\dot r = u^\top \dot d$; 0 at $d = 0$."""
    (d,), (d_dot,) = primals, tangents
    u, _, nonzero = unit_and_length(d)
    return norm(d), dot(jnp.where(nonzero, u, 0), d_dot)


@jax.custom_jvp
def direction(d):
    r"""$d / |d|$ for 3D vectors, the x axis $(1, 0, 0)$ at $d = 0$ (the spatial bearing)."""
    return unit_and_length(d)[0]


@direction.defjvp
def _direction_jvp(primals, tangents):
    r"""$\dot b = (\dot d - u\,(u^\top \dot d)) / |d|$, the raw derivative (S2's carrier); 0 at
    $d = 0$."""
    (d,), (d_dot,) = primals, tangents
    u, length, nonzero = unit_and_length(d)
    moved = (d_dot - u * dot(u, d_dot)[..., None]) / length
    return u, jnp.where(nonzero, moved, 0)


def target_points(pose, target, operation, dim):
    """The positions `pose.bearing` / `pose.range` (`operation`) are taken to: another pose's
    translation (of `pose`'s group) or points `(*batch, dim)` in `pose`'s dtype, whose batch
    broadcasts with `pose`'s; errors name the group and the operation."""
    group = type(pose).__name__
    if isinstance(target, AbstractGroup):
        pose._check_same_group(target, operation)
        points = target.translation()
    else:
        name = f"{group}.{operation} target"
        points = match_dtype(target, pose.dtype, name, f"the {group}")
        points = check_last_axis(points, dim, name, f"{dim}D points or an {group}")
    broadcast_batch(f"{group}.{operation}", pose.batch_shape, points.shape[:-1])
    return points
