r"""The rules that are the same for every group, written once from a group's kernels.

For a group with the local carrier (see `lieax.groups._base`), `local_rules(kernels, **values)`
wraps the plain array functions `exp`, `log`, `compose`, `inverse`, `adjoint`, `as_matrix`,
`from_matrix` and `normalize` (values only, no derivatives) in `jax.custom_jvp` functions whose
rules hold for any matrix Lie group under right perturbations (Solà, Deray, Atchuthan, "A micro Lie
theory for state estimation in robotics" (2018), Sec. IV-B, the Jacobians of the elementary
operations; manif writes compose's as `J_mc_ma = Ad(m_b⁻¹)`, `J_mc_mb = I`):

- $\mathrm{Exp}$: $\dot X = X\,(J_r(\xi)\,\dot\xi)^\wedge$; $\mathrm{Log}$: $\dot\xi = J_r^{-1}(\xi)\,\delta$;
- $X_1 X_2$: $\delta = \mathrm{Ad}(X_2^{-1})\,\delta_1 + \delta_2$; $X^{-1}$: $\delta' = -\mathrm{Ad}(X)\,\delta$;
- $\mathrm{Ad}_X$: $\dot{\mathrm{Ad}} = \mathrm{Ad}_X\,\mathrm{ad}_\delta$; the matrix: $\dot M = M\,\delta^\wedge$;
- `from_matrix`: $\delta = (M^{-1} \dot M)^\vee$; `normalize`: the radial part of the carrier dropped,

with $\delta$ the local tangent read from the carrier by `kernels.to_local` and written back by
`kernels.from_local`; and the two carrier maps where raw arrays cross the API, `to_parameters` and
`from_parameters` (identity on values), whose rules are `kernels.raw_from_carrier(params, carrier)`
(the raw derivative moved by a carrier) and its inverse `kernels.carrier_from_raw(params, raw)`,
both evaluated at raw parameters. `kernels` (the group's module) supplies `to_local`,
`from_local`, `raw_from_carrier`, `carrier_from_raw`, `ad`, `right_jacobian`,
`right_jacobian_inverse`, `hat` and `vee`, looked up when a rule runs. Inside
the rules everything that depends on the parameters goes through these same `custom_jvp`
functions, so derivatives of every order are consistent with the carrier. An operation given as a
`jax.custom_jvp` function already is a group's override (a cheaper closed form): it keeps its own
rule, and the generic rules call it like the others.
"""

import types

import jax
import jax.numpy as jnp

from .._linalg import matvec
from . import _rules


def local_rules(kernels, *, exp, log, compose, inverse, adjoint, as_matrix, from_matrix, normalize):
    """The eight operations of a local-carrier group and its two carrier maps (`to_parameters`,
    `from_parameters`) as `jax.custom_jvp` functions.

    **Arguments:**

    - `kernels`: the group's kernel namespace (see the module docstring).
    - `exp`, ..., `normalize`: the values of each operation, plain array functions, or
      `jax.custom_jvp` functions that keep their own rules (overrides).

    **Returns:** a namespace with the same eight names and the two carrier maps, each with its
    closed-form rule."""
    values = dict(
        exp=exp, log=log, compose=compose, inverse=inverse, adjoint=adjoint, as_matrix=as_matrix,
        from_matrix=from_matrix, normalize=normalize,
    )  # fmt: skip
    generated = {name for name, value in values.items() if not isinstance(value, jax.custom_jvp)}
    ops = types.SimpleNamespace(
        **{name: jax.custom_jvp(v) if name in generated else v for name, v in values.items()}
    )

    def _exp_jvp(primals, tangents):
        (xi,), (xi_dot,) = primals, tangents
        params = ops.exp(xi)
        return params, kernels.from_local(params, matvec(kernels.right_jacobian(xi), xi_dot))

    def _log_jvp(primals, tangents):
        (params,), (carrier,) = primals, tangents
        xi = ops.log(params)
        local = kernels.to_local(params, carrier)
        return xi, matvec(kernels.right_jacobian_inverse(xi), local)

    def _compose_jvp(primals, tangents):
        (params1, params2), (carrier1, carrier2) = primals, tangents
        params = ops.compose(params1, params2)
        local1 = _rules.local_tangent(kernels.to_local, params1, carrier1)
        local2 = _rules.local_tangent(kernels.to_local, params2, carrier2)
        moved = None if local1 is None else matvec(ops.adjoint(ops.inverse(params2)), local1)
        local = _rules.add(moved, local2)
        return _rules.finish(params, None if local is None else kernels.from_local(params, local))

    def _inverse_jvp(primals, tangents):
        (params,), (carrier,) = primals, tangents
        params_inverse = ops.inverse(params)
        local = -matvec(ops.adjoint(params), kernels.to_local(params, carrier))
        return params_inverse, kernels.from_local(params_inverse, local)

    def _adjoint_jvp(primals, tangents):
        (params,), (carrier,) = primals, tangents
        matrix = ops.adjoint(params)
        return matrix, matrix @ kernels.ad(kernels.to_local(params, carrier))

    def _as_matrix_jvp(primals, tangents):
        (params,), (carrier,) = primals, tangents
        matrix = ops.as_matrix(params)
        return matrix, matrix @ kernels.hat(kernels.to_local(params, carrier))

    def _from_matrix_jvp(primals, tangents):
        (matrix,), (matrix_dot,) = primals, tangents
        params = ops.from_matrix(matrix)
        local = kernels.vee(ops.as_matrix(ops.inverse(params)) @ matrix_dot)
        return params, kernels.from_local(params, local)

    def _normalize_jvp(primals, tangents):
        (params,), (carrier,) = primals, tangents
        params_out = ops.normalize(params)
        local = kernels.to_local(params, carrier)
        return params_out, jnp.broadcast_to(kernels.from_local(params_out, local), carrier.shape)

    def _to_parameters_jvp(primals, tangents):
        (params,), (carrier,) = primals, tangents
        raw = ops.to_parameters(params)
        return raw, kernels.raw_from_carrier(raw, carrier)

    def _from_parameters_jvp(primals, tangents):
        (params,), (raw,) = primals, tangents
        return ops.from_parameters(params), kernels.carrier_from_raw(params, raw)

    ops.to_parameters = jax.custom_jvp(_identity)
    ops.from_parameters = jax.custom_jvp(_identity)
    ops.to_parameters.defjvp(_to_parameters_jvp)
    ops.from_parameters.defjvp(_from_parameters_jvp)

    rules = dict(
        exp=_exp_jvp, log=_log_jvp, compose=_compose_jvp, inverse=_inverse_jvp,
        adjoint=_adjoint_jvp, as_matrix=_as_matrix_jvp, from_matrix=_from_matrix_jvp,
        normalize=_normalize_jvp,
    )  # fmt: skip
    for name in generated:  # symbolic zeros for compose, whose rule skips a constant argument
        getattr(ops, name).defjvp(rules[name], symbolic_zeros=name == "compose")
    return ops


def _identity(params):
    """The carrier maps' values: the parameters themselves."""
    return params
