r"""Initial poses for hard graphs: composition along a spanning tree, and chordal initialisation.

- `spanning_tree_poses`: a breadth-first spanning tree from the first pose (or a given root), each
  pose the composition of the measurements along the tree path ($X_j = X_i Z_{ij}$, or
  $X_i = X_j Z_{ij}^{-1}$ for an edge walked backwards). Used by `read_g2o` for files without
  vertices; exact where the graph is a tree, odometry drift elsewhere.
- `chordal_initialization`: rotations first, by the chordal relaxation
  $\min \sum_{ij} w_{ij} \|R_j - R_i \tilde R_{ij}\|_F^2$ over unconstrained $d \times d$ matrices
  with the root's rotation held, each result projected back to $SO(d)$ (SVD); then translations
  by the linear least squares $\min \sum_{ij} w_{ij} \|t_j - t_i - R_i \tilde t_{ij}\|^2$ with those
  rotations (Carlone, Tron, Daniilidis, Dellaert, "Initialization techniques for 3D SLAM: a survey
  on rotation estimation and its use in pose graph optimization", ICRA 2015; Martinec and Pajdla
  2007). The weights $w_{ij}$ are the means of the rotational and translational diagonals of each
  edge's information. Both solves are sparse symmetric systems, solved by SciPy's SuperLU once.
"""

import collections

import jax.numpy as jnp
import numpy as np

from ..groups import SE2, SE3
from ._graph import PoseGraph


def spanning_tree_poses(graph: PoseGraph, root: int = 0) -> SE2 | SE3:
    """Poses composed along a breadth-first spanning tree of `graph` from pose `root` (kept at
    its current value); `ValueError` if some pose cannot be reached."""
    n = graph.num_poses
    i, j = graph.between.i, graph.between.j
    Z = np.asarray(graph.between.measured.as_matrix(), dtype=np.float64)
    neighbours = [[] for _ in range(n)]
    for k, (a, b) in enumerate(zip(i.tolist(), j.tolist())):
        neighbours[a].append((b, k, False))
        neighbours[b].append((a, k, True))
    T = np.zeros((n, *Z.shape[1:]))
    T[root] = np.asarray(graph.poses[root].as_matrix(), dtype=np.float64)
    seen = np.zeros(n, dtype=bool)
    seen[root] = True
    queue = collections.deque([root])
    while queue:
        a = queue.popleft()
        for b, k, backwards in neighbours[a]:
            if not seen[b]:
                seen[b] = True
                T[b] = T[a] @ (_inverse(Z[k]) if backwards else Z[k])
                queue.append(b)
    if not seen.all():
        raise ValueError(
            f"{int((~seen).sum())} poses are not connected to pose {root}; no spanning tree "
            "reaches them."
        )
    return graph.group.from_matrix(jnp.asarray(T, dtype=graph.poses.dtype))


def _inverse(T):
    d = T.shape[0] - 1
    out = np.eye(d + 1)
    out[:d, :d] = T[:d, :d].T
    out[:d, d] = -T[:d, :d].T @ T[:d, d]
    return out


