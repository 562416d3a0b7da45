"""`lieax.align`: closed-form least-squares alignment of corresponding point sets (Kabsch; Umeyama
with scale), the same as `SE3.align` / `Sim3.align`. The solution, its implicit derivative and the
input checks live beside the groups, in `lieax.groups._procrustes`.
"""

from typing import Literal, overload

from jax.typing import ArrayLike

from .groups import SE3, Sim3


@overload
def align(
    points_a: ArrayLike,
    points_b: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    with_scale: Literal[False] = False,
) -> SE3: ...
@overload
def align(
    points_a: ArrayLike,
    points_b: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    with_scale: Literal[True],
) -> Sim3: ...
@overload
def align(
    points_a: ArrayLike, points_b: ArrayLike, weights: ArrayLike | None = None, *, with_scale: bool
) -> SE3 | Sim3: ...
def align(
    points_a: ArrayLike,
    points_b: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    with_scale: bool = False,
) -> SE3 | Sim3:
    r"""The least-squares alignment $T_{ab}$ of corresponding points, $a_i \approx T_{ab}\,b_i$.

    **Arguments:**

    - `points_a`, `points_b`: corresponding points, shape `(*batch, N, 3)` (batch shapes broadcast),
      finite, $N \ge 3$, not all on a line (the rotation is not unique otherwise); fewer than 3
      points is a `ValueError` naming the count.
    - `weights`: nonnegative finite weights `(*batch, N)` (default: all 1), not all zero. Concrete
      inputs that break these rules are a `ValueError`; traced ones (under `jit`) are not checked,
      and all-zero weights there give NaN in every output (never a silent identity).
    - `with_scale`: also estimate the scale (Umeyama); the result is then a `Sim3`.

    **Returns:** `SE3` $T_{ab}$ minimizing $\sum_i w_i |a_i - T_{ab} b_i|^2$ (a `Sim3` with
    `with_scale`), batch shape `(*batch)`. Differentiable with respect to the points and weights
    (forward and reverse mode, any order) through the implicit function theorem on the optimality
    conditions, never through the SVD; where the rotation is not unique (collinear points) the
    derivative is not finite.
    """
    if with_scale:
        return Sim3.align(points_a, points_b, weights)
    return SE3.align(points_a, points_b, weights)
