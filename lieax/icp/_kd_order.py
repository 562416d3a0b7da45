"""The points of a k-d tree of equal leaves, in leaf order: median splits on the widest axis, level
by level, under `jit` with fixed shapes (`lieax.icp._neighbors` builds its neighbour graph on
them).

Why this shape: on the CPU, XLA's float and key-value sorts are slow (tens of ns per element), so
each level sorts packed 32-bit integer keys.
"""

import math

import jax
import jax.numpy as jnp


def tree_shape(n: int, leaf_size: int) -> tuple:
    """`(depth, leaf_size)` of the tree over `n` points: `2**depth` leaves of `ceil(n / 2**depth)`
    points, the fewest leaves with at most `leaf_size` points each."""
    depth = max(0, math.ceil(math.log2(max(n, 1) / leaf_size)))
    return depth, max(1, math.ceil(n / 2**depth))


def kd_order(points, valid, depth, size):
    """Median splits on the widest axis, level by level (one `fori_loop` body for every level).

    Each level sorts all slots once by a packed 32-bit key: the node in the high bits, the
    coordinate along the node's widest axis quantized to `32 - ceil(log2 N)` bits, then the position
    within the node (an integer sort; XLA's float and key-value sorts are 10-30x slower on the
    CPU). Invalid points get the largest key, so they sort last in their node.

    **Returns:** `(points, valid, order)`, slots in leaf order.
    """
    total = points.shape[0]
    leaves = 2**depth
    index_bits = max(1, math.ceil(math.log2(total)))
    key_bits = 32 - index_bits
    top = 2**key_bits - 1
    slot = jnp.arange(total, dtype=jnp.uint32)
    # One array, one gather per level: coordinates, original index (exact in float32 below 2**24),
    # and validity.
    packed = jnp.concatenate(
        [
            points,
            jnp.arange(total, dtype=points.dtype)[:, None],
            valid[:, None].astype(points.dtype),
        ],
        axis=1,
    )

    def level(depth_here, packed):
        here = depth_here.astype(jnp.uint32)
        coords, ok = packed[:, :3], packed[:, 4] > 0
        width = jnp.uint32(size) << (jnp.uint32(depth) - here)
        segment = slot // width
        ids = segment.astype(jnp.int32)
        lo = jax.ops.segment_min(
            jnp.where(ok[:, None], coords, jnp.inf), ids, leaves, indices_are_sorted=True
        )
        hi = jax.ops.segment_max(
            jnp.where(ok[:, None], coords, -jnp.inf), ids, leaves, indices_are_sorted=True
        )
        extent = jnp.where(jnp.isfinite(hi - lo), hi - lo, 0.0)
        axis = jnp.where(
            (extent[:, 0] >= extent[:, 1]) & (extent[:, 0] >= extent[:, 2]),
            0,
            jnp.where(extent[:, 1] >= extent[:, 2], 1, 2),
        ).astype(jnp.int32)
        point_axis = axis[ids]
        coordinate = pick_axis(coords, point_axis)
        lo_axis = pick_axis(lo, axis)[ids]
        span = pick_axis(extent, axis)[ids]
        scale = jnp.where(span > 0, top / jnp.where(span > 0, span, 1.0), 0.0)
        quantized = jnp.clip(jnp.floor((coordinate - lo_axis) * scale), 0, top - 1)
        quantized = jnp.where(ok, quantized, top).astype(jnp.uint32)
        position_bits = jnp.uint32(index_bits) - here
        high = jnp.where(here > 0, segment << (jnp.uint32(key_bits) + position_bits), 0)
        key = jnp.sort(high | (quantized << position_bits) | (slot - segment * width))
        owner = jnp.where(here > 0, key >> (jnp.uint32(key_bits) + position_bits), 0)
        position = key & ((jnp.uint32(1) << position_bits) - 1)
        packed = packed[(owner * width + position).astype(jnp.int32)]
        return packed

    packed = jax.lax.fori_loop(0, depth, level, packed)
    valid = packed[:, 4] > 0
    order = jnp.where(valid, packed[:, 3], 0).astype(jnp.int32)
    return packed[:, :3], valid, order


def pick_axis(values, axis):
    """`values[i, axis[i]]` for `(n, 3)` values, by selection (no gather)."""
    return jnp.where(axis == 0, values[:, 0], jnp.where(axis == 1, values[:, 1], values[:, 2]))
