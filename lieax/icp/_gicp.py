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

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ..groups import SE3, kernels
from ..lstsq._normal_equations import solve_spd
from ._checks import check_cloud, check_mask, check_parameter
from ._covariances import check_covariances, default_covariances
from ._normals import _UPPER, upper_entry
from ._parts import Step
from ._registration import ICPResult, _register
from ._robust import WeightedLoss
from ._search import NeighbourIndex

ROTATION_EPSILON = 0.1 * math.pi / 180  # small_gicp's default step tolerance, 0.1°
# The default translation tolerance per unit of max_correspondence_distance: small_gicp's 1 mm at
# its default distance, 1 m.
TRANSLATION_EPSILON_PER_DISTANCE = 1e-3


# ---- the update ---------------------------------------------------------------------------------


def _symmetric(matrix):
    """The six upper entries `(00, 01, 02, 11, 12, 22)` of `(n, 3, 3)` matrices, each `(n,)`."""
    return [matrix[:, a, b] for a, b in _UPPER]


def _mahalanobis(rotation, source_covariances, target_covariances):
    r"""$M_i = (C^d_i + R C^s_i R^\top)^{-1}$ as six `(n,)` entries, written out elementwise: the
    rotated covariance entry by entry, then the symmetric inverse by cofactors,
    $S^{-1} = \mathrm{adj}(S) / \det S$."""
    cs = _symmetric(source_covariances)
    cd = _symmetric(target_covariances)
    # B = R C^s (3 x 3), then S = C^d + B R^T (upper entries).
    b = [[sum(rotation[a, j] * upper_entry(cs, j, c) for j in range(3)) for c in range(3)] for a in
         range(3)]  # fmt: skip
    s = [upper_entry(cd, a, c) + sum(b[a][j] * rotation[c, j] for j in range(3)) for a, c in _UPPER]
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
    me = [sum(upper_entry(m, a, b) * e[b] for b in range(3)) for a in range(3)]
    costs = sum(e[a] * me[a] for a in range(3))
    if callable(weights):
        weights = weights(costs)
    # e_b x s, and M~ (e_b x s): entry c of e_b x s is 0 for c = b.
    columns = [[None, -s[2], s[1]], [s[2], None, -s[0]], [-s[1], s[0], None]]
    m_columns = [
        [sum(upper_entry(m, a, c) * columns[b][c] for c in range(3) if c != b) for a in range(3)]
        for b in range(3)
    ]  # fmt: skip
    s_cross = [_cross(s, m_columns[b]) for b in range(3)]
    entries = [upper_entry(m, a, b) for a, b in _UPPER]
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
    source: ArrayLike,
    target: ArrayLike,
    *,
    max_correspondence_distance: ArrayLike,
    source_covariances: ArrayLike | None = None,
    target_covariances: ArrayLike | None = None,
    init: SE3 | None = None,
    max_iterations: int | np.integer = 30,
    relative_fitness: ArrayLike = 1e-6,
    relative_rmse: ArrayLike = 1e-6,
    rotation_epsilon: ArrayLike = ROTATION_EPSILON,
    translation_epsilon: ArrayLike | None = None,
    loss: WeightedLoss | None = None,
    source_mask: ArrayLike | None = None,
    target_mask: ArrayLike | None = None,
    covariances_k: int | np.integer = 20,
    verbose: bool = False,
    throw: bool = True,
    search: str | NeighbourIndex = "auto",
    buckets: bool = True,
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
        source_covariances = default_covariances(source, source_mask, covariances_k, buckets)
    if target_covariances is None:
        target_covariances = default_covariances(target, target_mask, covariances_k, buckets)
    source_covariances = check_covariances(source_covariances, source, "source_covariances")
    target_covariances = check_covariances(target_covariances, target, "target_covariances")
    if translation_epsilon is None:
        check_parameter(max_correspondence_distance, "max_correspondence_distance", positive=True)
        translation_epsilon = TRANSLATION_EPSILON_PER_DISTANCE * max_correspondence_distance
    return _register(
        GICP, source, target, max_correspondence_distance, init, max_iterations,
        relative_fitness, relative_rmse, loss, source_mask, target_mask, verbose, throw, search,
        buckets, source_rows=source_covariances, target_rows=target_covariances,
        step_tolerance=(rotation_epsilon, translation_epsilon),
    )  # fmt: skip
