"""Local Jacobians of every operation of every group, in float64.

For each (group, operation) one jitted call evaluates, on a batch holding one point of each regime
(identity, 1e-9 from it, pure translation, ~1e-4 rad, π - 1e-6, random): the value, `lieax.jacobian`
in forward and reverse mode on the batch, `lieax.jacobian` of the unbatched function vmapped over
the batch, and `jax.jacfwd` / `jax.jacrev` on the raw parameters. The tests then compare, in NumPy:

- the value with the matrix formula (`scipy.linalg.expm` / `logm` of `hat`);
- each regime's Jacobian blocks with central finite differences on matrices, `X · expm(hat(δ))`
  (for tangent inputs, `Exp(ξ + εe_k) ⊖ Exp(ξ)`: this is what catches a wrong translation/rotation
  coupling at zero rotation);
- forward with reverse mode, the batched Jacobian (block diagonal) with the vmapped one of the
  unbatched function, and `jax.jacfwd` with `jax.jacrev`.

Compilation dominates the run time, so each case is one XLA program (`results`, cached).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from registry import (
    FD_STEP,
    FLOAT32_TOLERANCE,
    GROUPS,
    OPERATIONS,
    VALUE_ATOL_F64,
    assert_close_to_fd,
    build_arguments,
    fd_jacobians,
    fd_step,
    log_near_identity,
    random_points,
    random_tangents,
    regime_tangents,
    regimes_for,
)

import lieax

SPECS = {spec.name: spec for spec in GROUPS}
OPS = {op.name: op for op in OPERATIONS}


def build_inputs(spec, op):
    """The operation's arguments on the regime batch (see `registry.build_arguments`)."""
    return build_arguments(spec, op, regime_tangents(spec))


def _as_array(value):
    return value.as_matrix() if isinstance(value, lieax.AbstractGroup) else value


def _parameters(x):
    return x.parameters() if isinstance(x, lieax.AbstractGroup) else x


def compiled_checks(group_name, op_name):
    """The functions evaluating what the tests compare for (group, operation), all jitted together
    by `results` (one XLA program per case compiles faster than one per quantity)."""
    spec, op = SPECS[group_name], OPS[op_name]
    f = functools.partial(op.apply, spec.cls)
    argnums = op.diff

    def on_parameters(args):
        def evaluate(*params):
            rebuilt = [
                type(a)._wrap(p) if isinstance(a, lieax.AbstractGroup) else p
                for a, p in zip(args, params)
            ]
            return _parameters(f(*rebuilt))

        return evaluate, [_parameters(a) for a in args]

    def jacfwd(args):
        evaluate, params = on_parameters(args)
        return jax.jacfwd(evaluate, argnums)(*params)

    def jacrev(args):
        evaluate, params = on_parameters(args)
        return jax.jacrev(evaluate, argnums)(*params)

    return {
        "value": lambda args: _as_array(f(*args)),
        "vmapped_value": lambda args: _as_array(jax.vmap(f)(*args)),
        "fwd": lambda args: lieax.jacobian(f, argnums, mode="fwd")(*args),
        "rev": lambda args: lieax.jacobian(f, argnums, mode="rev")(*args),
        "vmapped": lambda args: jax.vmap(lieax.jacobian(f, argnums))(*args),
        "jacfwd": jacfwd,
        "jacrev": jacrev,
    }


@functools.cache
def results(group_name, op_name):
    """The jitted checks' outputs (as NumPy) and the per-element NumPy arguments."""
    spec, op = SPECS[group_name], OPS[op_name]
    args, per_element = build_inputs(spec, op)
    checks = compiled_checks(group_name, op_name)
    evaluate_all = jax.jit(lambda a: {key: check(a) for key, check in checks.items()})
    out = jax.tree_util.tree_map(np.asarray, evaluate_all(args))
    return out, per_element


def split_batched(block, count, out_ndim):
    """Per-element blocks `(R, O, I)` and the largest off-diagonal entry of a batched Jacobian block
    of shape `(R, *out, R, *in)`, `out` having `out_ndim` axes."""
    block = np.asarray(block)
    out_size = int(np.prod(block.shape[1 : 1 + out_ndim]))
    block = block.reshape(count, out_size, count, -1)
    diagonal = block[np.arange(count), :, np.arange(count), :]
    off = block.copy()
    off[np.arange(count), :, np.arange(count), :] = 0.0
    return diagonal, np.max(np.abs(off))


