r"""The pose-graph container: poses, between factors, prior factors and fixed vertices.

Conventions are lieax's (see docs/conventions.md): right perturbation, translation-first
tangents, so a residual's information matrix is ordered like the tangent, `(vx, vy, ω)` in 2D and
`(vx, vy, vz, ωx, ωy, ωz)` in 3D. Factors keep the square root $R$ of their information
$\Omega = R^\top R$ ($R$ upper triangular), and the cost of a residual $r$ is
$\tfrac12 r^\top \Omega r = \tfrac12 \|R r\|^2$.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..factorgraph import connected_components, square_root_information
from ..groups import SE2, SE3, AbstractGroup, kernels

GROUPS = {2: SE2, 3: SE3}


@dataclasses.dataclass(frozen=True)
class BetweenFactors:
    r"""Relative-pose factors $r = \mathrm{Log}(Z^{-1} X_i^{-1} X_j)$, one per edge.

    **Fields:**

    - `i`, `j`: numpy int arrays `(m,)`, indices into the graph's poses (not file ids).
    - `measured`: the measurements $Z = X_i^{-1} X_j$, a group batched `(m,)`.
    - `sqrt_information`: `(m, d, d)` upper-triangular $R$, $R^\top R = \Omega$.
    - `loss`: `None` (least squares) or a robust loss from `lieax.lstsq` (any object with
      `loss(s)` $= \rho(s)$ and `loss.weight(s)` $= \rho'(s)$ of the whitened squared norm $s$).
    """

    i: np.ndarray
    j: np.ndarray
    measured: AbstractGroup
    sqrt_information: jnp.ndarray
    loss: object = None

    def __len__(self):
        return int(self.i.shape[0])


@dataclasses.dataclass(frozen=True)
class PriorFactors:
    r"""Absolute-pose factors $r = \mathrm{Log}(Z^{-1} X_k)$; fields as `BetweenFactors` with
    `index` `(p,)` in place of `i`, `j`."""

    index: np.ndarray
    measured: AbstractGroup
    sqrt_information: jnp.ndarray
    loss: object = None

    def __len__(self):
        return int(self.index.shape[0])


@dataclasses.dataclass(frozen=True)
class PoseGraph:
    """A pose graph: `poses` (one batched `SE2` or `SE3`, in file order), the file's ids of those
    poses in `vertex_ids`, `between` factors, optional `priors`, and `fixed` pose indices (the
    g2o `FIX` lines) that the optimizer holds constant.

    Build one with `read_g2o`, or `PoseGraph.create` from arrays.
    """

    poses: AbstractGroup
    vertex_ids: np.ndarray
    between: BetweenFactors
    priors: PriorFactors | None = None
    fixed: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @classmethod
    def create(
        cls,
        poses,
        edges,
        measurements,
        information=None,
        *,
        vertex_ids=None,
        sqrt_information=None,
        loss=None,
    ):
        """A graph from poses `(n,)`, `edges` `(m, 2)` pose indices, measurements `(m,)` of the
        same group, and either `information` `(m, d, d)` (or `(d, d)` for all edges; identity when
        both are `None`) or its upper-triangular square root `sqrt_information`."""
        if not isinstance(poses, (SE2, SE3)):
            raise TypeError(f"poses must be an SE2 or SE3, got {type(poses).__name__}.")
        if type(measurements) is not type(poses):
            raise TypeError(
                f"measurements must be {type(poses).__name__} like the poses, "
                f"got {type(measurements).__name__}."
            )
        if len(poses.batch_shape) != 1:
            raise ValueError(
                f"poses must have one batch axis, got batch shape {poses.batch_shape}."
            )
        n = poses.batch_shape[0]
        edges = np.asarray(edges)
        if edges.ndim != 2 or edges.shape[1] != 2 or not np.issubdtype(edges.dtype, np.integer):
            raise ValueError(
                f"edges must be an integer array (m, 2), got {edges.dtype} {edges.shape}."
            )
        m = edges.shape[0]
        if measurements.batch_shape != (m,):
            raise ValueError(
                f"measurements must have batch shape ({m},) like edges, got {measurements.batch_shape}."
            )
        if m and (edges.min() < 0 or edges.max() >= n):
            raise ValueError(f"edges refer to poses outside 0..{n - 1}.")
        if np.any(edges[:, 0] == edges[:, 1]):
            raise ValueError(
                f"edge {int(np.argmax(edges[:, 0] == edges[:, 1]))} joins a pose to itself."
            )
        d = poses.tangent_dim
        if sqrt_information is None:
            info = np.eye(d) if information is None else np.asarray(information, dtype=np.float64)
            info = np.broadcast_to(info, (m, d, d))
            sqrt_information = square_root_information(info, "information matrix of edge")
        sqrt_information = jnp.broadcast_to(
            jnp.asarray(sqrt_information, dtype=poses.dtype), (m, d, d)
        )
        ids = np.arange(n) if vertex_ids is None else np.asarray(vertex_ids)
        if ids.shape != (n,):
            raise ValueError(f"vertex_ids must have shape ({n},), got {ids.shape}.")
        between = BetweenFactors(
            edges[:, 0].astype(np.int64),
            edges[:, 1].astype(np.int64),
            measurements,
            sqrt_information,
            loss,
        )
        return cls(poses, ids, between)

    # ---- shape ---------------------------------------------------------------------------------
    @property
    def group(self):
        return type(self.poses)

    @property
    def dim(self) -> int:
        """2 or 3: the dimension of the space the poses move in."""
        return self.poses.space_dim

    @property
    def num_poses(self) -> int:
        return int(self.poses.batch_shape[0])

    @property
    def num_edges(self) -> int:
        return len(self.between)

    @property
    def edges(self) -> np.ndarray:
        """`(m, 2)` pose indices of the between factors."""
        return np.stack([self.between.i, self.between.j], axis=1)

    @property
    def measurements(self):
        return self.between.measured

    @property
    def information(self):
        r"""$\Omega = R^\top R$ of every between factor, `(m, d, d)`."""
        r = self.between.sqrt_information
        return jnp.swapaxes(r, -1, -2) @ r

    def __repr__(self):
        priors = 0 if self.priors is None else len(self.priors)
        return (
            f"PoseGraph({self.group.__name__}, {self.num_poses} poses, {self.num_edges} edges, "
            f"{priors} priors, {len(self.fixed)} fixed)"
        )

    # ---- derived graphs --------------------------------------------------------------------------
    def replace(self, **changes):
        return dataclasses.replace(self, **changes)

    def with_poses(self, poses):
        """The same factors around other poses (for example an initialisation)."""
        if type(poses) is not self.group or poses.batch_shape != self.poses.batch_shape:
            raise ValueError(
                f"poses must be {self.group.__name__} of batch shape {self.poses.batch_shape}."
            )
        return self.replace(poses=poses)

    def with_loss(self, loss):
        """The same graph with a robust loss on the between factors (`None` removes it)."""
        return self.replace(between=dataclasses.replace(self.between, loss=loss))

    def with_prior(self, index, measured=None, information=None, *, loss=None):
        """The graph with prior factors on poses `index` (an int or `(p,)` ints) at `measured`
        (default: the current poses there) with `information` `(d, d)` or `(p, d, d)` (default
        the identity). Priors replace the gauge: the optimizer then holds no pose fixed (unless
        `fixed` is set)."""
        index = np.atleast_1d(np.asarray(index)).astype(np.int64)
        if index.ndim != 1 or (index.size and (index.min() < 0 or index.max() >= self.num_poses)):
            raise ValueError(f"prior indices must be in 0..{self.num_poses - 1}, got {index}.")
        if measured is None:
            measured = self.poses[index]
        elif type(measured) is not self.group:
            raise TypeError(
                f"measured must be {self.group.__name__}, got {type(measured).__name__}."
            )
        else:
            measured = kernels.element(
                self.group,
                jnp.broadcast_to(measured.parameters(), (index.size, self.group.parameters_dim)),
            )
        d = self.poses.tangent_dim
        info = np.eye(d) if information is None else np.asarray(information, dtype=np.float64)
        root = square_root_information(
            np.broadcast_to(info, (index.size, d, d)), "prior information"
        )
        root = jnp.asarray(root, dtype=self.poses.dtype)
        priors = PriorFactors(index, measured, root, loss)
        if self.priors is not None:
            old = self.priors
            if old.loss is not loss:
                raise ValueError("all priors of a graph share one loss; pass the same loss.")
            priors = PriorFactors(
                np.concatenate([old.index, index]),
                kernels.element(
                    self.group, jnp.concatenate([old.measured.parameters(), measured.parameters()])
                ),
                jnp.concatenate([old.sqrt_information, root]),
                loss,
            )
        return self.replace(priors=priors)

    def with_fixed(self, index):
        """The graph with poses `index` held constant by the optimizer."""
        index = np.unique(np.atleast_1d(np.asarray(index)).astype(np.int64))
        if index.size and (index.min() < 0 or index.max() >= self.num_poses):
            raise ValueError(f"fixed indices must be in 0..{self.num_poses - 1}, got {index}.")
        return self.replace(fixed=index)

    def index_of(self, vertex_id) -> int:
        """The pose index of a file's vertex id."""
        hits = np.flatnonzero(self.vertex_ids == vertex_id)
        if hits.size == 0:
            raise KeyError(f"no vertex with id {vertex_id}.")
        return int(hits[0])

    def components(self):
        """`(count, labels)`: the connected components of the graph, as scipy's
        `connected_components` returns them (labels `(n,)` per pose)."""
        return connected_components(self.num_poses, self.between.i, self.between.j)
