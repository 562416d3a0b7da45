r"""Nearest neighbours under `jit` with fixed shapes: an index built once per target cloud.

The index (`NeighborIndex`, a pytree of arrays) holds

- a k-d tree with `2**L` leaves of equal size `B` (median splits on the widest axis), its points
  stored leaf by leaf ("slots"), padding and masked points marked invalid, and the bounding box
  of every node;
- a graph: each point's `degree` nearest neighbours, exact up to a *coverage* radius (every target
  point closer than `coverage[c]` to point `c` is in its list), plus `links` longer edges to the
  nearest point of each nearby leaf (range scans are sampled along lines; these edges cross them).

A query follows three steps, all fixed-shape and batchable:

1. **seed**: a beam search down the tree (the `width` nearest leaves by box distance), or, for a
   moving query (`track`), the better of its previous match and the representative point of the
   leaf it now falls in;
2. **descend** the graph: move to the best neighbour while that gets closer (one or two steps
   once warm-started);
3. **certify**: at the final point $c$ with distance $d$, any target point closer than
   $d' = \min(d, r)$ lies within $d + d'$ of $c$, so if $d + d' \le$ `coverage[c]` the match is
   exact (exact within the radius $r$: a query beyond $r$ is certified to have no neighbour
   within $r$). The uncertified queries (10-20% on range scans: holes, borders, queries far from
   the surface) are gathered and searched in the 8 leaves a beam search keeps, which certifies
   them by the beam's reach; what is still uncertified is searched leaf by leaf.

`nearest(index, queries, radius=r)` runs all three and is exact within $r$ (up to ties);
`track` alone is the cheap step used inside the ICP iterations. Exactness and costs are measured
in `benchmarks/icp.py` and `benchmarks/neighbors.py`; this is the `search="graph"` backend of
`lieax.icp._search` (beside a voxel grid, a host k-d tree and brute force).

Why this shape: on the CPU, XLA's float and key-value sorts, `top_k`, and reductions fused with
their producer are slow (tens of ns per element), and a per-query tree walk under `vmap` runs as
many steps as the slowest query. So the build sorts packed 32-bit integer keys, selects nearest
candidates with a compare-exchange network over packed keys, and every query step is a row
gather plus short elementwise work.
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ._coordinates import squared_norms

_MAX_INDEX_BITS = 24  # 2**24 points at most: the kd sort packs an 8-bit key with the position


class NeighborIndex(NamedTuple):
    """A target cloud prepared for nearest-neighbour queries (see the module docstring).

    Shapes: `N = leaves * B` slots, `D = degree`.

    **Fields:**

    - `points`: `(N, 3)` the target points in leaf order; invalid slots hold `inf`.
    - `order`: `(N,)` int32, the index in the original cloud of each slot (0 for invalid slots).
    - `valid`: `(N,)` bool.
    - `split_axis`, `split_value`: `(leaves - 1,)` (at least 1) the tree's internal nodes, in heap
      order; a query goes right when `q[axis] > value`.
    - `node_lo`, `node_hi`: `(2 * leaves - 1, 3)` bounding boxes of the valid points under every
      node of the tree, in heap order (the leaves last); empty nodes hold `(inf, -inf)`.
    - `graph`: `(N, D)` int32, the slots of each point's nearest neighbours (itself excluded).
    - `graph_points`: `(N, 3, D)` their coordinates, coordinate-major (one row gather per step).
    - `coverage`: `(N,)` every valid target point closer than this to the slot is in its list.
    - `representative`: `(leaves,)` int32, the slot of the valid point nearest to the centre of
      each leaf's box (where `track` restarts a query that moved into that leaf).
    """

    points: jax.Array
    order: jax.Array
    valid: jax.Array
    split_axis: jax.Array
    split_value: jax.Array
    node_lo: jax.Array
    node_hi: jax.Array
    graph: jax.Array
    graph_points: jax.Array
    coverage: jax.Array
    representative: jax.Array

    @property
    def leaves(self) -> int:
        return (self.node_lo.shape[-2] + 1) // 2

    @property
    def leaf_size(self) -> int:
        return self.points.shape[-2] // self.leaves

    @property
    def depth(self) -> int:
        return round(math.log2(self.leaves))

    @property
    def degree(self) -> int:
        return self.graph.shape[-1]


class Neighbors(NamedTuple):
    """The nearest target point of each query.

    **Fields:**

    - `index`: `(n,)` int32, index of the nearest point in the original target cloud.
    - `slot`: `(n,)` int32, the same point's slot in the `NeighborIndex` (for warm starts).
    - `distance`: `(n,)` Euclidean distance to it (`inf` where the target has no valid point).
    - `certified`: `(n,)` bool, the match is proven exact within the search radius.
    """

    index: jax.Array
    slot: jax.Array
    distance: jax.Array
    certified: jax.Array


def tree_shape(n: int, leaf_size: int) -> tuple:
    """`(depth, leaf_size)` of the tree over `n` points: `2**depth` leaves of `ceil(n / 2**depth)`
    points, the fewest leaves with at most `leaf_size` points each."""
    depth = max(0, math.ceil(math.log2(max(n, 1) / leaf_size)))
    return depth, max(1, math.ceil(n / 2**depth))


# ---- build --------------------------------------------------------------------------------------


def build_index(
    points, mask=None, *, leaf_size=16, degree=8, links=4, adjacent_leaves=16
) -> NeighborIndex:
    """Prepare `points` (shape `(n, 3)`) for nearest-neighbour queries; runs under `jit` and `vmap`.

    **Arguments:**

    - `points`: the target cloud. Rows where `mask` is False are ignored (padding).
    - `leaf_size`: largest number of points per leaf of the tree.
    - `degree`: nearest neighbours per point in the descent graph.
    - `links`: further edges per point, to the nearest point of each of its nearest other leaves.
    - `adjacent_leaves`: leaves searched around each leaf when the graph is built.

    **Returns:** a `NeighborIndex`.
    """
    points = jnp.asarray(points)
    n = points.shape[0]
    if n >= 2**_MAX_INDEX_BITS:
        raise ValueError(f"build_index handles fewer than {2**_MAX_INDEX_BITS} points, got {n}.")
    valid = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)
    depth, size = tree_shape(n, leaf_size)
    slots = size * 2**depth
    pad = slots - n
    points = jnp.where(valid[:, None], points, jnp.inf)
    points = jnp.concatenate([points, jnp.full((pad, 3), jnp.inf, points.dtype)])
    valid = jnp.concatenate([valid, jnp.zeros((pad,), bool)])
    points, valid, order, split_axis, split_value = _build_tree(points, valid, depth, size)

    leaves = 2**depth
    blocks = points.reshape(leaves, size, 3)
    block_valid = valid.reshape(leaves, size, 1)
    leaf_lo = jnp.min(jnp.where(block_valid, blocks, jnp.inf), axis=1)
    leaf_hi = jnp.max(jnp.where(block_valid, blocks, -jnp.inf), axis=1)
    # Every node's box in one scatter: leaf j lies under node 2**l - 1 + (j >> (depth - l)).
    levels = jnp.arange(depth + 1, dtype=jnp.int32)
    ancestors = (2**levels - 1) + (jnp.arange(leaves, dtype=jnp.int32)[:, None] >> (depth - levels))
    node_lo = jax.ops.segment_min(
        jnp.repeat(leaf_lo, depth + 1, axis=0), ancestors.reshape(-1), 2 * leaves - 1
    )
    node_hi = jax.ops.segment_max(
        jnp.repeat(leaf_hi, depth + 1, axis=0), ancestors.reshape(-1), 2 * leaves - 1
    )
    adjacent, reach2 = _beam(
        node_lo, node_hi, leaf_lo, leaf_hi, depth, min(adjacent_leaves, leaves),
        own_leaf=jnp.arange(leaves, dtype=jnp.int32),
    )  # fmt: skip
    graph, coverage = _neighbor_graph(
        points, valid, adjacent, jnp.sqrt(reach2), size, degree, links
    )
    graph_points = jnp.transpose(points[graph], (0, 2, 1))
    centre = 0.5 * (leaf_lo + leaf_hi)
    d2 = jnp.where(block_valid[..., 0], jnp.sum((blocks - centre[:, None]) ** 2, axis=-1), jnp.inf)
    representative = jnp.arange(leaves, dtype=jnp.int32) * size + jnp.argmin(d2, axis=1).astype(
        jnp.int32
    )
    return NeighborIndex(
        points, order, valid, split_axis, split_value, node_lo, node_hi, graph, graph_points,
        coverage, representative,
    )  # fmt: skip


def _build_tree(points, valid, depth, size):
    """Median splits on the widest axis, level by level (one `fori_loop` body for every level).

    Each level sorts all slots once by a packed 32-bit key: the node in the high bits, the
    coordinate along the node's widest axis quantized to `32 - ceil(log2 N)` bits, then the position
    within the node (an integer sort; XLA's float and key-value sorts are 10-30x slower on the
    CPU). Invalid points get the largest key, so they sort last in their node, and a query is sent
    right only when the right half holds a valid point.

    **Returns:** `(points, valid, order, split_axis, split_value)`, slots in leaf order.
    """
    total = points.shape[0]
    leaves = 2**depth
    nodes = max(leaves - 1, 1)
    index_bits = max(1, math.ceil(math.log2(total)))
    key_bits = 32 - index_bits
    top = 2**key_bits - 1
    slot = jnp.arange(total, dtype=jnp.uint32)
    segment_ids = jnp.arange(leaves, dtype=jnp.uint32)
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

    def level(depth_here, carry):
        packed, split_axis, split_value = carry
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
        coordinate = _pick_axis(coords, point_axis)
        lo_axis = _pick_axis(lo, axis)[ids]
        span = _pick_axis(extent, axis)[ids]
        scale = jnp.where(span > 0, top / jnp.where(span > 0, span, 1.0), 0.0)
        quantized = jnp.clip(jnp.floor((coordinate - lo_axis) * scale), 0, top - 1)
        quantized = jnp.where(ok, quantized, top).astype(jnp.uint32)
        position_bits = jnp.uint32(index_bits) - here
        high = jnp.where(here > 0, segment << (jnp.uint32(key_bits) + position_bits), 0)
        key = jnp.sort(high | (quantized << position_bits) | (slot - segment * width))
        owner = jnp.where(here > 0, key >> (jnp.uint32(key_bits) + position_bits), 0)
        position = key & ((jnp.uint32(1) << position_bits) - 1)
        packed = packed[(owner * width + position).astype(jnp.int32)]
        # The split: the last coordinate of the left half, if the right half has a valid point.
        half = width // 2
        last_left = jnp.minimum(segment_ids * width + half - 1, total - 1).astype(jnp.int32)
        first_right = jnp.minimum(segment_ids * width + half, total - 1).astype(jnp.int32)
        value = jnp.where(
            packed[first_right, 4] > 0, _pick_axis(packed[last_left, :3], axis), jnp.inf
        )
        count = jnp.uint32(1) << here
        node = jnp.where(segment_ids < count, count - 1 + segment_ids, nodes).astype(jnp.int32)
        split_axis = split_axis.at[node].set(axis, mode="drop")
        split_value = split_value.at[node].set(value.astype(split_value.dtype), mode="drop")
        return packed, split_axis, split_value

    start = (packed, jnp.zeros((nodes,), jnp.int32), jnp.full((nodes,), jnp.inf, points.dtype))
    packed, split_axis, split_value = jax.lax.fori_loop(0, depth, level, start)
    valid = packed[:, 4] > 0
    order = jnp.where(valid, packed[:, 3], 0).astype(jnp.int32)
    return packed[:, :3], valid, order, split_axis, split_value


def _pick_axis(values, axis):
    """`values[i, axis[i]]` for `(n, 3)` values, by selection (no gather)."""
    return jnp.where(axis == 0, values[:, 0], jnp.where(axis == 1, values[:, 1], values[:, 2]))


def _box_distance_squared(lo_a, hi_a, lo_b, hi_b):
    gap = jnp.maximum(jnp.maximum(lo_b - hi_a, lo_a - hi_b), 0.0)
    gap = jnp.where(jnp.isnan(gap), jnp.inf, gap)
    return squared_norms(gap)


def _select_smallest(values, count):
    """Column indices of the `count` smallest entries of each row of `values` (ties, and near-ties
    within a relative 2**-(23 - column bits), in any order), and `values` with those entries set to
    `inf` (for an exact bound on what was not selected).

    Keys pack the value's float32 bits with the column index into one int32; a compare-exchange
    insertion network keeps the `count` smallest keys of each row in registers while the columns
    stream past (XLA's `top_k` and sorts are several times slower on the CPU).
    """
    columns = values.shape[-1]
    count = min(count, columns)
    bits = max(1, math.ceil(math.log2(columns)))
    as_float32 = jnp.minimum(values, jnp.finfo(jnp.float32).max).astype(jnp.float32)
    as_float32 = jnp.where(values == jnp.inf, jnp.inf, as_float32)
    key = jax.lax.bitcast_convert_type(as_float32, jnp.int32)
    key = (key >> bits << bits) | jnp.arange(columns, dtype=jnp.int32)
    key = jnp.moveaxis(key, -1, 0)  # columns first: one row of keys per step
    largest = jnp.iinfo(jnp.int32).max

    def insert(column, best):
        x = key[column]
        kept = []
        for b in best:
            kept.append(jnp.minimum(b, x))
            x = jnp.maximum(b, x)
        return tuple(kept)

    start = tuple(jnp.full(key.shape[1:], largest, jnp.int32) for _ in range(count))
    best = jax.lax.fori_loop(0, columns, insert, start)
    chosen = jnp.stack(best, axis=-1) & (2**bits - 1)
    selected = jnp.any(
        jnp.arange(columns, dtype=jnp.int32) == chosen[..., :, None], axis=-2
    )  # (..., columns)
    return chosen, jnp.where(selected, jnp.inf, values)


def _beam(node_lo, node_hi, query_lo, query_hi, depth, width, own_leaf=None):
    """The `width` leaves nearest to each query box (a point when `lo == hi`), by a beam search
    down the tree: at every level keep the `width` nearest children of the nodes kept above.

    Whatever the beam drops lies at least `reach` away (box distances only grow from a node to its
    descendants), so a match within `sqrt(reach2)` found in the kept leaves is exact. `own_leaf`
    forces each query's own leaf (and its ancestors) into the beam.

    **Returns:** `(leaves (m, width) int32, -1 where fewer exist; reach2 (m,))`.
    """
    m = query_lo.shape[0]
    candidates = jnp.full((m, width), -1, jnp.int32).at[:, 0].set(0)
    reach2 = jnp.full((m,), jnp.inf, node_lo.dtype)

    def level(here, carry):
        candidates, reach2 = carry
        children = jnp.concatenate([2 * candidates, 2 * candidates + 1], axis=1)
        children = jnp.where(jnp.concatenate([candidates, candidates], axis=1) >= 0, children, -1)
        heap = jnp.where(children >= 0, (2 << here) - 1 + children, 0)
        d2 = _box_distance_squared(
            query_lo[:, None], query_hi[:, None], node_lo[heap], node_hi[heap]
        )
        d2 = jnp.where(children >= 0, d2, jnp.inf)
        if own_leaf is not None:
            ancestor = own_leaf >> (depth - 1 - here)
            d2 = jnp.where(children == ancestor[:, None], -1.0, d2)
        chosen, rest = _select_smallest(d2, width)
        kept = jnp.take_along_axis(children, chosen, axis=1)
        kept_d2 = jnp.take_along_axis(d2, chosen, axis=1)
        kept = jnp.where(kept_d2 < jnp.inf, kept, -1)
        return kept, jnp.minimum(reach2, jnp.min(rest, axis=1))

    return jax.lax.fori_loop(0, depth, level, (candidates, reach2))


def _neighbor_graph(points, valid, adjacent, reach, size, degree, links=0):
    """Each point's `degree` nearest among the points of its leaf's adjacent leaves, and the
    radius within which that list is complete; then `links` longer edges: the nearest point of
    each of the nearest other leaves (a kNN graph of a range scan links along its scan lines;
    these edges cross between them and between nearby sheets, so that descents do not stall)."""
    leaves, count = adjacent.shape
    slots = points.shape[0]
    own = points.reshape(leaves, size, 3)
    candidate_slots = adjacent[:, :, None] * size + jnp.arange(size, dtype=jnp.int32)
    candidate_slots = jnp.where(adjacent[:, :, None] >= 0, candidate_slots, 0).reshape(
        leaves, count * size
    )
    present = jnp.repeat(adjacent >= 0, size, axis=1)
    candidates = jnp.where(
        present[..., None], points[candidate_slots], jnp.inf
    )  # (leaves, count * size, 3)
    d2 = sum(
        (own[:, :, None, axis] - candidates[:, None, :, axis]) ** 2 for axis in range(3)
    )  # (leaves, size, count * size)
    own_slot = jnp.arange(slots, dtype=jnp.int32).reshape(leaves, size)
    d2 = jnp.where(own_slot[..., None] == candidate_slots[:, None, :], jnp.inf, d2)
    d2 = jnp.where(jnp.isnan(d2), jnp.inf, d2)
    degree_here = min(degree, count * size)
    columns, rest = _select_smallest(d2, degree_here)
    graph = jnp.take_along_axis(
        jnp.broadcast_to(candidate_slots[:, None, :], d2.shape), columns, axis=2
    ).reshape(slots, degree_here)
    if degree_here < degree:
        graph = jnp.concatenate([graph, jnp.repeat(graph[:, :1], degree - degree_here, 1)], 1)
    unlisted = jnp.sqrt(jnp.min(rest, axis=2)).reshape(slots)
    coverage = jnp.minimum(unlisted, jnp.repeat(reach, size))
    links = min(links, count - 1)
    if links > 0:
        per_leaf = d2.reshape(leaves, size, count, size)[:, :, 1 : links + 1]
        _, column = _min_and_argmin(per_leaf)  # (leaves, size, links)
        linked = adjacent[:, None, 1 : links + 1] * size + column
        linked = jnp.where(
            adjacent[:, None, 1 : links + 1] >= 0, linked, graph.reshape(leaves, size, -1)[..., :1]
        )
        graph = jnp.concatenate([graph, linked.reshape(slots, links)], axis=1)
    return graph, jnp.where(valid, coverage, 0.0)


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


# ---- queries ------------------------------------------------------------------------------------


def locate_leaf(index: NeighborIndex, queries):
    """The leaf of the tree each query falls in, shape `(n,)` int32."""

    def down(_, node):
        coordinate = _pick_axis(queries, index.split_axis[node])
        return 2 * node + 1 + (coordinate > index.split_value[node]).astype(jnp.int32)

    node = jax.lax.fori_loop(0, index.depth, down, jnp.zeros(queries.shape[:-1], jnp.int32))
    return node - (index.leaves - 1)


def _squared_distances(candidates, queries):
    """`candidates (n, m, 3)` against `queries (n, 3)`, shape `(n, m)`; inf for inf candidates."""
    d2 = sum((candidates[..., axis] - queries[..., None, axis]) ** 2 for axis in range(3))
    return jnp.where(jnp.isnan(d2), jnp.inf, d2)


def _min_and_argmin(d2):
    """Row minima and the first column attaining them (two plain reductions: XLA's variadic
    argmin reduction is much slower on the CPU)."""
    d2 = jax.lax.optimization_barrier(d2)
    smallest = jnp.min(d2, axis=-1)
    columns = d2.shape[-1]
    first = jnp.min(
        jnp.where(d2 == smallest[..., None], jnp.arange(columns, dtype=jnp.int32), columns), axis=-1
    )
    return smallest, jnp.minimum(first, columns - 1)


def seed(index: NeighborIndex, queries, *, width=2):
    """A first match for each query: the nearest point in the `width` leaves nearest to it (a
    narrow beam search; queries far outside the cloud then start on its near side).

    **Returns:** `(slot, squared_distance)`."""
    m = queries.shape[0]
    slot = jnp.zeros((m,), jnp.int32)
    slot, d2, _ = _beam_match(
        index,
        queries,
        slot,
        jnp.full((m,), jnp.inf, queries.dtype),
        jnp.inf,
        min(width, index.leaves),
    )
    return slot, d2


def track(index: NeighborIndex, queries, previous, *, max_steps=16, mask=None):
    """Follow moving queries: start each from the closer of its previous match and the
    representative point of the leaf it now falls in, then `descend`. (Descent alone can stay on
    the wrong sheet of a surface after a large move: a neighbour graph is only locally connected.)

    **Returns:** `(slot, squared_distance, steps)`."""
    candidate = index.representative[locate_leaf(index, queries)]
    candidate_d2 = squared_norms(index.points[candidate] - queries)
    previous_d2 = squared_norms(index.points[previous] - queries)
    start = jnp.where(candidate_d2 < previous_d2, candidate, previous)
    return descend(index, queries, start, max_steps=max_steps, mask=mask)


def descend(index: NeighborIndex, queries, slot, *, max_steps=64, mask=None):
    """Greedy descent on the neighbour graph from `slot`: move to the nearest neighbour of the
    current point while it is closer to the query, until no query moves or `max_steps`.

    **Returns:** `(slot, squared_distance, steps)`."""
    active = jnp.ones(queries.shape[:-1], bool) if mask is None else mask
    d2 = squared_norms(index.points[slot] - queries)
    d2 = jnp.where(jnp.isnan(d2), jnp.inf, d2)

    def step(state):
        slot, d2, _, steps = state
        rows = index.graph_points[slot]  # (n, 3, degree)
        nd2 = sum((rows[..., axis, :] - queries[..., axis, None]) ** 2 for axis in range(3))
        nd2 = jnp.where(jnp.isnan(nd2), jnp.inf, nd2)
        best, column = _min_and_argmin(nd2)
        better = (best < d2) & active
        nxt = jnp.take_along_axis(index.graph[slot], column[..., None], axis=-1)[..., 0]
        return jnp.where(better, nxt, slot), jnp.where(better, best, d2), jnp.any(better), steps + 1

    def keep_going(state):
        return state[2] & (state[3] < max_steps)

    slot, d2, _, steps = jax.lax.while_loop(
        keep_going, step, (slot, d2, jnp.asarray(True), jnp.asarray(0, jnp.int32))
    )
    return slot, d2, steps


def certify(index: NeighborIndex, slot, d2, radius):
    """Whether the match at `slot` (squared distance `d2`) is provably the nearest target point
    within `radius` (see the module docstring)."""
    d = jnp.sqrt(d2)
    return (d + jnp.minimum(d, radius)) <= index.coverage[slot]


def _scan_leaves(index: NeighborIndex, queries, slot, d2, radius, leaves_per_round):
    """Exact search for a (compacted) batch of queries: visit, `leaves_per_round` at a time, every
    leaf whose box is closer than the starting best distance (capped at `radius`), skipping those
    that the improving best has ruled out.

    **Returns:** `(slot, squared_distance)`."""
    m = queries.shape[0]
    leaves, size = index.leaves, index.leaf_size
    blocks = index.points.reshape(leaves, size, 3)
    box2 = _box_distance_squared(
        queries[:, None, :],
        queries[:, None, :],
        index.node_lo[None, leaves - 1 :],
        index.node_hi[None, leaves - 1 :],
    )  # (m, leaves)
    r2 = radius * radius
    rank = jnp.cumsum(box2 < jnp.minimum(d2, r2)[:, None], axis=1, dtype=jnp.int32)
    total = rank[:, -1]
    steps = max(1, math.ceil(math.log2(leaves)) + 1)
    rows = jnp.arange(m)[:, None]

    def body(state):
        slot, d2, done = state
        wanted = done + 1 + jnp.arange(leaves_per_round, dtype=jnp.int32)  # ranks, 1-based

        def bisect(_, bounds):  # the first leaf whose rank reaches `wanted`
            lo, hi = bounds
            mid = (lo + hi) // 2
            below = jnp.take_along_axis(rank, mid, axis=1) < wanted
            return jnp.where(below, mid + 1, lo), jnp.where(below, hi, mid)

        lo = jnp.zeros((m, leaves_per_round), jnp.int32)
        hi = jnp.full((m, leaves_per_round), leaves - 1, jnp.int32)
        lo, _ = jax.lax.fori_loop(0, steps, bisect, (lo, hi))
        picks = jnp.minimum(lo, leaves - 1)
        present = (wanted <= total[:, None]) & (box2[rows, picks] < jnp.minimum(d2, r2)[:, None])
        candidates = blocks[picks].reshape(m, leaves_per_round * size, 3)
        cd2 = jnp.where(
            jnp.repeat(present, size, axis=1), _squared_distances(candidates, queries), jnp.inf
        )
        best, column = _min_and_argmin(cd2)
        found = picks[jnp.arange(m), column // size] * size + column % size
        better = best < d2
        return jnp.where(better, found, slot), jnp.where(better, best, d2), done + leaves_per_round

    def keep_going(state):
        return state[2] < jnp.max(total)

    slot, d2, _ = jax.lax.while_loop(keep_going, body, (slot, d2, jnp.asarray(0, jnp.int32)))
    return slot, d2


def _beam_match(index: NeighborIndex, queries, slot, d2, radius, width):
    """Search the `width` leaves a beam search keeps for each query; certify by its reach.

    **Returns:** `(slot, squared_distance, certified)`."""
    m, size = queries.shape[0], index.leaf_size
    leaves, reach2 = _beam(index.node_lo, index.node_hi, queries, queries, index.depth, width)
    blocks = index.points.reshape(index.leaves, size, 3)[jnp.maximum(leaves, 0)]
    present = jnp.repeat(leaves >= 0, size, axis=1)
    cd2 = jnp.where(
        present, _squared_distances(blocks.reshape(m, width * size, 3), queries), jnp.inf
    )
    best, column = _min_and_argmin(cd2)
    found = (
        jnp.take_along_axis(leaves, (column // size)[:, None], axis=1)[:, 0] * size + column % size
    )
    better = best < d2
    slot, d2 = jnp.where(better, found, slot), jnp.where(better, best, d2)
    return slot, d2, jnp.minimum(d2, radius * radius) <= reach2


def _compacted(fn, queries, slot, d2, certified, chunk):
    """Apply `fn(queries, slot, d2) -> (slot, d2, certified)` once to every uncertified query,
    `chunk` at a time (gathered with `nonzero`, scattered back). A query `fn` leaves uncertified
    is not visited again (a second pass would repeat the same search)."""
    n = queries.shape[0]

    def body(state):
        slot, d2, certified, visited = state
        (pending,) = jnp.nonzero(~certified & ~visited, size=chunk, fill_value=n)
        present = pending < n
        rows = jnp.minimum(pending, n - 1)
        s, e, ok = fn(queries[rows], slot[rows], d2[rows])
        target = jnp.where(present, rows, n)  # out-of-range rows are dropped by the scatter
        slot = slot.at[target].set(s, mode="drop")
        d2 = d2.at[target].set(e, mode="drop")
        certified = certified.at[target].set(ok, mode="drop")
        visited = visited.at[target].set(True, mode="drop")
        return slot, d2, certified, visited

    def keep_going(state):
        return jnp.any(~state[2] & ~state[3])

    slot, d2, certified, _ = jax.lax.while_loop(
        keep_going, body, (slot, d2, certified, jnp.zeros_like(certified))
    )
    return slot, d2, certified


def refine_uncertified(
    index: NeighborIndex, queries, slot, d2, certified, radius, *, width=8, scan=True
):
    """Make every match exact within `radius`. Uncertified queries are gathered and searched in
    the `width` leaves of a beam search; with `scan`, the few that its reach cannot certify (more
    than `width` leaves within reach) are then searched leaf by leaf.

    **Returns:** `(slot, squared_distance, certified)`; `certified` is all True with `scan`.
    """
    n = queries.shape[0]
    width = min(width, index.leaves)
    slot, d2, certified = _compacted(
        lambda q, s, e: _beam_match(index, q, s, e, radius, width),
        queries, slot, d2, certified, max(1, min(n, max(64, n // 8))),
    )  # fmt: skip

    if not scan:
        return slot, d2, certified

    def leaf_by_leaf(q, s, e):
        s, e = _scan_leaves(index, q, s, e, radius, 4)
        return s, e, jnp.ones(s.shape, bool)

    return _compacted(leaf_by_leaf, queries, slot, d2, certified, max(1, min(n, max(16, n // 64))))


def nearest(
    index: NeighborIndex, queries, *, radius=jnp.inf, initial=None, mask=None, exact=True
) -> Neighbors:
    """The nearest target point of every query, exact within `radius` when `exact`.

    **Arguments:**

    - `index`: from `build_index`.
    - `queries`: shape `(n, 3)`.
    - `radius`: matches farther than this need not be exact (they are rejected by ICP anyway);
      `inf` makes every match exact (slower for queries far from the target).
    - `initial`: slots to start the descent from (a previous `Neighbors.slot`); default: seed.
    - `mask`: queries to skip (their result is meaningless).
    - `exact`: run the certification and exact fallback; `False` returns the descent's result.

    **Returns:** `Neighbors`.
    """
    queries = jnp.asarray(queries)
    active = jnp.ones(queries.shape[:-1], bool) if mask is None else jnp.asarray(mask, bool)
    queries = jnp.where(active[:, None], queries, 0.0)
    if initial is None:
        slot, _ = seed(index, queries)
    else:
        slot = initial
    slot, d2, _ = descend(index, queries, slot, mask=active)
    if exact:
        certified = certify(index, slot, d2, radius) | ~active
        slot, d2, certified = refine_uncertified(index, queries, slot, d2, certified, radius)
    else:
        certified = jnp.zeros_like(active)
    return Neighbors(index.order[slot], slot, jnp.sqrt(d2), certified & active)