def out_ndim(op, value):
    """Axes of one element's output tangent: 1 for groups, the value's own axes for arrays."""
    return 1 if op.output == "group" else value.ndim - 1


CASES = [(spec, op) for spec in GROUPS for op in OPERATIONS]
CASE_IDS = [f"{spec.name}-{op.name}" for spec, op in CASES]
REGIME_CASES = [(spec, op, r) for spec, op in CASES for r in regimes_for(spec)]
REGIME_CASE_IDS = [f"{s.name}-{o.name}-{r}" for s, o, r in REGIME_CASES]


@pytest.mark.parametrize("spec, op", CASES, ids=CASE_IDS)
def test_value_matches_matrix_formula(spec, op):
    out, per_element = results(spec.name, op.name)
    for regime, value, args in zip(regimes_for(spec), out["value"], per_element):
        expected = op.reference(spec, *args)
        scale = max(1.0, np.max(np.abs(expected)))
        np.testing.assert_allclose(
            value, expected, rtol=0, atol=VALUE_ATOL_F64 * scale, err_msg=f"{spec}.{op} at {regime}"
        )


@pytest.mark.parametrize("spec, op, regime", REGIME_CASES, ids=REGIME_CASE_IDS)
def test_jacobian_matches_finite_differences(spec, op, regime):
    out, per_element = results(spec.name, op.name)
    index = regimes_for(spec).index(regime)
    expected = fd_jacobians(spec, op, per_element[index], fd_step(regime))
    for position, (argnum, reference) in enumerate(zip(op.diff, expected)):
        blocks, _ = split_batched(
            out["fwd"][position], len(per_element), out_ndim(op, out["value"])
        )
        assert_close_to_fd(blocks[index], reference, f"{spec}.{op} d/d(arg {argnum}) at {regime}")


@pytest.mark.parametrize("spec, op", CASES, ids=CASE_IDS)
def test_modes_and_batching_agree(spec, op):
    """fwd == rev; the batched Jacobian is block diagonal, its blocks those of the unbatched
    function's Jacobian (vmapped); the batched value is the vmapped one."""
    out, per_element = results(spec.name, op.name)
    count = len(per_element)
    np.testing.assert_allclose(out["vmapped_value"], out["value"], rtol=1e-13, atol=1e-13)
    for position, argnum in enumerate(op.diff):
        what = f"{spec}.{op} d/d(arg {argnum})"
        fwd, rev = out["fwd"][position], out["rev"][position]
        np.testing.assert_allclose(rev, fwd, rtol=1e-12, atol=1e-12, err_msg=f"{what}: rev vs fwd")
        blocks, off_diagonal = split_batched(fwd, count, out_ndim(op, out["value"]))
        assert off_diagonal == 0.0, f"{what}: batch elements are coupled ({off_diagonal})"
        vmapped = out["vmapped"][position].reshape(blocks.shape)
        np.testing.assert_allclose(vmapped, blocks, rtol=1e-12, atol=1e-12, err_msg=f"{what}: vmap")


@pytest.mark.parametrize("spec, op", CASES, ids=CASE_IDS)
def test_jacfwd_equals_jacrev_on_parameters(spec, op):
    out, _ = results(spec.name, op.name)
    for position, argnum in enumerate(op.diff):
        fwd, rev = out["jacfwd"][position], out["jacrev"][position]
        assert np.all(np.isfinite(fwd)), f"{spec}.{op}: jax.jacfwd not finite"
        np.testing.assert_allclose(
            rev, fwd, rtol=1e-12, atol=1e-12, err_msg=f"{spec}.{op} d/d(arg {argnum})"
        )


