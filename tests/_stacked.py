"""One call for several cases in the tests' jitted check programs: XLA compiles a copy of an
operation's kernel for every call in a program, so calls of one operation on stacked cases
compile it once (with the same values)."""

import jax
import jax.numpy as jnp


def stacked(*cases):
    """Arrays or group elements (pytrees of one structure) stacked on a new leading axis."""
    return jax.tree_util.tree_map(lambda *parts: jnp.stack(parts), *cases)


def unstacked(batch, count):
    """The `count` cases along `batch`'s leading axis (an array or a group element)."""
    return [batch[i] for i in range(count)]


def at_zero_and_steps(f, steps):
    """`(f(0), f(+steps), f(-steps))` over the rows of `steps`, from one `jax.vmap` of `f` (one
    copy of its program where separate calls would trace one each): the value at the base point
    and the two sides of central differences."""
    zero = jnp.zeros_like(steps[0])
    values = jax.vmap(f)(jnp.concatenate([zero[None], steps, -steps]))
    plus, minus = jnp.split(values[1:], 2)
    return values[0], plus, minus
