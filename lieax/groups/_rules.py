"""Small helpers for writing `jax.custom_jvp` rules with symbolic zeros.

Every kernel's rule is registered with `symbolic_zeros=True`, so a tangent that is known to be zero
(a constant point cloud, a pose that is not differentiated) arrives as a `SymbolicZero` and its
term is skipped instead of being multiplied out.
"""

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero


def is_zero(tangent) -> bool:
    return isinstance(tangent, SymbolicZero)


def local_tangent(to_local, params, params_dot):
    """The right-local tangent of a parameter tangent, or `None` when it is a symbolic zero."""
    return None if is_zero(params_dot) else to_local(params, params_dot)


def add(*terms):
    """Sum of the terms that are not `None` (`None` if all are)."""
    present = [t for t in terms if t is not None]
    if not present:
        return None
    total = present[0]
    for t in present[1:]:
        total = total + t
    return total


def finish(primal_out: jax.Array, tangent_out):
    """The rule's `(primal, tangent)` pair, the tangent broadcast to the primal's shape."""
    if tangent_out is None:
        return primal_out, jnp.zeros_like(primal_out)
    return primal_out, jnp.broadcast_to(tangent_out, primal_out.shape).astype(primal_out.dtype)


def defjvp(kernel):
    """Decorator registering a rule for `kernel` that receives symbolic zeros."""

    def register(rule):
        kernel.defjvp(rule, symbolic_zeros=True)
        return rule

    return register
