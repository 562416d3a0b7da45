"""S2, unit directions in 3D (GTSAM's `Unit3`): a manifold, not a group.

Parameters: the unit vector $p$, shape `(*batch, 3)`; tangent $\\xi \\in \\mathbb{R}^2$ in the
orthonormal tangent basis $B_p$ (3×2, $B_p^\\top p = 0$, $B_p^\\top B_p = I$).

- Retraction (GTSAM math notes, Sec. 14.3; Absil et al.): $p \\oplus \\xi = (p + B_p\\xi) / |p + B_p\\xi|$;
  its derivative in $\\xi$ at 0 is $B_p$.
- Its inverse: $q \\ominus p = B_p^\\top q / (p^\\top q)$, so that `p.rplus(q.rminus(p)) == q` for $p^\\top q > 0$
  (from $\\alpha q = p + B_p\\xi$: project on $B_p$ and on $p$; notes Sec. 14.3). Undefined on the
  far hemisphere ($p^\\top q \\le 0$).
- Rotating a direction (notes Sec. 14.4): $q = R p$, Jacobian
  $[-B_{Rp}^\\top R [p]_\\times,\\ B_{Rp}^\\top R B_p]$ with respect to $(R, p)$ in local coordinates.
- The error between directions (notes Sec. 14.5): $e(p, q) = B_p^\\top q \\in \\mathbb{R}^2$, zero when
  $q = p$, with $\\partial e / \\partial q = B_p^\\top B_q$; `distance` is the geodesic angle.

The basis. A smooth field of tangent frames on the whole sphere does not exist (the hairy-ball
theorem); lieax uses one that is smooth (rational in $p$) everywhere except at the single point
$p^\\star = -r$, $r = (1, 2, 3)/\\sqrt{14}$, a direction unlikely in practice (unlike the axes:
gravity is often $-e_z$). It is the frame $[u_1, u_2]$ at $r$, $u_1 = (-2, 1, 0)/\\sqrt5$,
$u_2 = r \\times u_1$, carried to $p$ by the smallest rotation taking $r$ to $p$:
$$B_p u = u + k \\times u + \\frac{k \\times (k \\times u)}{1 + r^\\top p}, \\qquad k = r \\times p,$$
with $1 + r^\\top p$ evaluated as $|r + p|^2 / 2$ (exact on the sphere, and without cancellation
near $p^\\star$). $B_p$ is computed from $p / |p|$, so it depends on the direction only. GTSAM's
`Unit3::basis()` instead crosses $p$ with the axis of its smallest component: deterministic but
discontinuous where that axis changes; `lieax.conventions` converts between the two charts (they
differ by a 2×2 rotation of the tangent coordinates, so Jacobians at the linearization point agree
after that rotation; GTSAM's `retract` is also the exponential map rather than this normalizing
retraction, which agrees with it to first order).

Tangent carrier: the JAX tangent of the parameter leaf is the raw derivative $\\dot p$ (no
conversion at the API), read as the local tangent $B_p^\\top \\dot p$ and seeded as $B_p\\xi$. Every
operation is a few rational functions and square roots of $p$ (no trigonometry), so JAX
differentiates them directly; rotations go through SO3's kernels and their closed-form rules.
"""

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_last_axis
from .._linalg import cross, dot
from . import _so3 as so3
from ._base import AbstractManifold
from ._so3 import SO3

# ---- the tangent basis ---------------------------------------------------------------------------

_REFERENCE = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)  # r; the basis is singular at -r only
_U1 = np.array([-2.0, 1.0, 0.0]) / np.sqrt(5.0)
_U2 = np.cross(_REFERENCE, _U1)
SINGULAR_DIRECTION = tuple(-_REFERENCE)  # where `basis` is undefined (documented, tested)


def _normalize(v):
    return v / jnp.sqrt(dot(v, v))[..., None]


def basis(p):
    """$B_p$, shape `(*batch, 3, 2)`: the frame $[u_1, u_2]$ at $r$ moved to $p/|p|$ by the smallest
    rotation (module docstring). Finite everywhere (the identity frame at $-r$ itself)."""
    p = _normalize(p)
    r = jnp.asarray(_REFERENCE, dtype=p.dtype)
    k = cross(jnp.broadcast_to(r, p.shape), p)
    plus = p + r
    one_plus_cos = 0.5 * dot(plus, plus)[..., None]
    safe = jnp.where(one_plus_cos > 0.0, one_plus_cos, 1.0)

    def moved(u):
        u = jnp.broadcast_to(jnp.asarray(u, dtype=p.dtype), p.shape)
        ku = cross(k, u)
        return u + ku + cross(k, ku) / safe

    return jnp.stack([moved(_U1), moved(_U2)], axis=-1)


def to_local(p, p_dot):
    """The local tangent $B_p^\\top \\dot p$ of a raw derivative."""
    return jnp.sum(basis(p) * p_dot[..., :, None], axis=-2)