@functools.cache
def broadcast_results(group_name):
    """Jacobians where a single element meets a batch: `X @ Y` for X of batch (R,) and one Y,
    `X ⊖ Y` likewise, and one pose acting on a cloud of R points; with the vmapped Jacobians that
    they must equal and the inputs as NumPy."""
    spec = SPECS[group_name]
    G = spec.cls
    xis = regime_tangents(spec)
    x = G.exp(jnp.asarray(xis))
    y = G.exp(jnp.asarray(random_tangents(spec, 1, seed=3)[0]))
    cloud = jnp.asarray(random_points(spec, len(xis), seed=4))

    def compose(a, b):
        return a @ b

    def rminus(a, b):
        return a.rminus(b)

    def act(a, p):
        return a @ p

    @jax.jit
    def evaluate(x, y, cloud):
        pose = x[regimes_for(spec).index("random")]
        return {
            "compose": lieax.jacobian(compose, (0, 1))(x, y),
            "compose_vmapped": jax.vmap(lieax.jacobian(compose, (0, 1)), (0, None))(x, y),
            "rminus": lieax.jacobian(rminus, (0, 1), mode="rev")(x, y),
            "rminus_vmapped": jax.vmap(lieax.jacobian(rminus, (0, 1)), (0, None))(x, y),
            "act": lieax.jacobian(act, (0, 1))(pose, cloud),
            "act_vmapped": jax.vmap(lieax.jacobian(act, (0, 1)), (None, 0))(pose, cloud),
            "pose": pose.as_matrix(),
        }

    out = jax.tree_util.tree_map(np.asarray, evaluate(x, y, cloud))
    return out, np.asarray(cloud)


def test_jacobians_broadcast_against_a_single_element(spec):
    """The block of a single element that meets a batch holds, per batch element, that element's
    Jacobian (vmapped with `in_axes=None`); a pose acting on a cloud against finite differences."""
    out, cloud = broadcast_results(spec.name)
    count, d, s = len(cloud), spec.dim, spec.space
    for name, out_size in (("compose", d), ("rminus", d)):
        batched, vmapped = out[name], out[f"{name}_vmapped"]
        blocks, off_diagonal = split_batched(batched[0], count, 1)
        assert off_diagonal == 0.0
        np.testing.assert_allclose(blocks, vmapped[0], rtol=1e-12, atol=1e-12, err_msg=name)
        assert batched[1].shape == (count, out_size, d), name  # the single element's block
        np.testing.assert_allclose(batched[1], vmapped[1], rtol=1e-12, atol=1e-12, err_msg=name)
    pose_block, points_block = out["act"]
    assert pose_block.shape == (count, s, d)
    np.testing.assert_allclose(pose_block, out["act_vmapped"][0], rtol=1e-12, atol=1e-12)
    blocks, off_diagonal = split_batched(points_block, count, 1)
    assert off_diagonal == 0.0
    np.testing.assert_allclose(blocks, out["act_vmapped"][1], rtol=1e-12, atol=1e-12)
    act = OPS["act"]
    for i, point in enumerate(cloud):
        expected_pose, expected_point = fd_jacobians(spec, act, [out["pose"], point], FD_STEP)
        assert_close_to_fd(pose_block[i], expected_pose, f"{spec} single pose on a cloud, d/dX")
        assert_close_to_fd(blocks[i], expected_point, f"{spec} single pose on a cloud, d/dp")


# ---- right / left Jacobians of Exp: values against their definitions, and their derivatives ------


def _exp_definition_fd(spec, xi, step, side):
    """Finite differences of the definitions: column k of `Jr` is the derivative of
    `Exp(ξ)⁻¹ Exp(ξ + εe_k)`, of `Jl` that of `Exp(ξ + εe_k) Exp(ξ)⁻¹` (on matrices)."""
    base_inverse = np.linalg.inv(spec.expm(xi))
    columns = []
    for direction in np.eye(spec.dim):
        sides = []
        for sign in (1.0, -1.0):
            moved = spec.expm(xi + sign * step * direction)
            relative = base_inverse @ moved if side == "right" else moved @ base_inverse
            sides.append(spec.vee(log_near_identity(relative)))
        columns.append((sides[0] - sides[1]) / (2.0 * step))
    return np.stack(columns, axis=1)


def _log_definition_fd(spec, xi, step):
    """Finite differences of `Log(Exp(ξ) Exp(εe_k))`, whose derivative is `Jr(ξ)⁻¹`."""
    base = spec.expm(xi)
    columns = [
        (spec.logm(base @ spec.expm(step * e)) - spec.logm(base @ spec.expm(-step * e)))
        / (2 * step)
        for e in np.eye(spec.dim)
    ]
    return np.stack(columns, axis=1)


