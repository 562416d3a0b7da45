r"""Pose-graph factors for `lieax.factorgraph`: `between_factor` and `prior_factor` make the
`Factor` kinds of GTSAM's `BetweenFactor` and `PriorFactor` with their closed-form blocks, and
`to_factor_graph` turns a `PoseGraph` into a `lieax.factorgraph.FactorGraph` of them;
`optimize` solves it.

The residuals and their closed-form blocks are `between_error` / `between_jacobians` and
`prior_error` / `prior_jacobian` (see `_factors`: $e = \mathrm{Log}(Z^{-1} X_i^{-1} X_j)$ with
$\partial e/\partial X_j = J_r^{-1}(e)$, $\partial e/\partial X_i = -J_r^{-1}(e)\,\mathrm{Ad}((X_i^{-1}X_j)^{-1})$;
$e = \mathrm{Log}(Z^{-1} X)$, $\partial e / \partial X = J_r^{-1}(e)$). The gauge is `optimize`'s:
`graph.fixed`, else none with priors, else the first pose.
"""

import functools
from collections.abc import Sequence

import numpy as np
from jax.typing import ArrayLike

from ..factorgraph import Factor, FactorGraph, Var, VarRef
from ..groups import SE2, SE3
from ..lstsq import AbstractLoss
from ._factors import between_error, between_jacobians, prior_error, prior_jacobian
from ._graph import PoseGraph


def _between_blocks(pose_i, pose_j, measured, exact):
    error, J_e_pose_i, J_e_pose_j = between_jacobians(pose_i, pose_j, measured, exact)
    return error, (J_e_pose_i, J_e_pose_j)


def _prior_blocks(pose, measured, exact):
    error, J_e_pose = prior_jacobian(pose, measured, exact)
    return error, (J_e_pose,)


_BLOCKS = {
    exact: (
        functools.partial(_between_blocks, exact=exact),
        functools.partial(_prior_blocks, exact=exact),
    )
    for exact in (True, False)
}


def refuse_sightings(graph, entry):
    """Refuse a `LandmarkGraph` with bearing-range sightings: `entry` models poses only."""
    sightings = getattr(graph, "bearing_range", None)
    if sightings is not None and len(sightings):
        raise ValueError(
            f"{entry} models poses only, and this graph has {len(sightings)} bearing-range "
            "sightings of landmarks: build the problem with lieax.factorgraph from "
            "to_factor_graph(graph.pose_graph()) and a landmark Var with a bearing-range Factor."
        )


def between_factor(
    poses_i: VarRef,
    poses_j: VarRef,
    measured: SE2 | SE3,
    *,
    sqrt_information: ArrayLike | None = None,
    loss: AbstractLoss | None = None,
    closed_form: bool = True,
    exact: bool = True,
    name: str = "between",
) -> Factor:
    r"""The `lieax.factorgraph.Factor` kind of between measurements (GTSAM's `BetweenFactor`):
    residual $\mathrm{Log}(Z^{-1} X_i^{-1} X_j)$ (`between_error`).

    **Arguments:**

    - `poses_i`, `poses_j`: the instances, indexed views of a pose `Var` (`poses[i]`,
      `poses[j]`).
    - `measured`: the measurements $Z$, a batched `SE2`/`SE3` of one per instance.
    - `sqrt_information`, `loss`: as `Factor`'s (the upper Cholesky factor of each information
      matrix; a robust loss).
    - `closed_form`: give the factor its closed-form blocks (`between_jacobians`; default);
      `False` lets `lieax.jacobian` differentiate the residual through the groups' rules.
    - `exact`: `False` drops $J_r^{-1}(e)$ from the closed-form blocks (GTSAM's blocks
      "before the Log").
    - `name`: the factor kind's name.
    """
    _check_blocks(closed_form, exact)
    return Factor(
        between_error,
        (poses_i, poses_j),
        measured,
        sqrt_information=sqrt_information,
        loss=loss,
        jacobian_fn=_BLOCKS[bool(exact)][0] if closed_form else None,
        name=name,
    )


def prior_factor(
    poses: VarRef,
    measured: SE2 | SE3,
    *,
    sqrt_information: ArrayLike | None = None,
    loss: AbstractLoss | None = None,
    closed_form: bool = True,
    exact: bool = True,
    name: str = "prior",
) -> Factor:
    r"""The `lieax.factorgraph.Factor` kind of pose priors (GTSAM's `PriorFactor`): residual
    $\mathrm{Log}(Z^{-1} X)$ (`prior_error`), with `poses` an indexed view of a pose `Var`
    and the other arguments as `between_factor`'s (blocks `prior_jacobian`)."""
    _check_blocks(closed_form, exact)
    return Factor(
        prior_error,
        (poses,),
        measured,
        sqrt_information=sqrt_information,
        loss=loss,
        jacobian_fn=_BLOCKS[bool(exact)][1] if closed_form else None,
        name=name,
    )


def _check_blocks(closed_form, exact):
    if not closed_form and not exact:
        raise ValueError("exact=False selects approximate closed-form blocks: needs closed_form.")


def to_factor_graph(
    graph: PoseGraph,
    *,
    closed_form: bool = True,
    exact: bool = True,
    fixed: ArrayLike | Sequence[int] | str | None = "auto",
    check_gauge: bool = True,
) -> tuple[FactorGraph, Var]:
    """`(factor_graph, poses)`: the `lieax.factorgraph.FactorGraph` of a `PoseGraph` (its
    `between_factor` and, when it has priors, its `prior_factor`) and its pose `Var`, to add
    factors of other kinds to, or to solve with other options.

    **Arguments:**

    - `graph`: the `PoseGraph`.
    - `closed_form`, `exact`: as `between_factor`'s (`exact=False` is `optimize`'s
      `jacobian="approximate"`).
    - `fixed`: the pose indices held constant. `"auto"` (default) is `optimize`'s gauge:
      `graph.fixed`, else none with priors, else the first pose. Pass `None` (or indices) when
      factors added later anchor the graph, e.g. GPS positions, with `check_gauge=False` here:
      `FactorGraph([*factor_graph.factors, gps])` checks the gauge of the whole graph.
    - `check_gauge`: as `FactorGraph`'s.
    """
    refuse_sightings(graph, "to_factor_graph")
    _check_blocks(closed_form, exact)
    if isinstance(fixed, str) and fixed == "auto":
        if len(graph.fixed):
            fixed = np.asarray(graph.fixed)
        elif graph.priors is not None and len(graph.priors):
            fixed = None
        else:
            fixed = [0]
    elif isinstance(fixed, str):
        raise ValueError(f"fixed must be 'auto', None or pose indices, got {fixed!r}.")
    poses = Var(graph.poses, fixed=fixed, name="poses")
    b, p = graph.between, graph.priors
    blocks = {"closed_form": closed_form, "exact": exact}
    factors = [
        between_factor(
            poses[b.i],
            poses[b.j],
            b.measured,
            sqrt_information=b.sqrt_information,
            loss=b.loss,
            **blocks,
        )  # fmt: skip
    ]
    if p is not None and len(p):
        factors.append(
            prior_factor(
                poses[p.index],
                p.measured,
                sqrt_information=p.sqrt_information,
                loss=p.loss,
                **blocks,
            )  # fmt: skip
        )
    return FactorGraph(factors, [poses], check_gauge=check_gauge), poses
