"""Padding clouds to shared shapes: `pad_clouds` stacks clouds of different sizes into one masked
array, so that pairs batch under `vmap`; `bucket_size` / `pad_to_bucket` pad one cloud to a
capacity bucket (four sizes per doubling, at most 25% padded rows), so that ICP on clouds of a new
size reuses a loop compiled for an earlier size of the same bucket."""

from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike, DTypeLike

from .._checks import to_device


def pad_clouds(
    clouds: Iterable[ArrayLike], size: int | None = None, *, dtype: DTypeLike | None = None
) -> tuple[jax.Array, jax.Array]:
    """Stack clouds of different sizes into `(points (b, size, 3), mask (b, size))`.

    Each cloud fills the first rows of its slice; the rest is zero and masked out. Every lieax.icp
    function takes such a mask (`source_mask`, `target_mask`, `mask`) and treats masked rows as
    absent, so a batch of pairs of different sizes registers in one `vmap`ped call, compiled once:

    ```python
    sources, source_mask = icp.pad_clouds([s0, s1, s2])
    targets, target_mask = icp.pad_clouds([t0, t1, t2])
    register = lambda s, sm, t, tm: icp.point_to_plane(
        s, t, source_mask=sm, target_mask=tm, max_correspondence_distance=0.05)
    results = jax.vmap(register)(sources, source_mask, targets, target_mask)
    ```

    **Arguments:**

    - `clouds`: a sequence of arrays of shape `(n_i, 3)`.
    - `size`: rows per cloud (default: the largest `n_i`); smaller than a cloud raises.
    - `dtype`: of the result (default: the clouds' common dtype).
    """
    clouds = [np.asarray(c) for c in clouds]
    if not clouds:
        raise ValueError("pad_clouds needs at least one cloud.")
    for i, c in enumerate(clouds):
        if c.ndim != 2 or c.shape[1] != 3:
            raise ValueError(f"cloud {i} must have shape (n, 3), got {c.shape}.")
    largest = max(c.shape[0] for c in clouds)
    size = largest if size is None else size
    if size < largest:
        raise ValueError(f"size {size} is smaller than the largest cloud ({largest} points).")
    dtype = dtype or np.result_type(*clouds)
    points = np.zeros((len(clouds), size, 3), dtype)
    mask = np.zeros((len(clouds), size), bool)
    for i, c in enumerate(clouds):
        points[i, : c.shape[0]] = c
        mask[i, : c.shape[0]] = True
    return jnp.asarray(points), jnp.asarray(mask)


def bucket_size(n: int) -> int:
    r"""The capacity bucket of `n` rows: the smallest multiple of $2^{\max(b - 3, 0)}$ that holds
    `n`, with $b$ the bit length of $n - 1$ (so $2^{b-1} < n \le 2^b$). Buckets are 5, 6, 7 and 8
    times $2^{b-3}$: four shapes per doubling of the size, and at most 25% of padded rows
    ($2^{b-3} / 2^{b-1}$). Sizes up to 8 are their own bucket. E.g. 3000 → 3072, 3100 → 3584,
    4500 → 5120, 25,000 → 28,672."""
    step = 1 << max((n - 1).bit_length() - 3, 0)
    return -(-n // step) * step


def pad_to_bucket(points, mask, *rows):
    """`points`, `mask` and any other per-point arrays (`rows`, `None` passes through) padded with
    zero rows (masked out) to `bucket_size(len(points))` rows; works on traced arrays (the shapes
    are static). Concrete arrays are padded by NumPy: a new size compiles nothing."""
    n = points.shape[0]
    extra = bucket_size(n) - n
    if extra == 0:
        return (points, mask, *rows)

    def pad(array):
        if array is None:
            return None
        widths = [(0, extra)] + [(0, 0)] * (array.ndim - 1)
        if isinstance(array, jax.core.Tracer):
            return jnp.pad(array, widths)
        return to_device(np.pad(np.asarray(array), widths))

    return (pad(points), pad(mask), *(pad(r) for r in rows))


# A chunk of a batch on the CPU holds about this many source points (see `chunked_on_cpu`).
CHUNK_POINTS = 2**13


def chunked_on_cpu(solve, n):
    """`solve(*args)` (one registration of `n` source points) whose `vmap` on a CPU runs the batch
    in chunks of `chunk_size(n, batch)` elements, one chunk after another (`lax.map`), the elements
    of a chunk in lockstep (`vmap`); on other backends the batch is `vmap`ped whole.

    Under `vmap` a loop runs until its slowest element stops, and the elements that have stopped
    still cost their share of every iteration's arithmetic: on a CPU that share is time, and a whole
    batch's arrays outgrow the caches. Lockstep pays only for small clouds, where each iteration's
    fixed cost dominates. Measured on 64 registrations of resampled bunny scans, float32, 2 cores
    (the best chunk 1.00; one target shared by the batch / a target each): at 500 points a chunk
    of 16 took 1.12 / 1.00, the whole batch in lockstep 1.00 / 1.40, one at a time 1.45 / 1.15; at
    2000 a chunk of 4 took 1.19 / 1.02, lockstep 1.00 / 1.21; at 8000 one at a time was best and
    lockstep took 1.85 / 1.73. Arguments are pytrees of arrays; unbatched ones are shared by every
    chunk, not broadcast."""

    @jax.custom_batching.custom_vmap
    def call(*args):
        return solve(*args)

    @call.def_vmap
    def call_batched(axis_size, in_batched, *args):
        leaves, treedef = jax.tree.flatten(args)
        flags = jax.tree.leaves(tuple(in_batched))
        chunk = chunk_size(n, axis_size) if jax.default_backend() == "cpu" else axis_size

        def element(batched_leaves):
            rest = iter(batched_leaves)
            full = [next(rest) if flag else leaf for leaf, flag in zip(leaves, flags)]
            return solve(*jax.tree.unflatten(treedef, full))

        batched = [leaf for leaf, flag in zip(leaves, flags) if flag]
        out = jax.lax.map(element, batched, batch_size=None if chunk == 1 else chunk)
        return out, jax.tree.map(lambda _: True, out)

    return call


def chunk_size(n: int, batch: int) -> int:
    """Elements per chunk for a batch of `batch` registrations of `n` source points on a CPU:
    `CHUNK_POINTS // n`, between 1 and `batch`."""
    return max(1, min(batch, CHUNK_POINTS // max(n, 1)))
