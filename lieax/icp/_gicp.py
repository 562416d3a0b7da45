r"""Generalized ICP (plane-to-plane; Segal, Haehnel, Thrun, "Generalized-ICP", RSS 2009).

Every point carries a covariance of its local surface; a pair $(s_i, d_i)$ (source point, its
nearest target point) has the residual $r_i = T s_i - d_i$ and the Mahalanobis weight
$M_i = (C^d_i + R C^s_i R^\top)^{-1}$, and the pose minimizes $\sum_i \rho(r_i^\top M_i r_i)$.
It runs in the ICP loop (`lieax.icp._loop`: match, update, re-match, the same statuses and
stopping rule as `point_to_plane`), handed this module's Gauss-Newton update (`GICP`, a
`lieax.icp._parts.Step`) and, as small_gicp, a stop on the size of the step as well.

Conventions (right perturbation, translation-first tangents, `T_a_b` maps b into a) are the
docs/conventions.md.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .. import _cpu_emitters as cpu_emitters
from .._checks import as_float_array, is_concrete, to_device
from .._host_call import host_call
from ..groups import SE3, kernels
from ..lstsq._normal_equations import solve_spd
from . import _host_kdtree, _native_kdtree, _neighbors, _normals, _search
from ._batch import pad_to_bucket
from ._checks import check_cloud, check_count, check_mask, check_parameter
from ._normals import _UPPER, offset_covariances, smallest_eigenvector
from ._parts import Step
from ._registration import ICPResult, _register

EPSILON = 1e-3  # the smallest regularized eigenvalue (GICP, fast_gicp, small_gicp)
ROTATION_EPSILON = 0.1 * math.pi / 180  # small_gicp's default step tolerance, 0.1°
# The default translation tolerance per unit of max_correspondence_distance: small_gicp's 1 mm at
# its default distance, 1 m.
TRANSLATION_EPSILON_PER_DISTANCE = 1e-3
MIN_NEIGHBOURS = 5  # fewer valid neighbours give the identity (small_gicp's rule)


# ---- covariances --------------------------------------------------------------------------------


def estimate_covariances(points, *, k=20, mask=None, search="auto"):
    r"""Regularized local covariances of a point cloud, shape `(n, 3, 3)`.

    The sample covariance of each point and its `k - 1` nearest neighbours, eigen-decomposed as
    $U \Lambda U^\top$ (eigenvalues ascending), is replaced by
    $C = U\,\mathrm{diag}(\varepsilon, 1, 1)\,U^\top = I - (1 - \varepsilon)\,n n^\top$
    with $\varepsilon = 10^{-3}$ and $n$ the eigenvector of the smallest eigenvalue: the "plane"
    regularization of Segal et al. (2009, section III.B), as small_gicp's `CovarianceSetter` and
    fast_gicp's `PLANE` method. Neighbourhoods of fewer than 5 valid points get the identity
    (small_gicp's rule).

    **Arguments:**

    - `points`: shape `(n, 3)`.
    - `k`: neighbourhood size, the point itself included (small_gicp's default, 20).
    - `mask`: `(n,)` bools, False for padding; those rows get the identity.
    - `search`: how the neighbours are found, as for `estimate_normals`: `"kdtree"`, a k-d tree
      (the native library's, else pykdtree's or SciPy's on the host; exact; CPU only; the sums
      over each neighbourhood are made beside it, see `_kdtree_covariances`), `"graph"`, the
      fixed-shape neighbour graph (any backend;
      99.96% of the bunny's neighbourhoods exact), or `"auto"` (`"kdtree"` on a CPU, else
      `"graph"`).

    Runs under `jit` and `vmap`.
    """
    points = check_cloud(points, "points")
    mask = check_mask(mask, points, "mask")
    k = check_count(k, "k", minimum=MIN_NEIGHBOURS)
    if search not in ("auto", "graph", "kdtree"):
        raise ValueError(f"search must be 'auto', 'graph' or 'kdtree', got {search!r}.")
    if search == "auto":
        search = "kdtree" if _search.platform_of(points) == "cpu" else "graph"
    if search == "kdtree":
        _host_kdtree.check_on_host(points, "the points")
        return _kdtree_covariances(points, mask, k, _host_kdtree.default_library(points.dtype))
    return _estimate(points, mask, k=k)


@cpu_emitters.jit(static_argnames=("k",))
def _estimate(points, mask, *, k):
    safe = jnp.where(mask[:, None] & jnp.isfinite(points), points, 0.0)
    # 16 adjacent leaves of 16 points: 99.96% of the bunny's 20-neighbourhoods are exact (24 leaves:
    # 99.97%, at twice the build time; the rest swap a far neighbour for an almost as near one).
    index = _neighbors.build_index(safe, mask, degree=k - 1, adjacent_leaves=16)
    centre = index.points  # slot order
    neighbours = jnp.concatenate([centre[:, :, None], index.graph_points], axis=2)  # (slots, 3, k)
    # Clouds of fewer valid points than k fill the graph with invalid slots, the point itself and
    # (fewer slots than k - 1) repeats: count each valid neighbour once.
    others = index.valid[index.graph] & (index.graph != jnp.arange(index.graph.shape[0])[:, None])
    if index.graph.shape[0] < k - 1:
        earlier = jnp.tril(jnp.ones((k - 1, k - 1), bool), -1)
        repeated = jnp.any((index.graph[:, :, None] == index.graph[:, None, :]) & earlier, axis=2)
        others = others & ~repeated
    inside = jnp.concatenate([index.valid[:, None], others], axis=1)
    regularized = _regularized(centre, neighbours, inside, index.valid)
    slots = jnp.where(index.valid, index.order, points.shape[0])
    identities = jnp.broadcast_to(jnp.eye(3, dtype=points.dtype), (points.shape[0], 3, 3))
    return identities.at[slots].set(regularized, mode="drop")


@cpu_emitters.jit
def _covariances_of_neighbours(points, mask, found):
    """The covariances over the neighbourhoods `found` (`-1` for none) of `_normals.neighbourhoods`
    (the host k-d tree's: exact)."""
    valid = mask & jnp.all(jnp.isfinite(points), axis=1)
    safe = jnp.where(valid[:, None], points, 0.0)
    neighbours = jnp.transpose(safe[jnp.maximum(found, 0)], (0, 2, 1))  # (n, 3, k)
    return _regularized(safe, neighbours, found >= 0, valid)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3))
def _kdtree_covariances(points, mask, k, library):
    """`estimate_covariances(search="kdtree")`: the neighbours' sums beside the k-d tree, in the
    native library's custom call (`lieax.icp._native_kdtree.covariance_entries`) or the host
    tree's callback (`_host_covariance_entries`), the eigenvector and the regularization in JAX.

    Either skips what the JAX path of `_covariances_of_neighbours` pays for: the `(n, k)`
    indices' trip back to XLA and XLA's gather of `(n, 3, k)` copies (on the Kinect cloud of
    `benchmarks/gicp.py`, 67k points, about 2x the time of the NumPy sums). Derivatives (the
    neighbourhoods held fixed) are those of `_covariances_of_neighbours`, the JVP rule below."""
    return _kdtree_covariances_primal(points, mask, k=k, library=library)


@cpu_emitters.jit(static_argnames=("k", "library"))
def _kdtree_covariances_primal(points, mask, *, k, library):
    valid = mask & jnp.all(jnp.isfinite(points), axis=1)
    if library == "native":
        entries = _native_kdtree.covariance_entries(points, valid, k)
    else:
        host = functools.partial(_host_covariance_entries, k=k, library=library)
        result = jax.ShapeDtypeStruct((points.shape[0], 6), points.dtype)
        entries = host_call(host, result, points, valid)
    upper = [entries[:, j] for j in range(6)]
    covariance = jnp.stack(
        [jnp.stack([_entry(upper, a, b) for b in range(3)], -1) for a in range(3)], -2
    )
    count = jnp.minimum(k, jnp.sum(valid))  # every valid point has min(k, valid points) members
    return _plane_regularized(covariance, count, valid)


@_kdtree_covariances.defjvp
def _kdtree_covariances_jvp(k, library, primals, tangents):
    points, mask = primals
    found = _normals.neighbourhoods(points, mask, k, search="kdtree")
    return jax.jvp(lambda p: _covariances_of_neighbours(p, mask, found), (points,), tangents[:1])


def _host_covariance_entries(points, valid, k, library):
    r"""Host side of `_kdtree_covariances`: the six upper entries `(00, 01, 02, 11, 12, 22)` of
    the sample covariance of each valid row of `points` `(n, 3)` and its `k - 1` nearest valid
    rows (fewer where there are fewer), `(n, 6)` in the points' dtype, 0 in the rows not `valid`.

    The neighbourhoods are `_host_kdtree.valid_row_neighbours`'; then, in float64 with the
    offsets $o_j = p_j - p$ from the point, $\frac1c \sum_j o_j o_j^\top - \bar o \bar o^\top$
    (small_gicp's sums, about the point rather than the origin), one coordinate at a time: three
    `(n, k)` gathers, no `(n, k, 3)` copy."""
    out = np.zeros((points.shape[0], 6), points.dtype)
    rows, cloud, nearest = _host_kdtree.valid_row_neighbours(points, valid, k, library)
    if nearest is None:
        return out
    count = nearest.shape[1]
    columns = np.ascontiguousarray(cloud.T, np.float64)
    offsets = [np.take(column, nearest) - column[:, None] for column in columns]
    means = [np.sum(offset, axis=1) / count for offset in offsets]
    entries = np.empty((rows.size, 6), np.float64)
    for j, (a, b) in enumerate(_UPPER):
        products = np.einsum("ij,ij->i", offsets[a], offsets[b]) / count
        entries[:, j] = products - means[a] * means[b]
    out[slice(None) if rows.size == out.shape[0] else rows] = entries  # (no scatter: usual)
    return out


def _regularized(centre, neighbours, inside, valid):
    r"""$I - (1 - \varepsilon) n n^\top$ from the sample covariance of `neighbours` `(n, 3, k)`
    where `inside` `(n, k)`; the identity where fewer than 5 are inside or `valid` is False."""
    covariance, count = offset_covariances(neighbours - centre[:, :, None], inside)
    return _plane_regularized(covariance, count, valid)


def _plane_regularized(covariance, count, valid):
    r"""$I - (1 - \varepsilon) n n^\top$, $n$ the eigenvector of the smallest eigenvalue of each
    `(n, 3, 3)` covariance of `count` points; the identity where `count` is below 5 or `valid`
    is False."""
    normal = smallest_eigenvector(covariance)
    eye = jnp.eye(3, dtype=covariance.dtype)
    regularized = eye - (1.0 - EPSILON) * normal[:, :, None] * normal[:, None, :]
    return jnp.where((valid & (count >= MIN_NEIGHBOURS))[:, None, None], regularized, eye)


# ---- the update ---------------------------------------------------------------------------------


def _symmetric(matrix):
    """The six upper entries `(00, 01, 02, 11, 12, 22)` of `(n, 3, 3)` matrices, each `(n,)`."""
    return [matrix[:, a, b] for a, b in _UPPER]


def _entry(upper, a, b):
    return upper[_UPPER.index((min(a, b), max(a, b)))]


def _mahalanobis(rotation, source_covariances, target_covariances):
    r"""$M_i = (C^d_i + R C^s_i R^\top)^{-1}$ as six `(n,)` entries, written out elementwise: the
    rotated covariance entry by entry, then the symmetric inverse by cofactors,
    $S^{-1} = \mathrm{adj}(S) / \det S$."""
    cs = _symmetric(source_covariances)
    cd = _symmetric(target_covariances)
    # B = R C^s (3 x 3), then S = C^d + B R^T (upper entries).
    b = [[sum(rotation[a, j] * _entry(cs, j, c) for j in range(3)) for c in range(3)] for a in
         range(3)]  # fmt: skip
    s = [_entry(cd, a, c) + sum(b[a][j] * rotation[c, j] for j in range(3)) for a, c in _UPPER]
    s00, s01, s02, s11, s12, s22 = s
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    c11 = s00 * s22 - s02 * s02
    c12 = s01 * s02 - s00 * s12
    c22 = s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02
    return [c / det for c in (c00, c01, c02, c11, c12, c22)]


def _cross(a, b):
    r"""$a \times b$ of two 3-vectors given as lists of three coordinates (arrays or numbers)."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _hessian_index():
    r"""Where each entry of the 6x6 $H$ sits in the sums of `gicp_normal_equations`: the six upper
    entries of $H_{vv}$, then $H_{v\omega}$ row by row, then the six upper entries of
    $H_{\omega\omega}$."""
    index = np.zeros((6, 6), int)
    for k, (a, b) in enumerate(_UPPER):
        index[a, b] = index[b, a] = k
        index[3 + a, 3 + b] = index[3 + b, 3 + a] = 15 + k
    for a in range(3):
        for b in range(3):
            index[a, 3 + b] = index[3 + b, a] = 6 + 3 * a + b
    return index


_HESSIAN_INDEX = _hessian_index()


def gicp_normal_equations(params, source, matched, source_covariances, target_covariances, weights):
    r"""$H = \sum_i w_i J_i^\top M_i J_i$, $g = \sum_i w_i J_i^\top M_i r_i$ and the costs
    $r_i^\top M_i r_i$ of the GICP residuals $r_i = T s_i - d_i$ at `params`, with $M_i$ held
    fixed (`_mahalanobis` at the current rotation, as small_gicp recomputes it per
    linearization). `weights` (`(n,)`, or a function of the costs) are the pair weights (0 for
    rejected pairs).

    The Jacobian of the action, $J_i = \partial (T \oplus \xi) s_i / \partial \xi
    = R\,[I, -[s_i]_\times]$ (Solà, Deray, Atchuthan 2018, "A micro Lie theory", appendix D,
    right perturbation), puts $R$ outside: with $\tilde M_i = R^\top M_i R
    = (C^s_i + R^\top C^d_i R)^{-1}$, $e_i = R^\top r_i = s_i + R^\top (t - d_i)$ and the columns
    $-[s]_\times e_b = e_b \times s$,
    $H_{vv} = \sum w \tilde M$, $(H_{v\omega})_{ab} = \sum w (\tilde M (e_b \times s))_a$,
    $(H_{\omega\omega})_{ab} = \sum w (s \times \tilde M (e_b \times s))_a$,
    $g_v = \sum w \tilde M e$, $g_\omega = \sum w\, s \times \tilde M e$ and the costs
    $e^\top \tilde M e$: 27 weighted sums of per-pair entries, one matrix-vector product, where
    the dense $(6, 3n)$ layout of $J$ multiplies its zeros and ones (1.5x the time at 14.5k pairs).
    `tests/test_gicp.py` checks it against autodiff of the cost.

    **Returns:** `(H (6, 6), g (6,), costs (n,))`.
    """
    rotation = kernels.element(SE3, params).rotation().as_matrix()
    m = _mahalanobis(rotation.T, target_covariances, source_covariances)  # R^T M R
    s = [source[:, k] for k in range(3)]
    gap = [params[4 + a] - matched[:, a] for a in range(3)]
    e = [s[j] + sum(rotation[a, j] * gap[a] for a in range(3)) for j in range(3)]  # R^T r
    me = [sum(_entry(m, a, b) * e[b] for b in range(3)) for a in range(3)]
    costs = sum(e[a] * me[a] for a in range(3))
    if callable(weights):
        weights = weights(costs)
    # e_b x s, and M~ (e_b x s): entry c of e_b x s is 0 for c = b.
    columns = [[None, -s[2], s[1]], [s[2], None, -s[0]], [-s[1], s[0], None]]
    m_columns = [
        [sum(_entry(m, a, c) * columns[b][c] for c in range(3) if c != b) for a in range(3)]
        for b in range(3)
    ]  # fmt: skip
    s_cross = [_cross(s, m_columns[b]) for b in range(3)]
    entries = [_entry(m, a, b) for a, b in _UPPER]
    entries += [m_columns[b][a] for a in range(3) for b in range(3)]
    entries += [s_cross[b][a] for a, b in _UPPER]
    entries += me + _cross(s, me)
    sums = jnp.matmul(jnp.stack(entries), weights, precision=jax.lax.Precision.HIGHEST)
    return sums[_HESSIAN_INDEX], sums[21:], costs


def gicp_step(
    params, source, source_covariances, matched, target_covariances, inliers, loss_weights
):  # fmt: skip
    r"""One Gauss-Newton step $T \leftarrow T \oplus \delta$, $\delta = -H^{-1} g$ (see
    `gicp_normal_equations`), with the IRLS weights $w_i = \rho'(r_i^\top M_i r_i)$ of the
    inlier pairs; rejected pairs get identity covariances (any finite value: their weight is 0)."""
    eye = jnp.eye(3, dtype=params.dtype)
    source_covariances = jnp.where(inliers[:, None, None], source_covariances, eye)
    target_covariances = jnp.where(inliers[:, None, None], target_covariances, eye)
    hessian, gradient, _ = gicp_normal_equations(
        params, source, matched, source_covariances, target_covariances,
        lambda costs: inliers.astype(params.dtype) * loss_weights(costs),
    )  # fmt: skip
    step = -solve_spd(hessian, gradient)
    return kernels.element(SE3, params).rplus(step).parameters()


# The GICP update as the ICP loop's step (`lieax.icp._parts.Step`): its per-point data are the
# source's and the matched target points' covariances.
GICP = Step("gicp", gicp_step)


# ---- entry point --------------------------------------------------------------------------------


def gicp(
    source,
    target,
    *,
    max_correspondence_distance,
    source_covariances=None,
    target_covariances=None,
    init=None,
    max_iterations=30,
    relative_fitness=1e-6,
    relative_rmse=1e-6,
    rotation_epsilon=ROTATION_EPSILON,
    translation_epsilon=None,
    loss=None,
    source_mask=None,
    target_mask=None,
    exact=True,
    covariances_k=20,
    verbose=False,
    throw=True,
    search="auto",
    buckets=True,
) -> ICPResult:
    r"""Generalized ICP: minimize
    $\sum_i \rho\big(r_i^\top (C^d_i + R C^s_i R^\top)^{-1} r_i\big)$, $r_i = T s_i - d_i$,
    over $T$ = `T_target_source`, re-matching $d_i$ (nearest target point of $T s_i$) every
    iteration; one Gauss-Newton step per iteration (see `gicp_step`).

    The loop, the statuses and the errors are those of `point_to_plane`. It stops (`CONVERGED`)
    on either of two rules, after the update that meets it:
    - small_gicp's: the update just made, $T_\text{old}^{-1} T_\text{new}$ in the clouds' own
      frames, rotates by less than `rotation_epsilon` and translates by less than
      `translation_epsilon` (see `lieax.icp._loop._small_step`). small_gicp's
      translation default (1 mm) is absolute; the default here is $10^{-3}$
      `max_correspondence_distance`, which is small_gicp's 1 mm at its default distance (1 m,
      LiDAR) and scales with the clouds (10 µm for a 1 cm distance on an object scan): a stop
      that does not depend on the unit of length.
    - Open3D's (the shared loop's): the fitness and the inlier RMSE both changed by less than
      `relative_fitness` and `relative_rmse`.

    On the benchmark clouds (`benchmarks/gicp.py`) the step rule ends the LiDAR registration
    after small_gicp's 10 updates (Open3D's rule alone: 12) at its pose, and the other clouds
    where Open3D's rule does, as accurately. `rotation_epsilon=0, translation_epsilon=0` leaves
    Open3D's rule alone; `relative_fitness=0, relative_rmse=0` (with `translation_epsilon=1e-3`)
    is small_gicp's rule alone. (small_gicp reports one iteration fewer than it makes updates:
    its `iterations` is the index of the last; `ICPResult.iterations` counts updates.)

    **Arguments:**

    - `source`, `target`: clouds of shape `(n, 3)` and `(m, 3)`, the same floating dtype.
    - `max_correspondence_distance`: pairs farther apart are rejected (masked).
    - `source_covariances`, `target_covariances`: `(n, 3, 3)`, `(m, 3, 3)` symmetric positive
      definite; default `estimate_covariances(cloud, k=covariances_k)`.
    - `init`: initial `SE3` guess of `T_target_source` (default identity).
    - `max_iterations`: most pose updates.
    - `relative_fitness`, `relative_rmse`: the stopping tolerances (absolute changes).
    - `rotation_epsilon`: stop when an update rotates by less than this (radians, default 0.1°)
      and moves by less than `translation_epsilon`; non-negative (0 never stops this way).
    - `translation_epsilon`: see `rotation_epsilon` (a length; default
      `1e-3 * max_correspondence_distance`).
    - `loss`: robust loss with a `weight(s)` method of the squared Mahalanobis residual (the
      `lieax.lstsq` losses); default least squares.
    - `source_mask`, `target_mask`: `(n,)`, `(m,)` bools, False for padding (see `pad_clouds`).
    - `exact`: accepted for compatibility and ignored (as for `point_to_plane`).
    - `covariances_k`: neighbours for the default covariances (small_gicp's default, 20), found
      as `search` says (`"auto"`: see `estimate_covariances`).
    - `verbose`: print the fitness and inlier RMSE after every iteration.
    - `throw`: as for `point_to_plane` (raise `ICPError` for a `NONFINITE`, `INVALID` or
      `DEGENERATE` result; under `jit` when the program runs, under `vmap` never).
    - `search`: the correspondence search, as for `point_to_plane`.
    - `buckets`: pad the clouds (and the default covariances' clouds) to capacity buckets, as for
      `point_to_plane`.

    Derivatives through `gicp` raise `NotImplementedError` (the implicit derivatives of
    `lieax.icp._implicit` cover point-to-point and point-to-plane).

    **Returns:** an `ICPResult`.
    """
    source = check_cloud(source, "source")
    target = check_cloud(target, "target")
    source_mask = check_mask(source_mask, source, "source_mask")
    target_mask = check_mask(target_mask, target, "target_mask")
    if source_covariances is None:
        source_covariances = _default_covariances(source, source_mask, covariances_k, buckets)
    if target_covariances is None:
        target_covariances = _default_covariances(target, target_mask, covariances_k, buckets)
    source_covariances = _check_covariances(source_covariances, source, "source_covariances")
    target_covariances = _check_covariances(target_covariances, target, "target_covariances")
    if translation_epsilon is None:
        check_parameter(max_correspondence_distance, "max_correspondence_distance", positive=True)
        translation_epsilon = TRANSLATION_EPSILON_PER_DISTANCE * max_correspondence_distance
    return _register(
        GICP, source, target, max_correspondence_distance, init, max_iterations,
        relative_fitness, relative_rmse, loss, source_mask, target_mask, verbose, throw, search,
        buckets, source_rows=source_covariances, target_rows=target_covariances,
        step_tolerance=(rotation_epsilon, translation_epsilon),
    )  # fmt: skip


def _default_covariances(points, mask, k, buckets):
    """`estimate_covariances` of a cloud; with `buckets`, on the cloud padded (masked rows) to its
    capacity bucket, as `_register` pads it (`lieax.icp._batch.bucket_size`), cut back to the
    cloud's rows: a cloud of a new size in a known bucket compiles nothing new."""
    if not buckets:
        return estimate_covariances(points, k=k, mask=mask)
    padded, padded_mask = pad_to_bucket(points, mask)
    covariances = estimate_covariances(padded, k=k, mask=padded_mask)
    if is_concrete(covariances):  # a transfer, not a compiled slice (`to_device`)
        return to_device(np.asarray(covariances)[: points.shape[0]])
    return covariances[: points.shape[0]]


def _check_covariances(covariances, points, what):
    covariances = as_float_array(covariances, what)
    expected = (points.shape[0], 3, 3)
    if covariances.shape != expected:
        raise ValueError(
            f"{what} must have shape {expected} (one 3x3 matrix per point), "
            f"got shape {tuple(covariances.shape)}."
        )
    if covariances.dtype != points.dtype:
        raise TypeError(
            f"{what} must have the points' dtype {points.dtype}, got {covariances.dtype}."
        )
    return covariances