TANGENT_MAPS = ("right_jacobian", "right_jacobian_inverse")


def _reverse_and_value(tangent_map):
    """`ξ ↦ ((jax.jacrev(J)(ξ), J(ξ)), jax.jacrev(J)(ξ))`, for `jax.jacfwd(..., has_aux=True)`."""

    def evaluate(xi):
        reverse = jax.jacrev(tangent_map)(xi)
        return (reverse, tangent_map(xi)), reverse

    return evaluate


@functools.cache
def tangent_map_results(group_name):
    """Values of Jr, Jr⁻¹, Jl, Jl⁻¹ on the regime batch; first derivatives of Jr and Jr⁻¹ by
    `jax.jacfwd` and `jax.jacrev` (vmapped) and their second derivatives; values at ξ ± εe_k for
    finite differences. One jitted call.

    The derivatives come from one `jax.jacfwd` (forward mode, one tangent per coordinate of ξ) of
    `ξ ↦ (jax.jacrev(J)(ξ), J(ξ))`: its blocks are the second derivative (forward over reverse)
    and `jax.jacfwd(J)`, and the `jax.jacrev(J)` it differentiates is returned alongside (`has_aux`)
    instead of being traced again (the same values, bit for bit; a third less tracing)."""
    spec = SPECS[group_name]
    G = spec.cls
    xis = jnp.asarray(regime_tangents(spec))
    steps = jnp.asarray([fd_step(r) for r in regimes_for(spec)])
    offsets = steps[:, None, None, None] * jnp.stack([jnp.eye(spec.dim), -jnp.eye(spec.dim)], 1)

    def evaluate(xis, offsets):
        out = {
            "left_jacobian": G.left_jacobian(xis),
            "left_jacobian_inverse": G.left_jacobian_inverse(xis),
        }
        shifted = (xis[:, None, None, :] + offsets).reshape(-1, spec.dim)
        for name in TANGENT_MAPS:
            single = getattr(G, name)
            # the values at ξ and at ξ ± εe_k in one call (one copy of the kernel)
            values = single(jnp.concatenate([xis, shifted]))
            out[name] = values[: len(xis)]
            out[f"{name}_shifted"] = values[len(xis) :].reshape(*offsets.shape, spec.dim)
            (hessian, forward), reverse = jax.vmap(
                jax.jacfwd(_reverse_and_value(single), has_aux=True)
            )(xis)
            out[f"{name}_jacfwd"], out[f"{name}_jacrev"] = forward, reverse
            out[f"{name}_hessian"] = hessian
        return out

    out = jax.tree_util.tree_map(np.asarray, jax.jit(evaluate)(xis, offsets))
    return out, np.asarray(xis), np.asarray(steps)


TANGENT_CASES = [(spec, r) for spec in GROUPS for r in regimes_for(spec)]
TANGENT_IDS = [f"{spec.name}-{r}" for spec, r in TANGENT_CASES]


@pytest.mark.parametrize("spec, regime", TANGENT_CASES, ids=TANGENT_IDS)
def test_right_and_left_jacobians_match_their_definitions(spec, regime):
    out, xis, steps = tangent_map_results(spec.name)
    i = regimes_for(spec).index(regime)
    xi, step = xis[i], steps[i]
    jr_fd = _exp_definition_fd(spec, xi, step, "right")
    assert_close_to_fd(out["right_jacobian"][i], jr_fd, f"{spec} Jr at {regime}")
    jl_fd = _exp_definition_fd(spec, xi, step, "left")
    assert_close_to_fd(out["left_jacobian"][i], jl_fd, f"{spec} Jl at {regime}")
    jr_inverse_fd = _log_definition_fd(spec, xi, step)
    assert_close_to_fd(out["right_jacobian_inverse"][i], jr_inverse_fd, f"{spec} Jr⁻¹ at {regime}")
    assert_close_to_fd(
        out["left_jacobian_inverse"][i], np.linalg.inv(jl_fd), f"{spec} Jl⁻¹ at {regime}"
    )