def from_local(p, xi):
    """The raw derivative $B_p \\xi$ that moves $p$ along the local tangent $\\xi$."""
    return jnp.sum(basis(p) * xi[..., None, :], axis=-1)


def retract(p, xi):
    """$p \\oplus \\xi = (p + B_p \\xi) / |p + B_p \\xi|$."""
    return _normalize(p + from_local(p, xi))


def inverse_retract(q, p):
    """$q \\ominus p = B_p^\\top q / (p^\\top q)$ (for $p^\\top q > 0$)."""
    return to_local(p, q) / dot(p, q)[..., None]


def error(p, q):
    """$e(p, q) = B_p^\\top q$."""
    return to_local(p, q)


def distance(p, q):
    """The angle between $p$ and $q$, $\\mathrm{atan2}(|p \\times q|, p^\\top q)$ (derivative 0 at $p = q$,
    where it is not differentiable)."""
    c = cross(p, q)
    squared = dot(c, c)
    positive = squared > 0.0
    sine = jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)
    return jnp.arctan2(sine, dot(p, q))


class S2(AbstractManifold):
    """Unit directions in 3D: parameters the unit vector `(x, y, z)`, shape `(*batch, 3)`; tangent
    the 2D coordinates in the basis `basis()`, shape `(*batch, 2)`. A manifold, not a group: it has
    `rplus` / `rminus` (so `lieax.jacobian`, `lieax.rplus` and the solvers accept it), rotations
    act on it, and there is no `compose`, `inverse` or `exp`."""

    tangent_dim = 2
    parameters_dim = 3
    space_dim = 3
    parameters_layout = "unit vector xyz"

    _local_from_tangent = staticmethod(to_local)
    _tangent_from_local = staticmethod(from_local)

    @classmethod
    def from_vector(cls, vector):
        """The direction of nonzero vectors of shape `(*batch, 3)` (normalized)."""
        vector = check_last_axis(vector, 3, "S2.from_vector vector", "3D vectors")
        return cls(_normalize(vector))

    @classmethod
    def sample_uniform(cls, key, batch_shape=(), dtype=None):
        """Directions uniform on the sphere (normalized standard normal vectors)."""
        return cls._wrap(_normalize(jax.random.normal(key, (*tuple(batch_shape), 3), dtype=dtype)))

    def unit_vector(self) -> jax.Array:
        """$p$, shape `(*batch, 3)` (the same as `parameters()`)."""
        return self.parameters()

    def normalize(self):
        """$p / |p|$, for parameters that may have drifted off the sphere."""
        return self._wrap(_normalize(self._params))

    def basis(self) -> jax.Array:
        """$B_p$, shape `(*batch, 3, 2)`: orthonormal, orthogonal to $p$, smooth in $p$ except at
        `SINGULAR_DIRECTION`."""
        return basis(self._params)

    def rplus(self, tangent):
        """$p \\oplus \\xi = (p + B_p\\xi)/|p + B_p\\xi|$."""
        tangent = check_last_axis(tangent, 2, "S2 tangent")
        return self._wrap(retract(self._params, tangent))

    def rminus(self, other) -> jax.Array:
        """$p \\ominus q = B_q^\\top p / (q^\\top p)$ (`self` is $p$), so `other.rplus(self.rminus(other))
        == self`; defined for $q^\\top p > 0$."""
        self._check_same(other, "rminus")
        return inverse_retract(self._params, other._params)

    def error(self, other) -> jax.Array:
        """$e(p, q) = B_p^\\top q$ with `self` $= p$, `other` $= q$: zero at $q = p$, Jacobian
        $B_p^\\top B_q$ with respect to $q$ (GTSAM's `Unit3::errorVector`)."""
        self._check_same(other, "error")
        return error(self._params, other._params)

    def distance(self, other) -> jax.Array:
        """The geodesic angle between two directions, in $[0, \\pi]$."""
        self._check_same(other, "distance")
        return distance(self._params, other._params)

    def dot(self, other) -> jax.Array:
        self._check_same(other, "dot")
        return dot(self._params, other._params)

    def rotate(self, rotation: SO3):
        """$R p$ (through SO3's action and its closed-form rule), broadcasting batch shapes; local
        Jacobian $[-B_{Rp}^\\top R [p]_\\times,\\ B_{Rp}^\\top R B_p]$."""
        if not isinstance(rotation, SO3):
            raise TypeError(f"S2.rotate needs an SO3, got {type(rotation).__name__}.")
        return self._wrap(so3.act(rotation._params, self._params))

    def unrotate(self, rotation: SO3):
        """$R^\\top p$."""
        return self.rotate(rotation.inverse())

    def _check_same(self, other, operation):
        if not isinstance(other, S2):
            raise TypeError(f"S2.{operation} needs another S2, got {type(other).__name__}.")
