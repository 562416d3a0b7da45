r"""Scale-out over several devices (and hosts) with JAX's own sharding: no scheduler of our own.

Two ways to split work, both compiled once per shapes and mesh:

- **Along a batch of problems** (thousands of scan pairs, thousands of small solves):
  `batch_map(fn, mesh)` is `jax.vmap(fn)` run by `jax.shard_map` over the mesh, so every device
  runs the batched loop on its own slice of the batch. The result comes back sharded like the
  input (leading axis split over the mesh), and the compiled program holds no collective at all:
  each device's `lax.while_loop` runs its own problems in lockstep and stops when they are done.
  (`jax.jit(jax.vmap(fn))` on sharded inputs also works — XLA's SPMD partitioner splits it — but
  the batched loop then stops when the whole global batch is done, which costs one all-reduce of
  the loop condition per iteration and keeps every device waiting on the slowest problem
  anywhere.)
- **Along the residual axis of one large problem** (a cloud of millions of points):
  `shard_residuals(residual_fn, mesh)` evaluates a `lieax.lstsq.least_squares` residual shard by
  shard: the state is replicated, the data's leading axis is split, and each device computes its
  residuals and Jacobian blocks. The reductions into the cost, $J^\top W J$ and $J^\top W r$
  are contractions over the sharded axis, which the partitioner turns into local sums and one
  all-reduce of $(c, g, H)$ per iteration (1 + n + n² numbers) — the Jacobian is never gathered.

`batch_mesh` builds a one-axis mesh over all devices; `shard_batch` lays a pytree of batched
arrays (a padded batch of clouds from `lieax.icp.pad_clouds`, a batch of point pairs) out over it.

```python
mesh = lieax.sharding.batch_mesh()                        # every visible device
sources, source_mask = lieax.icp.pad_clouds(source_clouds)
targets, target_mask = lieax.icp.pad_clouds(target_clouds)
batch, valid = lieax.sharding.shard_batch(
    (sources, source_mask, targets, target_mask), mesh, pad=True)

def register(s, sm, t, tm):
    return lieax.icp.point_to_plane(
        s, t, source_mask=sm, target_mask=tm, max_correspondence_distance=0.05, throw=False)

results = lieax.sharding.batch_map(register, mesh)(*batch)   # ICPResult, sharded over the mesh
```

**Several hosts.** The same script runs on every host; call `jax.distributed.initialize()` before
anything else touches JAX (on Cloud TPU, SLURM or Open MPI it finds the cluster by itself;
otherwise pass `coordinator_address="host0:1234", num_processes=N, process_id=i`). Then
`jax.devices()` lists every device of every host and `batch_mesh()` spans them all. Either every
process passes the whole batch to `shard_batch` (each keeps the rows of its own devices), or each
loads only its part and passes `process_local=True` (parts in process order, equal sizes).
Results are global arrays: read a process's own rows through `.addressable_shards`, or gather
them with `jax.experimental.multihost_utils.process_allgather`. On CPUs across processes, set
`jax.config.update("jax_cpu_collectives_implementation", "gloo")` for the residual-axis
all-reduce (the batch axis needs no collective).

Conventions (right perturbation, tangent layouts) are docs/conventions.md.
"""

from collections.abc import Callable, Iterable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec

from ._typing import PyTree

__all__ = ["batch_map", "batch_mesh", "shard_batch", "shard_residuals"]


def batch_mesh(devices: Iterable[jax.Device] | None = None, axis_name: str = "batch") -> Mesh:
    """A one-axis mesh over `devices` (default: `jax.devices()`, every device of every process).

    The axis is of type `Auto`: XLA's partitioner propagates shardings through the code outside
    `shard_map` (the sums of `shard_residuals`). `jax.make_mesh` makes `Explicit` axes in recent
    JAX, under whose sharding-in-types rules those sums need annotations and
    `jax.jit(jax.vmap(least_squares))` does not trace (JAX 0.10); `batch_map` works with either.
    """
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("batch_mesh needs at least one device.")
    return Mesh(np.asarray(devices), (axis_name,), axis_types=(AxisType.Auto,))


def _axis(mesh: Mesh, axis_name):
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a jax.sharding.Mesh (see batch_mesh), got {mesh!r}.")
    if axis_name is None:
        if len(mesh.axis_names) != 1:
            raise ValueError(
                f"mesh has axes {mesh.axis_names}: pass axis_name to say which one to split over."
            )
        return mesh.axis_names[0]
    if axis_name not in mesh.axis_names:
        raise ValueError(f"axis_name {axis_name!r} is not an axis of the mesh {mesh.axis_names}.")
    return axis_name


