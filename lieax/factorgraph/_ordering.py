r"""Fill-reducing elimination orders of a block graph, for the symbolic analysis of the
multifrontal Cholesky (`_multifrontal.CholeskyPlan.analyze`, `_elimination`): minimum degree
(SuperLU's multiple minimum degree on $A^\top + A$, through `scipy.sparse.linalg.splu`; SciPy is
already a dependency of JAX) and nested dissection (George 1973; George and Liu 1981), which
keeps the elimination tree shallow where minimum degree's is tall (a chain, such as an IMU
smoother).
"""

import numpy as np


def minimum_degree_order(num_blocks, rows, cols):
    r"""A fill-reducing elimination order (new position -> block) of the graph with edges
    `(rows, cols)`: SuperLU's multiple minimum degree on $A^\top + A$ (`splu` is asked to factor a
    diagonally dominant matrix with this pattern and its column permutation is read back)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import splu

    n = num_blocks
    if n == 1:
        return np.zeros(1, dtype=np.int64)
    degree = np.bincount(np.concatenate([rows, cols]), minlength=n).astype(np.float64)
    ones = -np.ones(len(rows))
    matrix = coo_matrix(
        (
            np.concatenate([ones, ones, degree + 1.0]),
            (
                np.concatenate([rows, cols, np.arange(n)]),
                np.concatenate([cols, rows, np.arange(n)]),
            ),
        ),
        shape=(n, n),
    ).tocsc()
    lu = splu(
        matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    return np.argsort(lu.perm_c).astype(np.int64)


def nested_dissection_order(num_blocks, rows, cols, *, leaf=128):
    r"""A fill-reducing elimination order (new position -> block) by nested dissection on level
    structures (George, "Nested dissection of a regular finite element mesh", SIAM J. Numer.
    Anal. 1973; George and Liu, "Computer Solution of Large Sparse Positive Definite Systems",
    1981, Ch. 8): from a pseudo-peripheral block, the breadth-first level that halves the blocks
    separates the rest into the nearer and the farther part (only its blocks adjacent to the
    farther part are kept in the separator); both parts are ordered recursively, then the
    separator. Parts of at most `leaf` blocks are ordered by `minimum_degree_order`. Its
    elimination tree is shallow (about $\log_2$ of the blocks on a chain such as an IMU
    smoother, where minimum degree gives a path), so the numeric phase runs far fewer batches."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, shortest_path

    n = num_blocks
    adjacency = coo_matrix(
        (np.ones(2 * len(rows)), (np.concatenate([rows, cols]), np.concatenate([cols, rows]))),
        shape=(n, n),
    ).tocsr()
    result = []

    def by_minimum_degree(nodes, graph):
        upper = graph.tocoo()
        keep = upper.row < upper.col
        return nodes[minimum_degree_order(len(nodes), upper.row[keep], upper.col[keep])]

    def levels(graph, start):
        """Breadth-first distances from `start` (a connected graph)."""
        distance = shortest_path(graph, method="D", unweighted=True, indices=start)
        return distance.astype(np.int64)

    def dissect(nodes, graph):
        if len(nodes) <= leaf:
            result.append(by_minimum_degree(nodes, graph))
            return
        count, label = connected_components(graph, directed=False)
        if count > 1:
            for c in range(count):
                part = np.flatnonzero(label == c)
                dissect(nodes[part], graph[part][:, part])
            return
        # from a block farthest from block 0: a pseudo-peripheral block, nearly
        distance = levels(graph, int(np.argmax(levels(graph, 0))))
        height = int(distance.max())
        if height < 2:
            result.append(by_minimum_degree(nodes, graph))
            return
        middle = int(np.searchsorted(np.cumsum(np.bincount(distance)), len(nodes) / 2))
        middle = min(max(middle, 1), height - 1)
        farther = distance > middle
        separator = (distance == middle) & (graph @ farther.astype(np.float64) > 0)
        nearer = ~farther & ~separator
        for part in (nearer, farther):
            index = np.flatnonzero(part)
            dissect(nodes[index], graph[index][:, index])
        result.append(nodes[separator])

    dissect(np.arange(n), adjacency)
    return np.concatenate(result).astype(np.int64)


__all__ = ["minimum_degree_order", "nested_dissection_order"]
