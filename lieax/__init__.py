"""lieax: Lie groups and manifolds for JAX, with closed-form Jacobians injected through custom_jvp.

Conventions (right perturbation, wxyz quaternions, translation-first tangents) are listed in the
docs/conventions.md section.

Layers, bottom up: `groups` (the Lie groups and their kernels), `autodiff` (tangents of pytrees,
manifold-local Jacobians, implicit derivatives) and `retractions`, the solvers (`lstsq`, `optax`,
`factorgraph`, `graph`), and the applications (`icp`, `cameras`, `ba`, `imu`, `align`, `io`,
`conventions`).
The solvers share one `Status` enum, one `SolverResult` base of their results and one `SolveError`
base of their errors. `set_threads` / `threads` / `LIEAX_NUM_THREADS` choose the threads of lieax's
host and LAPACK work (small work runs on one thread; see `lieax._threads`).
"""

from importlib.metadata import version as _version

from . import (
    ba,
    cameras,
    conventions,
    factorgraph,
    graph,
    icp,
    imu,
    io,
    lstsq,
    optax,
    retractions,
    sharding,
)
from ._align import align
from ._compilation_cache import enable_compilation_cache
from ._threads import get_threads, set_threads, threads
from .autodiff import (
    flatten_tangents,
    grad,
    implicit_jacobian,
    inverse_function_jacobian,
    jacobian,
    rminus,
    rplus,
    tangent_dim,
    unflatten_tangents,
    value_and_grad,
    value_and_jacobian,
    with_implicit_derivative,
    with_inverse_derivative,
    zero_tangents,
)
from .groups import S2, SE2, SE3, SE23, SO2, SO3, AbstractGroup, AbstractManifold, Sim3
from .io import read_pcd, read_ply, read_point_cloud, write_pcd, write_ply
from .lstsq import SolveError, SolverResult, Status

__version__ = _version("lieax")

__all__ = [
    "AbstractGroup",
    "AbstractManifold",
    "S2",
    "SE2",
    "SE3",
    "SE23",
    "SO2",
    "SO3",
    "Sim3",
    "SolveError",
    "SolverResult",
    "Status",
    "align",
    "ba",
    "cameras",
    "conventions",
    "enable_compilation_cache",
    "factorgraph",
    "flatten_tangents",
    "get_threads",
    "grad",
    "graph",
    "icp",
    "imu",
    "read_pcd",
    "read_ply",
    "read_point_cloud",
    "retractions",
    "implicit_jacobian",
    "io",
    "inverse_function_jacobian",
    "jacobian",
    "lstsq",
    "optax",
    "rminus",
    "rplus",
    "set_threads",
    "sharding",
    "tangent_dim",
    "threads",
    "unflatten_tangents",
    "write_pcd",
    "write_ply",
    "value_and_grad",
    "value_and_jacobian",
    "with_implicit_derivative",
    "with_inverse_derivative",
    "zero_tangents",
]