@pytest.mark.parametrize("spec, regime", TANGENT_CASES, ids=TANGENT_IDS)
@pytest.mark.parametrize("name", TANGENT_MAPS)
def test_derivative_of_right_jacobian(spec, regime, name):
    """`jax.jacfwd` of Jr (and Jr⁻¹) against finite differences of its values, equal to
    `jax.jacrev`; second derivatives finite (also at zero)."""
    out, _, steps = tangent_map_results(spec.name)
    i = regimes_for(spec).index(regime)
    shifted = out[f"{name}_shifted"][i]  # (d, 2, d, d): direction k, sign, matrix
    fd = (shifted[:, 0] - shifted[:, 1]) / (2 * steps[i])  # (d, d_out, d_out)
    forward = out[f"{name}_jacfwd"][i]  # (d_out, d_out, d)
    assert_close_to_fd(forward, np.moveaxis(fd, 0, -1), f"{spec} d{name}/dξ at {regime}")
    np.testing.assert_allclose(out[f"{name}_jacrev"][i], forward, rtol=1e-12, atol=1e-12)
    assert np.all(np.isfinite(out[f"{name}_hessian"][i])), f"{spec} d²{name}/dξ² at {regime}"


# ---- float32 -------------------------------------------------------------------------------------

FLOAT32_CASES = [op.name for op in OPERATIONS] + list(TANGENT_MAPS)


@functools.cache
def float32_results(group_name):
    """Every operation's value and vmapped Jacobian (for Jr and Jr⁻¹: value and `jax.jacfwd`) in
    float32 on the regime batch, the float64 inputs rounded; one jitted call per group."""
    spec = SPECS[group_name]
    G = spec.cls
    inputs = {op.name: build_inputs(spec, op)[0] for op in OPERATIONS}
    inputs = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), inputs)
    xis = jnp.asarray(regime_tangents(spec), jnp.float32)

    def evaluate(inputs, xis):
        out = {}
        for op in OPERATIONS:
            f = functools.partial(op.apply, G)
            out[op.name] = (
                _as_array(f(*inputs[op.name])),
                jax.vmap(lieax.jacobian(f, op.diff))(*inputs[op.name]),
            )
        for name in TANGENT_MAPS:
            single = getattr(G, name)
            out[name] = (single(xis), (jax.vmap(jax.jacfwd(single))(xis),))
        return out

    return jax.jit(evaluate)(inputs, xis)


def float32_errors(spec, name):
    """Per regime, the largest error of the float32 value and Jacobian against float64, relative
    to max(1, |float64 value|)."""
    value32, jacobians32 = float32_results(spec.name)[name]
    assert {a.dtype for a in jax.tree_util.tree_leaves((value32, jacobians32))} == {
        jnp.dtype(jnp.float32)
    }, f"{spec}.{name}: float32 inputs gave another dtype"
    if name in TANGENT_MAPS:
        out64 = tangent_map_results(spec.name)[0]
        value64, jacobians64 = out64[name], (out64[f"{name}_jacfwd"],)
    else:
        out64 = results(spec.name, name)[0]
        value64, jacobians64 = out64["value"], out64["vmapped"]
    count = len(regimes_for(spec))

    def relative(a32, a64):
        a32 = np.asarray(a32, np.float64).reshape(count, -1)
        a64 = np.asarray(a64).reshape(count, -1)
        return np.max(np.abs(a32 - a64), axis=1) / np.maximum(1.0, np.max(np.abs(a64), axis=1))

    value_errors = relative(value32, value64)
    jacobian_errors = np.max([relative(a, b) for a, b in zip(jacobians32, jacobians64)], axis=0)
    return value_errors, jacobian_errors


@pytest.mark.parametrize("spec", GROUPS, ids=lambda s: s.name)
@pytest.mark.parametrize("name", FLOAT32_CASES)
def test_float32_accuracy(spec, name):
    """float32 values and Jacobians within the documented `FLOAT32_TOLERANCE` of float64, in every
    regime (π - 1e-6 included)."""
    value_errors, jacobian_errors = float32_errors(spec, name)
    value_tolerance, jacobian_tolerance = FLOAT32_TOLERANCE[name]
    for regime, value_error, jacobian_error in zip(
        regimes_for(spec), value_errors, jacobian_errors
    ):
        assert value_error <= value_tolerance, f"{spec}.{name} at {regime}: {value_error:.3g}"
        assert jacobian_error <= jacobian_tolerance, (
            f"{spec}.{name} Jacobian at {regime}: {jacobian_error:.3g}"
        )
