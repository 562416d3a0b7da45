r"""S2, unit directions in 3D (GTSAM's `Unit3`): a manifold, not a group.

Parameters: the unit vector $p$, shape `(*batch, 3)`; tangent $\xi \in \mathbb{R}^2$ in the
orthonormal tangent basis $B_p$ (3×2, $B_p^\top p = 0$, $B_p^\top B_p = I$).

- Retraction (GTSAM math notes, Sec. 14.3; Absil et al.): $p \oplus \xi = (p + B_p\xi) / |p + B_p\xi|$;
  its derivative in $\xi$ at 0 is $B_p$.
- Its inverse: $q \ominus p = B_p^\top q / (p^\top q)$, so that `p.rplus(q.rminus(p)) == q` for $p^\top q > 0$
  (from $\alpha q = p + B_p\xi$: project on $B_p$ and on $p$; notes Sec. 14.3). Undefined on the
  far hemisphere ($p^\top q \le 0$).
- Rotating a direction (notes Sec. 14.4): $q = R p$, Jacobian
  $[-B_{Rp}^\top R [p]_\times,\ B_{Rp}^\top R B_p]$ with respect to $(R, p)$ in local coordinates.
- The error between directions (notes Sec. 14.5): $e(p, q) = B_p^\top q \in \mathbb{R}^2$, zero when
  $q = p$, with $\partial e / \partial q = B_p^\top B_q$; `distance` is the geodesic angle.

The basis. A continuous field of tangent frames on the whole sphere does not exist (the
hairy-ball theorem), and one that is smooth everywhere but at one point turns ever faster near it
(its derivative grows like the inverse distance), so it cannot be computed accurately there. lieax
uses two charts. Away from $-r$, $r = (1, 2, 3)/\sqrt{14}$ (a direction unlikely in practice,
unlike the axes: gravity is often $-e_z$), it is the frame $[u_1, u_2]$ at $r$,
$u_1 = (-2, 1, 0)/\sqrt5$, $u_2 = r \times u_1$, carried to $p$ by the smallest rotation taking $r$
to $p$:
$$B_p u = u + k \times u + \frac{k \times (k \times u)}{1 + r^\top p}, \qquad k = r \times p,$$
with $1 + r^\top p$ evaluated as $|r + p|^2 / 2$ (exact on the sphere). Within 45.6° of $-r$
($1 + r^\top p < 0.3$) it is instead the frame $[u_1, -u_2]$ at $-r$ carried the same way from $-r$
(the formula with $r \to -r$). Each chart is used only where its denominator is at least 0.3, so
the basis is orthonormal and tangent to rounding everywhere, in float32 and float64, and rational
in $p$ on each side of the switching circle $1 + r^\top p = 0.3$; it jumps across that circle (by a
rotation of the tangent coordinates; both frames are right-handed, $b_1 \times b_2 = p$). The
circle passes at least 4.6° from every direction with components in $\{-1, 0, 1\}$ (the axes,
the diagonals). Every derivative (the retraction's, `rminus`'s, `rotate`'s) is the derivative of
the chart on the side of its linearization point, so Jacobians there are exact; a tangent is
meaningful at the point where it was computed (as with any chart), and an optimizer that crosses
the circle simply continues in the other chart. $B_p$ is computed from $p / |p|$, so it depends
on the direction only. GTSAM's
`Unit3::basis()` instead crosses $p$ with the axis of its smallest component: deterministic but
discontinuous where that axis changes; `lieax.conventions` converts between the two charts (they
differ by a 2×2 rotation of the tangent coordinates, so Jacobians at the linearization point agree
after that rotation; GTSAM's `retract` is also the exponential map rather than this normalizing
retraction, which agrees with it to first order).

Tangent carrier: the JAX tangent of the parameter leaf is the raw derivative $\dot p$ (no
conversion at the API), read as the local tangent $B_p^\top \dot p$ and seeded as $B_p\xi$. Every
operation is a few rational functions and square roots of $p$ (no trigonometry), so JAX
differentiates them directly; rotations go through SO3's kernels and their closed-form rules.
"""

from collections.abc import Sequence
from typing import Self

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike, DTypeLike

from .._checks import broadcast_batch, check_last_axis, check_same_dtype, match_dtype
from .._linalg import cross, dot
from . import _so3 as so3
from ._base import AbstractManifold
from ._so3 import SO3

# ---- the tangent basis ---------------------------------------------------------------------------

_REFERENCE = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)  # r
_U1 = np.array([-2.0, 1.0, 0.0]) / np.sqrt(5.0)
_U2 = np.cross(_REFERENCE, _U1)
REFERENCE = tuple(_REFERENCE)  # the frame is carried from r, and from -r near -r (tested)
SWITCH = 0.3  # the chart at -r is used where 1 + r·p < SWITCH (within 45.6° of -r)


def _normalize(v):
    return v / jnp.sqrt(dot(v, v))[..., None]


def _carried(reference, frame, p):
    r"""The frame `frame` (two unit vectors) at the unit `reference` $r$, moved to the unit $p$ by the
    smallest rotation: $u + k \times u + k \times (k \times u) / (1 + r^\top p)$, $k = r \times p$."""
    r = jnp.broadcast_to(jnp.asarray(reference, dtype=p.dtype), p.shape)
    k = cross(r, p)
    plus = p + r
    one_plus_cos = 0.5 * dot(plus, plus)[..., None]

    def moved(u):
        u = jnp.broadcast_to(jnp.asarray(u, dtype=p.dtype), p.shape)
        ku = cross(k, u)
        return u + ku + cross(k, ku) / one_plus_cos

    return jnp.stack([moved(u) for u in frame], axis=-1)


