"""Padding clouds of different sizes into one array, so that pairs batch under `vmap`."""

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
