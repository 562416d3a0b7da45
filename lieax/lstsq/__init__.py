r"""Nonlinear least squares on manifolds: Gauss-Newton and Levenberg-Marquardt over states that
mix lieax groups and arrays, robust losses, solves that batch under `vmap`, and implicit
derivatives of a solution.

Conventions (right perturbation $x \oplus \delta$, tangent layouts): docs/conventions.md.
"""

from ._least_squares import least_squares
from ._losses import AbstractLoss, Cauchy, GemanMcClure, Huber, Tukey
from ._solution import NonFiniteStartError, Solution, SolveError, SolverResult, Status
from ._solvers import AbstractSolver, GaussNewton, LevenbergMarquardt
from ._termination import Termination

__all__ = [
    "AbstractLoss",
    "AbstractSolver",
    "Cauchy",
    "GaussNewton",
    "GemanMcClure",
    "Huber",
    "LevenbergMarquardt",
    "NonFiniteStartError",
    "Solution",
    "SolveError",
    "SolverResult",
    "Status",
    "Termination",
    "Tukey",
    "least_squares",
]