def shard_batch(
    tree: PyTree,
    mesh: Mesh | None = None,
    *,
    pad: bool = False,
    process_local: bool = False,
    axis_name: str | None = None,
) -> PyTree:
    """Lays every array of `tree` out over `mesh`, its leading (batch) axis split evenly.

    **Arguments:**

    - `tree`: a pytree of arrays (and lieax groups) sharing the size `n` of their leading axis:
      a padded batch of clouds and masks, a batch of point pairs.
    - `mesh`: default `batch_mesh()`.
    - `pad`: `False`: `n` must be a multiple of the number of devices along the axis
      (`ValueError` otherwise). `True`: the batch is extended to the next multiple by repeating
      its last element, and `(tree, valid)` is returned, `valid` a boolean `(n_padded,)` array
      (sharded alike) that is False on the added rows. Repeated problems are ordinary problems
      (they cannot fail where the original did not); drop their results with `valid` (in one
      process they are the rows past `n`: `jax.tree.map(lambda a: a[:n], results)`). Along the
      *residual* axis repeated rows would be counted twice: zero their residuals with `valid`
      (`jnp.where(valid[:, None], r, 0)`).
    - `process_local`: several hosts only: `tree` holds this process's part of the batch (parts
      in process order, equal sizes), not the whole batch. Padding then applies to each part.
    - `axis_name`: which mesh axis to split over (default: the mesh's only axis).

    **Returns:** the tree of sharded `jax.Array`s, or `(tree, valid)` with `pad=True`.
    """
    mesh = batch_mesh() if mesh is None else mesh
    axis = _axis(mesh, axis_name)
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    if not leaves:
        raise ValueError("shard_batch got a tree without arrays.")
    sizes = {np.shape(leaf)[0] if np.ndim(leaf) else None for leaf in leaves}
    if None in sizes or len(sizes) != 1:
        shapes = [tuple(np.shape(leaf)) for leaf in leaves]
        raise ValueError(
            f"shard_batch needs arrays with one common leading (batch) axis, got shapes {shapes}."
        )
    (n,) = sizes
    if n == 0:
        raise ValueError("shard_batch got an empty batch (leading axis of size 0).")
    shards = mesh.shape[axis]
    processes = jax.process_count()
    if process_local:
        if shards % processes:
            raise ValueError(
                f"process_local=True needs the {shards} devices along {axis!r} split evenly over "
                f"the {processes} processes."
            )
        shards //= processes
    size = -(-n // shards) * shards
    if size != n and not pad:
        raise ValueError(
            f"the batch of {n} does not split evenly over {shards} devices along {axis!r}: pass "
            f"pad=True to extend it to {size} (or choose a batch that is a multiple of {shards})."
        )
    if size != n:
        leaves = [_pad_edge(leaf, size - n) for leaf in leaves]
    sharding = NamedSharding(mesh, PartitionSpec(axis))
    placed = treedef.unflatten([_place(leaf, sharding, process_local) for leaf in leaves])
    if not pad:
        return placed
    valid = _place(np.arange(size) < n, sharding, process_local)
    return placed, valid


def _pad_edge(leaf, extra):
    if isinstance(leaf, jax.Array):
        return jnp.concatenate([leaf, jnp.repeat(leaf[-1:], extra, axis=0)])
    leaf = np.asarray(leaf)
    return np.concatenate([leaf, np.repeat(leaf[-1:], extra, axis=0)])


def _place(leaf, sharding, process_local):
    if process_local:
        return jax.make_array_from_process_local_data(sharding, np.asarray(leaf))
    if jax.process_count() == 1:
        return jax.device_put(leaf, sharding)
    host = np.asarray(leaf)  # every process holds the whole batch; each keeps its devices' rows
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


def _specs(in_axes, axis, what):
    """`in_axes` (0 / None, or a pytree prefix of them) as `PartitionSpec`s."""

    def spec(entry):
        if entry is None:
            return PartitionSpec()
        if entry == 0:
            return PartitionSpec(axis)
        raise ValueError(
            f"{what} entries must be 0 (split along the leading axis) or None (the same for "
            f"every element), got {entry!r}."
        )

    return jax.tree_util.tree_map(spec, in_axes, is_leaf=lambda node: node is None)


def batch_map(
    fn: Callable[..., Any],
    mesh: Mesh | None = None,
    *,
    in_axes: PyTree = 0,
    axis_name: str | None = None,
) -> Callable[..., Any]:
    """`jax.vmap(fn)` split over the devices of `mesh` along the batch axis, jitted once.

    Each device runs `jax.vmap(fn, in_axes)` on its slice of the batch (`jax.shard_map`), with no
    communication: `lieax.lstsq.least_squares` and `lieax.icp` solves run their loops in lockstep
    per device, each device stopping when its own problems are done.

    **Arguments:**

    - `fn`: the function of one problem (positional arguments), e.g.
      `lambda data: least_squares(residual, x0, data, throw=False)` or a call of
      `lieax.icp.point_to_plane(..., throw=False)`. Under `vmap` nothing can be raised: pass
      `throw=False` and read the statuses.
    - `mesh`: default `batch_mesh()`.
    - `in_axes`: as `jax.vmap`'s, restricted to `0` (batched, split over the mesh) and `None`
      (shared by every problem, replicated), for all arguments or per positional argument.
    - `axis_name`: which mesh axis to split over (default: the mesh's only axis).

    **Returns:** a jitted function of the batched arguments (lay them out with `shard_batch`;
    uncommitted arrays are moved by `jit`) whose outputs are batched along their leading axis and
    sharded over the mesh like the inputs. The batch must split evenly over the devices. It
    compiles once per argument shapes: build it once and call it for every batch.
    """
    if not callable(fn):
        raise TypeError(f"fn must be callable, got {fn!r}.")
    mesh = batch_mesh() if mesh is None else mesh
    axis = _axis(mesh, axis_name)
    specs = _specs(in_axes, axis, "in_axes")
    shardings = jax.tree_util.tree_map(
        lambda spec: NamedSharding(mesh, spec),
        specs,
        is_leaf=lambda node: isinstance(node, PartitionSpec),
    )
    # check_vma=False: a lieax solve builds its loop state from unbatched constants (x0, the
    # solver's initial damping), which the varying-manual-axes type check would reject; the body
    # holds no collective, for which alone that check matters.
    per_device = jax.shard_map(
        jax.vmap(fn, in_axes=in_axes),
        mesh=mesh,
        in_specs=specs,
        out_specs=PartitionSpec(axis),
        check_vma=False,
    )
    return jax.jit(per_device, in_shardings=shardings)


def shard_residuals(
    residual_fn: Callable[[PyTree, PyTree], PyTree],
    mesh: Mesh | None = None,
    *,
    in_axes: PyTree = 0,
    axis_name: str | None = None,
) -> Callable[[PyTree, PyTree], PyTree]:
    r"""A `least_squares` residual function evaluated shard by shard along the residual axis.

    `shard_residuals(residual_fn, mesh)(x, args)` equals `residual_fn(x, args)` for a residual
    function whose output rows each depend on one row of `args` (one residual per point pair,
    built with `jax.vmap` over the data): the state `x` is replicated, the leading axis of `args`
    and of every residual leaf is split over the mesh, and each device evaluates its residuals
    and, when `least_squares` linearizes, its Jacobian blocks. The contractions into the cost,
    $J^\top W J$ and $J^\top W r$ then run over a sharded axis: XLA computes each device's part
    and sums them with one all-reduce per iteration.

    ```python
    mesh = lieax.sharding.batch_mesh(axis_name="residual")
    data = lieax.sharding.shard_batch((source, target, normals), mesh)
    solution = lieax.lstsq.least_squares(
        lieax.sharding.shard_residuals(point_to_plane_residual, mesh), lieax.SE3.identity(), data)
    ```

    **Arguments:**

    - `residual_fn`: `residual_fn(x, args)`, every output leaf of shape `(n, ...)` with `n` the
      leading size of the (batched) `args`.
    - `mesh`: default `batch_mesh()`.
    - `in_axes`: for `args`: `0` (split the leading axis) or `None` (replicated), or a pytree
      prefix of `args` with one of them per subtree.
    - `axis_name`: which mesh axis to split over (default: the mesh's only axis).

    The mesh axis must be of type `AxisType.Auto` (as `batch_mesh` makes it): with `Explicit`
    axes JAX asks for the sharding of every contraction over the split axis.

    **Returns:** a residual function with `residual_fn`'s signature. Build it once (the solve is
    compiled once per residual function object). Lay `args` out with `shard_batch` beforehand;
    otherwise the solve redistributes them. A residual that does not split by data row (a prior
    on the state) belongs in a separate leaf computed outside:
    `lambda x, a: (sharded(x, a), prior(x))`. The result is right either way; the reduction
    stays one all-reduce only where `least_squares` linearizes each residual leaf on its own
    (where it concatenates the leaves' Jacobians, XLA gathers the split one).
    """
    if not callable(residual_fn):
        raise TypeError(f"residual_fn must be callable, got {residual_fn!r}.")
    mesh = batch_mesh() if mesh is None else mesh
    axis = _axis(mesh, axis_name)
    if dict(zip(mesh.axis_names, mesh.axis_types))[axis] != AxisType.Auto:
        raise ValueError(
            f"shard_residuals needs a mesh axis of type AxisType.Auto, got {axis!r} of type "
            f"{dict(zip(mesh.axis_names, mesh.axis_types))[axis]}: the sums over the sharded "
            "residual axis are left to XLA's partitioner. Build the mesh with batch_mesh() (or "
            "jax.make_mesh(..., axis_types=(AxisType.Auto,)))."
        )
    per_device = jax.shard_map(
        residual_fn,
        mesh=mesh,
        in_specs=(PartitionSpec(), _specs(in_axes, axis, "in_axes")),
        out_specs=PartitionSpec(axis),
    )

    def sharded_residual_fn(x, args):
        return per_device(x, args)

    return sharded_residual_fn
