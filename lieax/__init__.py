"""lieax: Lie groups and manifolds for JAX, with closed-form Jacobians injected through custom_jvp.

Conventions (right perturbation, wxyz quaternions, translation-first tangents) are listed in the
README's "Conventions" section.
"""

from . import conventions, retractions
from ._align import align
from ._autodiff import grad, jacobian, value_and_grad, value_and_jacobian
from ._base import AbstractGroup, AbstractManifold
from ._pointcloud_io import read_pcd, read_ply, read_point_cloud, write_pcd, write_ply
from ._implicit_function import (
    implicit_jacobian,
    inverse_function_jacobian,
    with_implicit_derivative,
    with_inverse_derivative,
)
from ._manifold import (
    flatten_tangents,
    rminus,
    rplus,
    tangent_dim,
    unflatten_tangents,
    zero_tangents,
)
from ._s2 import S2
from ._se2 import SE2
from ._se3 import SE3
from ._sim3 import Sim3
from ._so2 import SO2
from ._so3 import SO3
from . import ba, factorgraph, graph, icp, lstsq, optax, sharding  # noqa: E402  (after the groups they build on)

__version__ = "0.1.0"

__all__ = [
    "AbstractGroup",
    "AbstractManifold",
    "S2",
    "SE2",
    "SE3",
    "SO2",
    "SO3",
    "Sim3",
    "align",
    "ba",
    "conventions",
    "factorgraph",
    "flatten_tangents",
    "grad",
    "graph",
    "icp",
    "read_pcd",
    "read_ply",
    "read_point_cloud",
    "retractions",
    "implicit_jacobian",
    "inverse_function_jacobian",
    "jacobian",
    "lstsq",
    "optax",
    "rminus",
    "rplus",
    "sharding",
    "tangent_dim",
    "unflatten_tangents",
    "write_pcd",
    "write_ply",
    "value_and_grad",
    "value_and_jacobian",
    "with_implicit_derivative",
    "with_inverse_derivative",
    "zero_tangents",
]
