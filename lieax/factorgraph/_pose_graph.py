"""Pose graphs as factor graphs: `from_pose_graph` turns a `lieax.graph.PoseGraph` into a
`FactorGraph` with a between factor kind and, when the graph has priors, a prior factor kind.

Between residual (GTSAM's `BetweenFactor`): $e = \\mathrm{Log}(Z^{-1} X_i^{-1} X_j)$ with the
closed-form blocks $\\partial e/\\partial X_j = J_r^{-1}(e)$ and
$\\partial e/\\partial X_i = -J_r^{-1}(e)\\,\\mathrm{Ad}((X_i^{-1}X_j)^{-1})$ (`lieax.graph`'s
`between_jacobians`); prior $e = \\mathrm{Log}(Z^{-1} X)$,
$\\partial e / \\partial X = J_r^{-1}(e)$. The gauge is `lieax.graph.optimize`'s:
`graph.fixed`, else none with priors, else the first pose.
"""

import jax.numpy as jnp
import numpy as np

from ._factors import Factor
from ._graph import FactorGraph
from ._variables import Var


def between_residual(pose_i, pose_j, measured):
    """$\\mathrm{Log}(Z^{-1} X_i^{-1} X_j)$."""
    return measured.between(pose_i.between(pose_j)).log()


def between_blocks(pose_i, pose_j, measured):
    """`(e, (J_e_pose_i, J_e_pose_j))` in closed form (see the module docstring)."""
    relative = pose_i.between(pose_j)
    error = measured.between(relative).log()
    J_e_pose_j = type(relative).right_jacobian_inverse(error)
    return error, (-J_e_pose_j @ relative.inverse().adjoint(), J_e_pose_j)


def between_blocks_approximate(pose_i, pose_j, measured):
    """`(e, (-Ad((X_i^{-1}X_j)^{-1}), I))`: the blocks without $J_r^{-1}(e)$, GTSAM's "I before
    the Log" (builds without `GTSAM_SLOW_BUT_CORRECT_BETWEENFACTOR`)."""
    relative = pose_i.between(pose_j)
    error = measured.between(relative).log()
    eye = jnp.eye(error.shape[-1], dtype=error.dtype)
    return error, (-relative.inverse().adjoint(), eye)


def prior_residual(pose, measured):
    """$\\mathrm{Log}(Z^{-1} X)$."""
    return measured.between(pose).log()


def prior_blocks(pose, measured):
    error = prior_residual(pose, measured)
    return error, (type(pose).right_jacobian_inverse(error),)


def prior_blocks_approximate(pose, measured):
    error = prior_residual(pose, measured)
    return error, (jnp.eye(error.shape[-1], dtype=error.dtype),)


def from_pose_graph(graph, *, closed_form=True, exact=True, check_gauge=True):
    """`(factor_graph, poses)`: the `FactorGraph` of a `lieax.graph.PoseGraph` and its pose
    `Var`. `closed_form` gives the factors the closed-form Jacobian blocks (default); otherwise
    `lieax.jacobian` differentiates the residuals through the groups' `custom_jvp` rules.
    `exact=False` drops $J_r^{-1}(e)$ from the closed-form blocks (`lieax.graph.optimize`'s
    `jacobian="approximate"`). `check_gauge` as `FactorGraph`'s."""
    if len(graph.fixed):
        fixed = np.asarray(graph.fixed)
    elif graph.priors is not None and len(graph.priors):
        fixed = None
    else:
        fixed = [0]
    poses = Var(graph.poses, fixed=fixed, name="poses")
    b = graph.between
    factors = [
        Factor(
            between_residual,
            (poses[b.i], poses[b.j]),
            b.measured,
            sqrt_information=b.sqrt_information,
            loss=b.loss,
            jacobian_fn=(between_blocks if exact else between_blocks_approximate)
            if closed_form
            else None,
            name="between",
        )
    ]
    p = graph.priors
    if p is not None and len(p):
        factors.append(
            Factor(
                prior_residual,
                (poses[p.index],),
                p.measured,
                sqrt_information=p.sqrt_information,
                loss=p.loss,
                jacobian_fn=(prior_blocks if exact else prior_blocks_approximate)
                if closed_form
                else None,
                name="prior",
            )
        )
    return FactorGraph(factors, [poses], check_gauge=check_gauge), poses
