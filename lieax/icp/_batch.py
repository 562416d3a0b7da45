"""Padding clouds to shared shapes: `pad_clouds` stacks clouds of different sizes into one masked
array, so that pairs batch under `vmap`; `bucket_size` / `pad_to_bucket` pad one cloud to a
capacity bucket (four sizes per doubling, at most 25% padded rows), so that ICP on clouds of a new
size reuses a loop compiled for an earlier size of the same bucket."""

import jax
import jax.numpy as jnp
import numpy as np


def pad_clouds(clouds, size=None, *, dtype=None):
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
        return jnp.asarray(np.pad(np.asarray(array), widths))

    return (pad(points), pad(mask), *(pad(r) for r in rows))