def basis(p):
    """$B_p$, shape `(*batch, 3, 2)`: the frame $[u_1, u_2]$ at $r$ moved to $p/|p|$ by the smallest
    rotation, or within 45.6° of $-r$ the frame $[u_1, -u_2]$ at $-r$ moved from there (module
    docstring). Each chart is evaluated at its own reference point where the other is used, so
    neither divides by a small number, in values or derivatives."""
    p = _normalize(p)
    r = jnp.asarray(_REFERENCE, dtype=p.dtype)
    plus = p + r
    near = (0.5 * dot(plus, plus) < SWITCH)[..., None]
    from_r = _carried(_REFERENCE, (_U1, _U2), jnp.where(near, r, p))
    from_minus_r = _carried(-_REFERENCE, (_U1, -_U2), jnp.where(near, p, -r))
    return jnp.where(near[..., None], from_minus_r, from_r)


def to_local(p, p_dot):
    r"""The local tangent $B_p^\top \dot p$ of a raw derivative."""
    return jnp.sum(basis(p) * p_dot[..., :, None], axis=-2)


def from_local(p, xi):
    r"""The raw derivative $B_p \xi$ that moves $p$ along the local tangent $\xi$."""
    return jnp.sum(basis(p) * xi[..., None, :], axis=-1)


def retract(p, xi):
    r"""$p \oplus \xi = (p + B_p \xi) / |p + B_p \xi|$."""
    return _normalize(p + from_local(p, xi))


def inverse_retract(q, p):
    r"""$q \ominus p = B_p^\top q / (p^\top q)$ (for $p^\top q > 0$)."""
    return to_local(p, q) / dot(p, q)[..., None]


def error(p, q):
    r"""$e(p, q) = B_p^\top q$."""
    return to_local(p, q)


def distance(p, q):
    r"""The angle between $p$ and $q$, $\mathrm{atan2}(|p \times q|, p^\top q)$ (derivative 0 at $p = q$,
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
    def from_vector(cls, vector: ArrayLike) -> Self:
        """The direction of nonzero vectors of shape `(*batch, 3)` (normalized)."""
        vector = check_last_axis(vector, 3, "S2.from_vector vector", "3D vectors")
        return cls(_normalize(vector))

    @classmethod
    def sample_uniform(
        cls, key: ArrayLike, batch_shape: Sequence[int] = (), dtype: DTypeLike | None = None
    ) -> Self:
        """Directions uniform on the sphere (normalized standard normal vectors)."""
        return cls._wrap(_normalize(jax.random.normal(key, (*tuple(batch_shape), 3), dtype=dtype)))

    def unit_vector(self) -> jax.Array:
        """$p$, shape `(*batch, 3)` (the same as `parameters()`)."""
        return self.parameters()

    def normalize(self) -> Self:
        """$p / |p|$, for parameters that may have drifted off the sphere."""
        return self._wrap(_normalize(self._params))

    def basis(self) -> jax.Array:
        r"""$B_p$, shape `(*batch, 3, 2)`: orthonormal, orthogonal to $p$, rational in $p$ on each side
        of the circle $1 + r^\top p = 0.3$ around $-r$ (module docstring)."""
        return basis(self._params)

    def rplus(self, tangent: ArrayLike) -> Self:
        r"""$p \oplus \xi = (p + B_p\xi)/|p + B_p\xi|$, broadcasting batch shapes."""
        tangent = match_dtype(tangent, self.dtype, "S2.rplus tangent", "the S2")
        tangent = check_last_axis(tangent, 2, "S2.rplus tangent")
        broadcast_batch("S2.rplus", self.batch_shape, tangent.shape[:-1])
        return self._wrap(retract(self._params, tangent))

    def rminus(self, other: Self) -> jax.Array:
        r"""$p \ominus q = B_q^\top p / (q^\top p)$ (`self` is $p$), so `other.rplus(self.rminus(other))
        == self`; defined for $q^\top p > 0$."""
        self._check_same(other, "rminus")
        return inverse_retract(self._params, other._params)

    def error(self, other: Self) -> jax.Array:
        r"""$e(p, q) = B_p^\top q$ with `self` $= p$, `other` $= q$: zero at $q = p$, Jacobian
        $B_p^\top B_q$ with respect to $q$ (GTSAM's `Unit3::errorVector`)."""
        self._check_same(other, "error")
        return error(self._params, other._params)

    def distance(self, other: Self) -> jax.Array:
        r"""The geodesic angle between two directions, in $[0, \pi]$."""
        self._check_same(other, "distance")
        return distance(self._params, other._params)

    def dot(self, other: Self) -> jax.Array:
        self._check_same(other, "dot")
        return dot(self._params, other._params)

    def rotate(self, rotation: SO3) -> Self:
        r"""$R p$ (through SO3's action and its closed-form rule), broadcasting batch shapes; local
        Jacobian $[-B_{Rp}^\top R [p]_\times,\ B_{Rp}^\top R B_p]$."""
        if not isinstance(rotation, SO3):
            raise TypeError(f"S2.rotate needs an SO3, got {type(rotation).__name__}.")
        check_same_dtype("S2.rotate", self.dtype, rotation.dtype)
        broadcast_batch("S2.rotate", self.batch_shape, rotation.batch_shape)
        return self._wrap(so3.act(rotation._params, self._params))

    def unrotate(self, rotation: SO3) -> Self:
        r"""$R^\top p$."""
        return self.rotate(rotation.inverse())

    def _check_same(self, other, operation):
        if not isinstance(other, S2):
            raise TypeError(f"S2.{operation} needs another S2, got {type(other).__name__}.")
        check_same_dtype(f"S2.{operation}", self.dtype, other.dtype)
        broadcast_batch(f"S2.{operation}", self.batch_shape, other.batch_shape)
