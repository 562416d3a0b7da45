"""A visiting order of a point cloud along a space-filling curve: consecutive points in it are
near each other (the ICP loop visits its source in this order, `lieax.icp._loop`)."""

import math

import jax.numpy as jnp


def spatial_order(points, mask=None):
    """A permutation of the points along a Morton (Z-order) curve over their bounding box (masked
    points last): one 32-bit integer sort of keys that pack the curve position (as many bits per
    axis as fit beside the point's index) with the index."""
    n = points.shape[0]
    valid = jnp.ones((n,), bool) if mask is None else mask
    index_bits = max(1, math.ceil(math.log2(max(n, 2))))
    per_axis = max(1, (32 - index_bits) // 3)
    lo = jnp.min(jnp.where(valid[:, None], points, jnp.inf), axis=0)
    hi = jnp.max(jnp.where(valid[:, None], points, -jnp.inf), axis=0)
    span = jnp.max(jnp.where(jnp.isfinite(hi - lo), hi - lo, 0.0))
    scale = jnp.where(span > 0, (2**per_axis - 1) / jnp.where(span > 0, span, 1.0), 0.0)
    cell = jnp.clip(jnp.floor((points - lo) * scale), 0, 2**per_axis - 1).astype(jnp.uint32)
    code = jnp.zeros((n,), jnp.uint32)
    for bit in range(per_axis):  # interleave: bit b of axis a goes to position 3b + a
        for axis in range(3):
            code = code | (((cell[:, axis] >> bit) & 1) << (3 * bit + axis))
    code = jnp.where(valid, code, 2 ** (3 * per_axis) - 1).astype(jnp.uint32)
    key = jnp.sort((code << index_bits) | jnp.arange(n, dtype=jnp.uint32))
    return (key & (2**index_bits - 1)).astype(jnp.int32)