def chordal_initialization(graph: PoseGraph, root: int = 0) -> SE2 | SE3:
    """Poses from chordal rotation initialisation and then linear translations (see the module
    docstring); pose `root` keeps its current value. Returns a group batch like `graph.poses`."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    n = graph.num_poses
    dim = graph.dim
    i, j = np.asarray(graph.between.i), np.asarray(graph.between.j)
    m = i.shape[0]
    Z = np.asarray(graph.between.measured.as_matrix(), dtype=np.float64)
    Zr, Zt = Z[:, :dim, :dim], Z[:, :dim, dim]
    info = np.asarray(graph.information, dtype=np.float64)
    diagonal = np.diagonal(info, axis1=1, axis2=2)
    w_translation = diagonal[:, :dim].mean(axis=1)
    w_rotation = diagonal[:, dim:].mean(axis=1)
    free = np.ones(n, dtype=bool)
    free[root] = False
    column = np.cumsum(free) - 1  # unknown index of each free pose

    # rotations: per edge and row a of R, r_j[a] - Zr^T r_i[a] = 0 (r[a] the rows, length dim);
    # the rows decouple and share one normal matrix.
    eye = np.eye(dim)
    blocks_i = -np.swapaxes(Zr, 1, 2)  # coefficient of r_i[a]
    blocks_j = np.broadcast_to(eye, Zr.shape)
    R_root = np.asarray(graph.poses[root].rotation().as_matrix(), dtype=np.float64)
    # frame of the root: solve with R_root = I, then rotate everything by R_root.
    A, rhs = _assemble_rows(
        n,
        dim,
        i,
        j,
        blocks_i,
        blocks_j,
        w_rotation,
        free,
        column,
        fixed_value=np.broadcast_to(eye, (dim, dim)),
    )
    rows = spsolve((A.T @ A).tocsc(), A.T @ rhs)
    rows = np.asarray(rows).reshape(-1, dim, dim)  # (free poses, component, a) -> transpose
    R = np.empty((n, dim, dim))
    R[root] = eye
    R[free] = np.swapaxes(rows, 1, 2)
    R = _project_rotations(R)
    R = R_root @ R

    # translations: t_j - t_i = R_i t_ij
    A_t = coo_matrix(
        (
            np.concatenate([-np.ones(m), np.ones(m)]) * np.sqrt(np.tile(w_translation, 2)),
            (np.tile(np.arange(m), 2), np.concatenate([i, j])),
        ),
        shape=(m, n),
    ).tocsc()
    b = np.einsum("kab,kb->ka", R[i], Zt) * np.sqrt(w_translation)[:, None]
    t_root = np.asarray(graph.poses[root].translation(), dtype=np.float64)
    b = b - A_t[:, [root]].toarray() * t_root[None, :]
    A_free = A_t[:, free]
    t_free = spsolve((A_free.T @ A_free).tocsc(), A_free.T @ b)
    t = np.empty((n, dim))
    t[root] = t_root
    t[free] = np.asarray(t_free).reshape(-1, dim)
    T = np.zeros((n, dim + 1, dim + 1))
    T[:, :dim, :dim] = R
    T[:, :dim, dim] = t
    T[:, dim, dim] = 1.0
    return graph.group.from_matrix(jnp.asarray(T, dtype=graph.poses.dtype))


def _assemble_rows(n, dim, i, j, blocks_i, blocks_j, weights, free, column, fixed_value):
    """The weighted system $A x = b$ of $B^j_k r_j + B^i_k r_i = 0$ per edge $k$, unknowns the
    rows of the free rotations stacked (`dim` per pose), the root's row values moved to `b`
    (one right-hand side per row index a)."""
    from scipy.sparse import coo_matrix

    m = i.shape[0]
    sw = np.sqrt(weights)
    data, r_idx, c_idx = [], [], []
    rhs = np.zeros((m * dim, dim))
    for pose, blocks in ((i, blocks_i), (j, blocks_j)):
        scaled = blocks * sw[:, None, None]
        is_free = free[pose]
        k = np.flatnonzero(is_free)
        rows = (k[:, None, None] * dim + np.arange(dim)[None, :, None]).repeat(dim, axis=2)
        cols = (column[pose[k]][:, None, None] * dim + np.arange(dim)[None, None, :]).repeat(
            dim, axis=1
        )
        data.append(scaled[k].ravel())
        r_idx.append(rows.ravel())
        c_idx.append(cols.ravel())
        # fixed pose: move B r_root[a] to the right side, for each row a (r_root[a] = e_a)
        k = np.flatnonzero(~is_free)
        for kk in k:
            rhs[kk * dim : (kk + 1) * dim] -= scaled[kk] @ np.asarray(fixed_value).T
    A = coo_matrix(
        (np.concatenate(data), (np.concatenate(r_idx), np.concatenate(c_idx))),
        shape=(m * dim, int(free.sum()) * dim),
    ).tocsr()
    return A, rhs


def _project_rotations(M):
    """The nearest rotation matrices (SVD, determinant fixed to +1)."""
    U, _, Vt = np.linalg.svd(M)
    det = np.sign(np.linalg.det(U @ Vt))
    U[:, :, -1] *= det[:, None]
    return U @ Vt
