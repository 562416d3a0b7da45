"""Tangents and derivatives of functions of pytrees that mix groups and arrays: the leafwise
manifold operations (`_tangents`), manifold-local Jacobians and gradients (`_jacobian`), and
derivatives of implicitly defined functions (`_implicit`)."""

from ._implicit import (
    implicit_jacobian,
    inverse_function_jacobian,
    with_implicit_derivative,
    with_inverse_derivative,
)
from ._jacobian import grad, jacobian, value_and_grad, value_and_jacobian
from ._tangents import (
    flatten_tangents,
    rminus,
    rplus,
    tangent_dim,
    unflatten_tangents,
    zero_tangents,
)

__all__ = [
    "flatten_tangents",
    "grad",
    "implicit_jacobian",
    "inverse_function_jacobian",
    "jacobian",
    "rminus",
    "rplus",
    "tangent_dim",
    "unflatten_tangents",
    "value_and_grad",
    "value_and_jacobian",
    "with_implicit_derivative",
    "with_inverse_derivative",
    "zero_tangents",
]
