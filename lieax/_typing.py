"""The type aliases of lieax's public signatures (read by type checkers and the API docs only)."""

from typing import Any

# A pytree (JAX's tuples, lists, dicts, named tuples and registered classes, nested) whose leaves
# are lieax groups and arrays. `Any`, as optax and equinox spell it: a precise recursive type
# would reject the user's own registered pytree classes, and no checker can follow
# `jax.tree_util` registration.
PyTree = Any
