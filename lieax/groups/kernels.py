r"""The groups' array kernels that lieax's domain packages (`imu`, `graph`, `cameras`, `icp`,
`retractions`, `conventions`) build on, and `element` and `carrier`, which wrap a kernel's output
and unwrap its input.

A kernel is a function of parameter arrays and tangents with a closed-form `jax.custom_jvp` rule
(the group modules' docstrings give the formulas and their sources); composing kernels keeps every
derivative closed-form. Their arrays are in the tangent carrier's form (`lieax.groups._generic`):
an array that a kernel returns becomes an element with `element(SE3, params)`, never with the
checked constructor `SE3(params)`, which converts a traced user array into that form.

The group modules' other names are their own: code outside `lieax.groups` imports the classes and
this module only (`tests/test_layout.py` keeps it so).
"""

from ._bearing_range import unit_and_length
from ._host import so3_as_matrix as host_so3_as_matrix
from ._procrustes import rotation as kabsch_rotation
from ._s2 import basis as s2_basis
from ._s2 import error as s2_error
from ._se2 import transform_to as se2_transform_to
from ._se3 import join as se3_join
from ._series import exp_coefficients as so3_exp_coefficients
from ._series import g
from ._series import jr_inverse_coefficients as so3_jr_inverse_coefficients
from ._so2 import perp as so2_perp
from ._so2 import rotate as so2_rotate
from ._so3 import as_matrix as so3_as_matrix
from ._so3 import cayley_quaternion as so3_cayley
from ._so3 import cayley_quaternion_inverse as so3_cayley_inverse
from ._so3 import exp as so3_exp
from ._so3 import from_matrix as so3_from_matrix
from ._so3 import log as so3_log
from ._so3 import right_jacobian as so3_right_jacobian
from ._so3 import right_jacobian_inverse as so3_right_jacobian_inverse
from ._so3 import to_parameters as so3_to_parameters


def element(group, params):
    """The element of `group` (a class of `lieax.groups`) around `params`, an array in the tangent
    carrier's form (a kernel's output, or a concrete array), without shape checks."""
    return group._wrap(params)


def carrier(element):
    """The parameter array of `element` in the tangent carrier's form (what kernels take);
    `element.parameters()` is the same array, converted for code that differentiates it raw."""
    return element._params


__all__ = [
    "carrier",
    "element",
    "g",
    "host_so3_as_matrix",
    "kabsch_rotation",
    "s2_basis",
    "s2_error",
    "se2_transform_to",
    "se3_join",
    "so2_perp",
    "so2_rotate",
    "so3_as_matrix",
    "so3_cayley",
    "so3_cayley_inverse",
    "so3_exp",
    "so3_exp_coefficients",
    "so3_from_matrix",
    "so3_jr_inverse_coefficients",
    "so3_log",
    "so3_right_jacobian",
    "so3_right_jacobian_inverse",
    "so3_to_parameters",
    "unit_and_length",
]
