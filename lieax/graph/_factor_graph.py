r"""A pose graph as a factor graph: `to_factor_graph` turns a `PoseGraph` into a
`lieax.factorgraph.FactorGraph` with a between factor kind and, when the graph has priors, a
prior factor kind; `optimize` solves it.

The residuals and their closed-form blocks are `between_error` / `between_jacobians` and
`prior_error` / `prior_jacobian` (see `_factors`: $e = \mathrm{Log}(Z^{-1} X_i^{-1} X_j)$ with
$\partial e/\partial X_j = J_r^{-1}(e)$, $\partial e/\partial X_i = -J_r^{-1}(e)\,\mathrm{Ad}((X_i^{-1}X_j)^{-1})$;
$e = \mathrm{Log}(Z^{-1} X)$, $\partial e / \partial X = J_r^{-1}(e)$). The gauge is `optimize`'s:
`graph.fixed`, else none with priors, else the first pose.
"""

import functools

import numpy as np

from ..factorgraph import Factor, FactorGraph, Var
from ._factors import between_error, between_jacobians, prior_error, prior_jacobian


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


def to_factor_graph(graph, *, closed_form=True, exact=True, fixed="auto", check_gauge=True):
    """`(factor_graph, poses)`: the `lieax.factorgraph.FactorGraph` of a `PoseGraph` and its
    pose `Var`, to add factors of other kinds to, or to solve with other options.

    **Arguments:**

    - `graph`: the `PoseGraph`.
    - `closed_form`: give the factors their closed-form Jacobian blocks (default); `False` lets
      `lieax.jacobian` differentiate the residuals through the groups' `custom_jvp` rules.
    - `exact`: `False` drops $J_r^{-1}(e)$ from the closed-form blocks (`optimize`'s
      `jacobian="approximate"`, GTSAM's blocks "before the Log").
    - `fixed`: the pose indices held constant. `"auto"` (default) is `optimize`'s gauge:
      `graph.fixed`, else none with priors, else the first pose. Pass `None` (or indices) when
      factors added later anchor the graph, e.g. GPS positions, with `check_gauge=False` here:
      `FactorGraph([*factor_graph.factors, gps])` checks the gauge of the whole graph.
    - `check_gauge`: as `FactorGraph`'s.
    """
    refuse_sightings(graph, "to_factor_graph")
    if not closed_form and not exact:
        raise ValueError("exact=False selects approximate closed-form blocks: needs closed_form.")
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
    between_blocks, prior_blocks = _BLOCKS[bool(exact)]
    b = graph.between
    factors = [
        Factor(
            between_error,
            (poses[b.i], poses[b.j]),
            b.measured,
            sqrt_information=b.sqrt_information,
            loss=b.loss,
            jacobian_fn=between_blocks if closed_form else None,
            name="between",
        )
    ]
    p = graph.priors
    if p is not None and len(p):
        factors.append(
            Factor(
                prior_error,
                (poses[p.index],),
                p.measured,
                sqrt_information=p.sqrt_information,
                loss=p.loss,
                jacobian_fn=prior_blocks if closed_form else None,
                name="prior",
            )
        )
    return FactorGraph(factors, [poses], check_gauge=check_gauge), poses
