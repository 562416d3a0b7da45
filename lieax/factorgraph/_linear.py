r"""Linear solvers for the block normal equations $H\,\delta = b$ of a `Layout`.

A system is `(diag, off, rhs)`: per variable kind `diag[k]` `(n_k, d_k, d_k)` and `rhs[k]`
`(n_k, d_k)`, per pair of kinds (in the order of `layout.pairs`) `off[j]` `(p, d_a, d_b)`.

- `"dense"`: the dense matrix and its Cholesky factor inside JAX (small problems).
- `"cholesky"`: `lieax.graph`'s multifrontal block Cholesky on the host (`CholeskyPlan`; its
  numeric phase a native custom call, or `host_call` without the native library), on the
  blocks padded to one size (see `_structure`).
- `"cg"`: conjugate gradients preconditioned by the inverse diagonal blocks, in JAX (the
  accelerator path; inexact steps).
- Schur complement (`schur_solve`): with $H = [H_{rr}, H_{re}; H_{er}, H_{ee}]$ and $H_{ee}$
  block diagonal, $S = H_{rr} - H_{re} H_{ee}^{-1} H_{er}$,
  $S\,\delta_r = b_r - H_{re} H_{ee}^{-1} b_e$ (solved by any of the three), then
  $\delta_e = H_{ee}^{-1}(b_e - H_{er}\,\delta_r)$ block by block (Triggs et al., "Bundle
  adjustment — a modern synthesis", 2000, Sec. 6.1; Ceres' `DENSE_SCHUR` / `SPARSE_SCHUR` /
  `ITERATIVE_SCHUR`, the last here without the implicit products). The sums of products
  $H_{re} H_{ee}^{-1} H_{er}$ are chunked Gram sums (`_gram`), $H_{ee}^{-1}$ of 3×3 blocks (points)
  is closed form (`spd_inverse`).
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._dense_solve import dense_solve
from ._gram import gram_sum, small_matmul, small_matvec
from ._pcg import pcg
from ._segments import segment_sum


def to_padded(layout, diag, off, rhs):
    """The system on the uniform padded `layout.pattern`: `(diag (N, D, D), off (P, D, D),
    rhs (N, D))`, padding identity on the diagonal, zero elsewhere."""
    D = layout.block_size
    if len(layout.dims) == 1 and layout.dims[0] == D:
        return diag[0], (off[0] if off else jnp.zeros((0, D, D), diag[0].dtype)), rhs[0]
    dtype = diag[0].dtype
    diags, rhss = [], []
    for d, block, r in zip(layout.dims, diag, rhs):
        pad = D - d
        if pad:
            eye = jnp.asarray(np.diag(np.r_[np.zeros(d), np.ones(pad)]), dtype)
            block = jnp.pad(block, ((0, 0), (0, pad), (0, pad))) + eye
            r = jnp.pad(r, ((0, 0), (0, pad)))
        diags.append(block)
        rhss.append(r)
    # each slot holds one block: a gather (`segment_sum`), where XLA CPU's scatter is a loop
    blocks = [jnp.zeros((0, D, D), dtype)]
    blocks += [jnp.pad(b, ((0, 0), (0, D - b.shape[1]), (0, D - b.shape[2]))) for b in off]
    slots = np.concatenate([np.zeros(0, np.int64), *(layout.slots[key] for key in layout.pairs)])
    padded_off = segment_sum(jnp.concatenate(blocks), slots, layout.pattern.num_pairs)
    return jnp.concatenate(diags), padded_off, jnp.concatenate(rhss)


def from_padded(layout, x):
    """Per-kind solutions `(n_k, d_k)` from the padded `(N, D)`."""
    return tuple(
        x[layout.offsets[k] : layout.offsets[k + 1], : layout.dims[k]]
        for k in range(len(layout.dims))
    )


def solve_system(layout, method, diag, off, rhs, *, cg_tolerance=1e-8, cg_max_iterations=None):
    """$H^{-1}$ `rhs` per kind by `method` (NaN when $H$ is not positive definite, except
    `"cg"`)."""
    d, o, r = to_padded(layout, diag, off, rhs)
    if method == "dense":
        x = dense_solve(layout.pattern, d, o, r)
    elif method == "cholesky":
        x = layout.cholesky_solve(d, o, r)
    else:
        x, _ = pcg(
            layout.pattern, d, o, r, tolerance=cg_tolerance, max_iterations=cg_max_iterations
        )
    return from_padded(layout, x)


def _t(a):
    return jnp.swapaxes(a, -1, -2)


def spd_inverse(a):
    r"""The inverses of a batch `(n, d, d)` of symmetric positive definite blocks; NaN where a
    block is not positive definite. For $d = 3$ in closed form (Cramer's rule),
    $A^{-1} = \operatorname{adj}(A) / \det A$ with the cofactors
    $c_{00} = a_{11}a_{22} - a_{12}^2$, $c_{01} = a_{02}a_{12} - a_{01}a_{22}$,
    $c_{02} = a_{01}a_{12} - a_{02}a_{11}$, $c_{11} = a_{00}a_{22} - a_{02}^2$,
    $c_{12} = a_{01}a_{02} - a_{00}a_{12}$, $c_{22} = a_{00}a_{11} - a_{01}^2$ and
    $\det A = a_{00}c_{00} + a_{01}c_{01} + a_{02}c_{02}$, positive definite when $a_{00}$,
    $c_{22}$ and $\det A$ are positive (Sylvester's criterion; Horn and Johnson, "Matrix
    analysis", Sec. 0.8.2 and Thm. 7.2.5); other sizes through the Cholesky factor."""
    d = a.shape[-1]
    if d != 3:
        chol = jnp.linalg.cholesky(a)
        eye = jnp.broadcast_to(jnp.eye(d, dtype=a.dtype), a.shape)
        return jax.scipy.linalg.cho_solve((chol, True), eye)
    a00, a01, a02 = a[:, 0, 0], a[:, 0, 1], a[:, 0, 2]
    a11, a12, a22 = a[:, 1, 1], a[:, 1, 2], a[:, 2, 2]
    c00, c01, c02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    scale = jnp.where((a00 > 0) & (c22 > 0) & (det > 0), 1 / det, jnp.nan)
    rows = [[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]]
    return jnp.stack([jnp.stack(row, -1) for row in rows], -2) * scale[:, None, None]


def schur_solve(layout, plan, method, diag, off, rhs, **options):
    r"""$H^{-1}$ `rhs` by eliminating `plan.eliminated` (a `SchurPlan` of `layout`). The sums of
    products $B_u H_{pp}^{-1} B_v^\top$ are `gram_sum`s over the plan's chunks of links, with
    the transposed blocks $B_u^\top$ `(d_e, d_r)` and $Q_p B_u^\top$, $Q_p = H_{pp}^{-1}$."""
    e = plan.eliminated
    keys = list(layout.pairs)
    n_e = layout.counts[e]
    q = spd_inverse(diag[e])
    b_e = rhs[e]
    # B_u^T = H_{p r} (d_e, d_r) of each link u, and Q_p B_u^T
    bt, qbt = {}, {}
    for r, (key, _, _, point, transposed) in plan.links.items():
        block = off[keys.index(key)]
        bt[r] = block if transposed else _t(block)
        qbt[r] = small_matmul(q[point], bt[r])
    red = plan.layout
    red_keys = list(red.pairs)
    new = {k: j for j, k in enumerate(plan.kept)}
    s_diag = [diag[k] for k in plan.kept]
    s_rhs = [rhs[k] for k in plan.kept]
    for r, (_, _, _, point, _) in plan.links.items():
        j = new[r]
        # [B Q B^T | B Q b_e] in one sum
        both = gram_sum(
            plan.diagonal[r], qbt[r], jnp.concatenate([bt[r], b_e[point][..., None]], -1)
        )
        s_diag[j] = s_diag[j] - both[..., :-1]
        s_rhs[j] = s_rhs[j] - both[..., -1]
    s_off = [
        jnp.zeros((len(red.pairs[key][0]), red.dims[key[0]], red.dims[key[1]]), diag[0].dtype)
        for key in red_keys
    ]
    for key, (rkey, slots) in plan.original.items():
        j = red_keys.index(rkey)
        s_off[j] = s_off[j] + segment_sum(off[keys.index(key)], slots, len(s_off[j]))
    for r1, r2, rkey, fill in plan.fill:
        j = red_keys.index(rkey)
        s_off[j] = s_off[j] - gram_sum(fill, qbt[r1], bt[r2])
    free = [jnp.asarray(red.pair_free[key]) for key in red_keys]
    s_off = [jnp.where(f[:, None, None], o, 0.0) for f, o in zip(free, s_off)]
    x_kept = solve_system(red, method, tuple(s_diag), tuple(s_off), tuple(s_rhs), **options)
    back = b_e
    for r, (_, _, inst, point, _) in plan.links.items():
        back = back - segment_sum(small_matvec(bt[r], x_kept[new[r]][inst]), point, n_e)
    x_e = small_matvec(q, back)
    x = [None] * len(layout.dims)
    for k, xk in zip(plan.kept, x_kept):
        x[k] = xk
    x[e] = x_e
    return tuple(x)
