"""The Lie groups and manifolds: SO2, SE2, SO3, SE3, SE23, Sim3 and the sphere S2.

Each group module holds its kernels (module-level functions on parameter arrays: the values of
its operations, `ad`, `Jr`, `Jr⁻¹`, `hat`, `vee`, the carrier maps, its action on points) and its
class; `_base` holds what every group shares (the kernel protocol and the one tangent-carrier
convention), `_generic` the closed-form `custom_jvp` rules written once for every group, `_rules`
the rule shapes that recur, `_series` the series coefficients of Exp, Log and their Jacobians near
zero, `_bearing_range` the range and 3D bearing of a point in a frame (safe at the origin).
"""

from ._base import AbstractGroup, AbstractManifold
from ._s2 import S2
from ._se2 import SE2
from ._se3 import SE3
from ._se23 import SE23
from ._sim3 import Sim3
from ._so2 import SO2
from ._so3 import SO3

__all__ = ["AbstractGroup", "AbstractManifold", "S2", "SE2", "SE3", "SE23", "SO2", "SO3", "Sim3"]
