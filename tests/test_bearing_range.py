"""Bearing and range (`SE2.bearing` / `range`, `SE3.bearing` / `range`, `SO2.relative_bearing`) and
the bearing-range factor (`lieax.graph.bearing_range_factor`), float64 unless stated:

- Jacobians in local coordinates against central finite differences on matrices (NumPy
  references written here, independently of lieax) at every pose regime of the registry
  (identity, 1e-9 from it, pure translation, ~1e-4 rad, π - 1e-6, random ones) and π - 1e-4,
  for point and pose targets; forward equals reverse mode; the batched Jacobian is block diagonal
  with the vmapped unbatched blocks; Hessians of a cost through them against finite differences
  of the gradient;
- a point at the pose's origin (range 0, no bearing): the documented values, zero derivatives of
  every order, never NaN, in float32 too; tiny and huge offsets without under- or overflow;
- the bearing residual wraps across ±π (and a solve across it converges);
- the factor's closed-form 2D blocks against the rules, the 3D direction error at its series
  switch and the antipode, a 3D solve, and the errors for bad input;
- GTSAM 4.3 as the oracle (`pytest.importorskip`): `Pose2` / `Pose3` `bearing` and `range`
  values and Jacobians (rotation-first Pose3 tangents and Unit3's basis converted by
  `lieax.conventions`), and `BearingRangeFactor2D` / `3D` errors.

Each check is one jitted program per group (`results`, cached): compilation dominates.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _stacked import at_zero_and_steps
from registry import (
    GROUPS,
    assert_close_to_fd,
    random_points,
    random_tangents,
    regime_tangents,
    regimes_for,
)

import lieax
from lieax import S2, SE2, SE3, SO2
from lieax.conventions import s2_jacobian_to_gtsam, se3_jacobian_to_gtsam
from lieax.factorgraph import FactorGraph, Var
from lieax.graph import bearing_range_error, bearing_range_factor, direction_error
from lieax.groups import _s2 as s2

SPECS = {spec.name: spec for spec in GROUPS if spec.name in ("SE2", "SE3")}
STEP = 1e-6
STEP_NEAR_PI = 1e-7  # no step crosses π
HESSIAN_STEP = 1e-5


def pose_tangents(spec):
    """The registry's regimes and π - 1e-4 (the regime names in `pose_regimes`)."""
    extra = np.zeros(spec.dim)
    axis = np.array([0.3, -0.5, 0.81])[: len(spec.rotation_index)]
    extra[list(spec.rotation_index)] = (np.pi - 1e-4) * axis / np.linalg.norm(axis)
    extra[list(spec.translation_index)] = 0.7
    return np.concatenate([regime_tangents(spec), extra[None]])


def pose_regimes(spec):
    return (*regimes_for(spec), "pi_minus_1e-4")


# ---- NumPy references on matrices ----------------------------------------------------------------


def reference(spec, what, pose, target):
    """`what` ("bearing", "range") of `target` (a point, or a pose matrix whose translation is
    taken) from the pose matrix `pose`: the angle or unit vector of $d = X^{-1} p$, or $|d|$."""
    k = spec.space
    point = target[:k, k] if np.ndim(target) == 2 else target
    d = np.linalg.solve(pose, np.append(point, 1.0))[:k]
    if what == "range":
        return np.linalg.norm(d)
    return np.arctan2(d[1], d[0]) if k == 2 else d / np.linalg.norm(d)


def fd_jacobians(spec, what, pose, target, step):
    """Central differences in local coordinates: poses moved by `X expm(hat(εe))`, points by
    `p + εe`; outputs compared by the wrapped angle difference, the difference, or S2's
    `B_b^T (b₊ - b₋)` at the base value b."""
    base = reference(spec, what, pose, target)
    blocks = []
    for position, argument in enumerate((pose, target)):
        is_pose = np.ndim(argument) == 2
        columns = []
        for direction in np.eye(spec.dim if is_pose else spec.space):
            sides = []
            for sign in (1.0, -1.0):
                moved = (
                    argument @ spec.expm(sign * step * direction)
                    if is_pose
                    else argument + sign * step * direction
                )
                args = [pose, target]
                args[position] = moved
                sides.append(reference(spec, what, *args))
            difference = sides[0] - sides[1]
            if what == "bearing" and spec.space == 2:
                difference = np.angle(np.exp(1j * difference))
            if what == "bearing" and spec.space == 3:
                difference = np.asarray(s2.basis(jnp.asarray(base))).T @ difference
            columns.append(np.atleast_1d(difference) / (2 * step))
        blocks.append(np.stack(columns, axis=1))
    return blocks


# ---- the operations under test -------------------------------------------------------------------


def bearing(x, target):
    return x.bearing(target)


def range_(x, target):
    return x.range(target)


OPERATIONS = {"bearing": bearing, "range": range_}
TARGETS = ("point", "pose")


def cost(x, target):
    """A scalar through the bearing and the range, nonlinear in both: for the Hessians."""
    bearing_value, distance = x.bearing(target), x.range(target)
    array = bearing_value.log() if isinstance(bearing_value, SO2) else bearing_value.parameters()
    weights = jnp.asarray([1.0, 2.0, 3.0])[: array.shape[-1]]
    return jnp.sum(jnp.sin(weights * array)) + jnp.sin(distance) + distance**2


@functools.cache
def results(name):
    """For every operation and target kind, on the regime batch of poses (with random points and
    random target poses): values, `lieax.jacobian` forward and reverse on the batch and the
    vmapped unbatched Jacobian. One jitted program."""
    spec = SPECS[name]
    G = spec.cls
    xis = jnp.asarray(pose_tangents(spec))
    count = len(xis)
    # points 1 to 3 from the pose, in random directions: away from the origin singularity
    points = np.asarray(G.exp(xis) @ jnp.asarray(random_points(spec, count, seed=7) + 0.5))
    others = jnp.asarray(random_tangents(spec, count, seed=8))

    def evaluate(xis, points, others):
        x = G.exp(xis)
        targets = {"point": points, "pose": G.exp(others)}
        out = {}
        for what, f in OPERATIONS.items():
            for kind, target in targets.items():
                key = f"{what}-{kind}"
                value = f(x, target)
                out[key] = {
                    "value": value.parameters()
                    if isinstance(value, lieax.AbstractManifold)
                    else value,
                    "fwd": lieax.jacobian(f, (0, 1), mode="fwd")(x, target),
                    "rev": lieax.jacobian(f, (0, 1), mode="rev")(x, target),
                    "vmapped": jax.vmap(lieax.jacobian(f, (0, 1)))(x, target),
                }
        return out

    out = jax.jit(evaluate)(xis, jnp.asarray(points), others)
    return jax.tree_util.tree_map(np.asarray, out), np.asarray(points), np.asarray(others)


@functools.cache
def hessian_results(name, kind):
    """`hessians` on the inputs of `results` (one jitted program per group and target kind:
    second derivatives through SE3's Exp compile slowly)."""
    spec = SPECS[name]
    G = spec.cls
    xis = jnp.asarray(pose_tangents(spec))
    _, points, others = results(name)
    target = jnp.asarray(points) if kind == "point" else jnp.asarray(others)

    @jax.jit
    def evaluate(xis, target):
        return hessians(spec, G.exp(xis), target if kind == "point" else G.exp(target))

    return jax.tree_util.tree_map(np.asarray, evaluate(xis, target))


def hessians(spec, x, target):
    """The Hessian of `cost` in the local coordinates of (pose, target) at 0, per batch element,
    and central differences of its gradient."""
    is_pose = isinstance(target, lieax.AbstractGroup)
    size = spec.dim + (spec.dim if is_pose else spec.space)

    def local_cost(delta, x_, target_):
        moved_x = x_.rplus(delta[: spec.dim])
        rest = delta[spec.dim :]
        moved_target = target_.rplus(rest) if is_pose else target_ + rest
        return cost(moved_x, moved_target)

    def one(x_, target_):
        gradient = jax.grad(local_cost)
        zero = jnp.zeros(size)
        at_zero, plus, minus = at_zero_and_steps(
            lambda s: gradient(s, x_, target_), HESSIAN_STEP * jnp.eye(size)
        )
        return {
            "gradient": at_zero,
            "hessian": jax.hessian(local_cost)(zero, x_, target_),
            "hessian_fd": (plus - minus).T / (2 * HESSIAN_STEP),
        }

    return jax.vmap(one)(x, target)


def diagonal_blocks(block, count):
    """Per-element blocks `(count, out, in)` of a batched Jacobian block and its largest
    off-diagonal entry."""
    block = np.asarray(block).reshape(count, -1, count, block.shape[-1])
    diagonal = block[np.arange(count), :, np.arange(count), :]
    off = block.copy()
    off[np.arange(count), :, np.arange(count), :] = 0
    return diagonal, np.abs(off).max()


CASES = [
    pytest.param(name, what, kind, id=f"{name}-{what}-{kind}")
    for name in SPECS
    for what in OPERATIONS
    for kind in TARGETS
]


@pytest.mark.parametrize("name, what, kind", CASES)
def test_jacobians_match_finite_differences(name, what, kind):
    spec = SPECS[name]
    out, points, others = results(name)
    case = out[f"{what}-{kind}"]
    count = len(points)
    for index, regime in enumerate(pose_regimes(spec)):
        pose = spec.expm(pose_tangents(spec)[index])
        target = points[index] if kind == "point" else spec.expm(others[index])
        expected_value = reference(spec, what, pose, target)
        value = case["value"][index]
        if what == "bearing" and spec.space == 2:
            value = np.arctan2(value[1], value[0])
        np.testing.assert_allclose(value, expected_value, rtol=0, atol=1e-12, err_msg=regime)
        step = STEP_NEAR_PI if "pi" in regime else STEP
        expected = fd_jacobians(spec, what, pose, target, step)
        for position, reference_block in enumerate(expected):
            blocks, _ = diagonal_blocks(case["fwd"][position], count)
            assert_close_to_fd(
                blocks[index], reference_block, f"{name}.{what}({kind}) arg {position} at {regime}"
            )


@pytest.mark.parametrize("name, what, kind", CASES)
def test_modes_and_batching_agree(name, what, kind):
    out, points, _ = results(name)
    case = out[f"{what}-{kind}"]
    count = len(points)
    for position in range(2):
        fwd, rev = case["fwd"][position], case["rev"][position]
        np.testing.assert_allclose(rev, fwd, rtol=1e-12, atol=1e-12)
        blocks, off_diagonal = diagonal_blocks(fwd, count)
        assert off_diagonal == 0.0
        vmapped = case["vmapped"][position].reshape(blocks.shape)
        np.testing.assert_allclose(vmapped, blocks, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(
    "name, kind",
    [
        ("SE2", "point"),
        ("SE2", "pose"),
        ("SE3", "point"),
        # a pose target is its translation given to the point's kernels (SE2's case runs that
        # code); SE3's Hessian in 12 coordinates compiles for ~6 s of CPU
        pytest.param("SE3", "pose", marks=pytest.mark.slow),
    ],
)
def test_second_derivatives_match_finite_differences(name, kind):
    """The Hessian of `cost` (the bearing and the range together) in the local coordinates of the
    pose and the target: symmetric, finite, equal to central differences of the gradient."""
    spec = SPECS[name]
    case = hessian_results(name, kind)
    for index, regime in enumerate(pose_regimes(spec)):
        hessian, fd = case["hessian"][index], case["hessian_fd"][index]
        assert np.all(np.isfinite(case["gradient"][index])) and np.all(np.isfinite(hessian))
        scale = max(1.0, np.abs(fd).max())
        np.testing.assert_allclose(hessian, hessian.T, atol=1e-10 * scale, err_msg=regime)
        np.testing.assert_allclose(hessian, fd, rtol=0, atol=1e-6 * scale, err_msg=regime)


# ---- the origin: a point at the pose ------------------------------------------------------------


@functools.cache
def origin_results(name, dtype):
    """At the point on a random pose (d = 0): values, Jacobians, a Hessian and a gradient through
    the raw parameters. From a pure rotation, at offsets 1e-30 and 1e-200 (1e-20 and 1e-30 in
    float32) and 1e30: values. One jitted program."""
    spec = SPECS[name]
    G = spec.cls
    k = G.space_dim
    tiny = (1e-20, 1e-30) if dtype == jnp.float32 else (1e-30, 1e-200)
    xi = random_tangents(spec, 1, seed=9)[0]
    rotation_only = xi.copy()
    rotation_only[list(spec.translation_index)] = 0.0
    offsets = np.array([s * np.arange(1.0, k + 1) for s in (*tiny, 1e30)])

    @jax.jit
    def evaluate(xi, rotation_only, offsets):
        x, rotation = G.exp(xi), G.exp(rotation_only)
        on_pose = x.translation()

        return {
            "bearing": x.bearing(on_pose).parameters(),
            "range": x.range(on_pose),
            "jacobians": lieax.jacobian(bearing, (0, 1))(x, on_pose),
            "range_jacobians": lieax.jacobian(range_, (0, 1))(x, on_pose),
            "hessian": jax.hessian(lambda p: cost(x, p))(on_pose),
            "grad_raw": jax.grad(lambda q: G(q).range(on_pose) ** 2)(x.parameters()),
            "scaled_bearing": rotation.bearing(rotation @ offsets).parameters(),
            "scaled_range": rotation.range(rotation @ offsets),
        }

    args = (jnp.asarray(xi, dtype), jnp.asarray(rotation_only, dtype), jnp.asarray(offsets, dtype))
    return jax.tree_util.tree_map(np.asarray, evaluate(*args)), offsets


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("name", list(SPECS))
def test_point_at_the_pose(name, dtype):
    """Range 0 and the bearing along the pose's x axis, with zero derivatives (never NaN, nor in
    the Hessian or through the raw parameters); tiny and huge offsets keep their direction and
    length (no under- or overflow)."""
    out, offsets = origin_results(name, dtype)
    np.testing.assert_array_equal(out["bearing"], np.eye(offsets.shape[1])[0])
    assert out["range"] == 0.0
    for block in (*out["jacobians"], *out["range_jacobians"]):
        np.testing.assert_array_equal(block, 0.0)
    assert np.all(np.isfinite(out["hessian"])) and np.all(np.isfinite(out["grad_raw"]))
    np.testing.assert_array_equal(out["grad_raw"], 0.0)
    rtol = 1e-6 if dtype == jnp.float32 else 1e-14
    lengths = np.array([1e-20, 1e-30, 1e30] if dtype == jnp.float32 else [1e-30, 1e-200, 1e30])
    lengths = lengths * np.linalg.norm(np.arange(1.0, offsets.shape[1] + 1))  # NumPy underflows
    np.testing.assert_allclose(out["scaled_range"], lengths, rtol=rtol)
    directions = np.arange(1.0, offsets.shape[1] + 1) / np.linalg.norm(
        np.arange(1.0, offsets.shape[1] + 1)
    )
    np.testing.assert_allclose(
        out["scaled_bearing"], np.broadcast_to(directions, offsets.shape), rtol=rtol
    )


def test_relative_bearing():
    """`SO2.relative_bearing` is the angle of a direction, the identity at zero, with Jacobian
    $(-d_y, d_x)/|d|^2$ (GTSAM's `Rot2::relativeBearing`)."""
    d = jnp.asarray([[3.0, 4.0], [-1.0, -1e-3], [0.0, 0.0]])
    angle, J = jax.jit(
        lambda d: (
            SO2.relative_bearing(d).as_angle(),
            jax.vmap(lieax.jacobian(SO2.relative_bearing))(d),
        )
    )(d)
    np.testing.assert_allclose(angle, np.arctan2(d[:, 1], d[:, 0]), atol=1e-15)
    expected = np.stack([-d[:, 1], d[:, 0]], 1) / np.maximum(np.sum(d**2, 1), 1e-300)[:, None]
    np.testing.assert_allclose(J[:, 0], expected, rtol=1e-14)
    with pytest.raises(ValueError, match=r"SO2.relative_bearing direction must have shape"):
        SO2.relative_bearing(jnp.ones(3))


def test_target_checks():
    """Targets of the wrong size, group, dtype or batch shape: errors naming the operation, at
    trace time (traced only, `jax.eval_shape`); batch shapes broadcast."""

    def traced(f):
        return jax.eval_shape(f)

    x2, x3 = SE2.identity(), SE3.identity()
    with pytest.raises(ValueError, match=r"SE2.bearing target must have shape \(\*batch, 2\)"):
        traced(lambda: x2.bearing(jnp.ones(3)))
    with pytest.raises(TypeError, match="SE2.range needs another SE2, got SE3"):
        traced(lambda: x2.range(x3))
    with pytest.raises(TypeError, match="SE3.bearing target has dtype float32"):
        traced(lambda: x3.bearing(jnp.ones(3, jnp.float32)))
    with pytest.raises(ValueError, match=r"SE3.range: batch shapes \(2,\) and \(3,\)"):
        traced(lambda: SE3.identity((2,)).range(jnp.ones((3, 3))))
    assert traced(lambda: SE3.identity((2, 1)).bearing(jnp.ones((4, 3)))).batch_shape == (2, 4)
    assert isinstance(traced(lambda: x3.bearing(jnp.ones(3))), S2)
    assert traced(lambda: x2.range(SE2.identity((5,)))).shape == (5,)


# ---- the wrap at ±π --------------------------------------------------------------------------------


def test_bearing_residual_wraps():
    """A landmark behind the pose: measured at π - 0.01, predicted at -π + 0.01: the residual is
    +0.02 (not 0.02 - 2π), continuous across the cut, so its Jacobian matches plain central
    differences there."""
    pose = SE2.from_xy_theta(0.3, -0.2, 0.0)
    behind = pose @ jnp.asarray([-2.0, -2.0 * np.tan(0.01)])  # bearing -π + 0.01
    measured = (SO2.from_angle(np.pi - 0.01), jnp.asarray(2.0))
    residual = jax.jit(bearing_range_error)
    error, (J_pose, J_landmark) = jax.jit(lieax.value_and_jacobian(bearing_range_error, (0, 1)))(
        pose, behind, measured
    )
    np.testing.assert_allclose(error[0], 0.02, atol=1e-14)
    step = 1e-6
    for k, direction in enumerate(np.eye(3)):
        plus = residual(pose.rplus(step * direction), behind, measured)
        minus = residual(pose.rplus(-step * direction), behind, measured)
        np.testing.assert_allclose(J_pose[:, k], (plus - minus) / (2 * step), atol=1e-8)
    for k, direction in enumerate(np.eye(2)):
        plus = residual(pose, behind + step * direction, measured)
        minus = residual(pose, behind - step * direction, measured)
        np.testing.assert_allclose(J_landmark[:, k], (plus - minus) / (2 * step), atol=1e-8)


def test_solve_across_the_wrap():
    """Landmarks behind two fixed poses, their bearings near ±π, starting where the predicted
    bearings are on the other side of the cut from the measured ones: the solve reaches the
    truth (an angle difference would be 2π off and pull them around the circle)."""
    truth = np.array([[-3.0, 0.02], [-3.0, -0.05]])
    poses = SE2.from_xy_theta(jnp.asarray([0.0, 0.5]), jnp.asarray([0.0, 0.1]), jnp.zeros(2))
    i, j = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])
    offsets = truth[j] - np.asarray(poses.translation())[i]
    bearings = np.arctan2(offsets[:, 1], offsets[:, 0])
    start = truth + np.array([[-0.5, -0.4], [-0.3, 0.6]])
    predicted = np.arctan2(start[j, 1] - np.asarray(poses.translation())[i, 1], start[j, 0])
    assert np.any(np.abs(predicted - bearings) > np.pi)  # the start is across the cut
    pose_var = Var(poses, fixed=[0, 1], name="poses")
    landmarks = Var(jnp.asarray(start), name="landmarks")
    factor = bearing_range_factor(
        pose_var[i], landmarks[j], bearings, np.linalg.norm(offsets, axis=1), sigmas=(0.01, 0.1)
    )
    result = FactorGraph([factor]).solve()
    assert result.status_name == "CONVERGED"
    np.testing.assert_allclose(result.values[1], truth, atol=1e-6)
    assert float(result.cost) < 1e-12


# ---- the factor ----------------------------------------------------------------------------------


@functools.cache
def factor_results():
    """The 2D closed-form blocks and the rules' blocks (`lieax.value_and_jacobian`), at random
    poses, landmarks and measurements and at a landmark on its pose; the 3D direction error
    around its series switch, at the antipode and on random pairs. One jitted program."""
    rng = np.random.default_rng(11)
    count = 6
    xi = jnp.asarray(random_tangents(SPECS["SE2"], count, seed=12))
    landmarks = rng.normal(size=(count, 2)) * 3
    # on the pose, exactly: through the traced kernel `evaluate` runs (SE2.exp of a concrete
    # tangent takes the NumPy path, a few ulp away)
    landmarks[0] = np.asarray(jax.jit(lambda x: SE2.exp(x).translation())(xi[:1])[0])
    measured = (SO2.from_angle(jnp.asarray(rng.uniform(-np.pi, np.pi, count))),
                jnp.asarray(rng.uniform(0.5, 3, count)))  # fmt: skip
    m = S2.sample_uniform(jax.random.PRNGKey(3), (count,)).parameters()
    m = m.at[1].set(m[0])  # the first two on either side of the switch, from one m
    basis = s2.basis(m)
    # directions at angles around the switch (sin² θ = 1e-2), tiny, 100°, 179.9° from m
    angles = jnp.asarray([np.arcsin(0.1) - 1e-9, np.arcsin(0.1) + 1e-9, 1e-9, 1.7, 3.14, 0.4])
    b = jnp.cos(angles)[:, None] * m + jnp.sin(angles)[:, None] * basis[..., 0]

    @jax.jit
    def evaluate(xi, landmarks, measured, m, b):
        poses = SE2.exp(xi)
        closed = jax.vmap(lieax.graph.bearing_range_jacobians_2d)(poses, landmarks, measured)
        rules = jax.vmap(lieax.value_and_jacobian(bearing_range_error, (0, 1)))(
            poses, landmarks, measured
        )
        antipode = direction_error(m[0], -m[0])
        return {
            "closed": closed,
            "rules": rules,
            "direction_error": direction_error(m, b),
            "direction_jacobian": jax.vmap(jax.jacfwd(direction_error, 1))(m, b),
            "direction_hessian": jax.vmap(
                jax.hessian(lambda m_, b_: direction_error(m_, b_)[0], 1)
            )(m, b),
            "antipode": antipode,
            "b": b,
            "antipode_jacobian": jax.jacfwd(direction_error, 1)(m[0], -m[0]),
        }

    out = evaluate(xi, jnp.asarray(landmarks), measured, m, b)
    return jax.tree_util.tree_map(np.asarray, out), np.asarray(angles), np.asarray(basis)


def test_closed_form_blocks_2d():
    out, _, _ = factor_results()
    (error, blocks), (rule_error, rule_blocks) = out["closed"], out["rules"]
    np.testing.assert_allclose(error, rule_error, atol=1e-15)
    for block, rule_block in zip(blocks, rule_blocks):
        np.testing.assert_allclose(block, rule_block, rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(block[0], 0.0)  # the landmark on its pose


def test_direction_error():
    """Norm θ (the angle), smooth across the series switch in value and derivative, $B_m^\\top$
    at $b = m$ (to first order), $(\\pi, 0)$ with a zero derivative at the antipode."""
    out, angles, basis = factor_results()
    error = out["direction_error"]
    # (b itself is rounded: 1e-16 of the tiny angle's 1e-9)
    np.testing.assert_allclose(np.linalg.norm(error, axis=1), angles, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(error[0] / angles[0], error[1] / angles[1], atol=1e-12)
    jacobian = out["direction_jacobian"]
    np.testing.assert_allclose(jacobian[0], jacobian[1], atol=1e-8)  # 2e-9 rad apart
    radial = np.einsum("kij,kj->ki", jacobian, np.asarray(out["b"]))
    np.testing.assert_allclose(radial, 0.0, atol=1e-12)  # a function of b's direction
    np.testing.assert_allclose(jacobian[2], np.swapaxes(basis[2], 0, 1), atol=1e-8)
    assert np.all(np.isfinite(jacobian)) and np.all(np.isfinite(out["direction_hessian"]))
    np.testing.assert_array_equal(out["antipode"], [np.pi, 0.0])
    np.testing.assert_array_equal(out["antipode_jacobian"], 0.0)
    np.testing.assert_allclose(np.linalg.norm(error[4]), 3.14, rtol=1e-13)  # 1.6e-3 from it


def test_solve_3d():
    """Noise-free sightings of 8 landmarks from 3 poses (the first fixed), starting perturbed:
    the solve reaches the truth with zero cost."""
    rng = np.random.default_rng(13)
    truth_poses = SE3.exp(jnp.asarray(random_tangents(SPECS["SE3"], 3, seed=14)))
    truth_landmarks = rng.normal(size=(8, 3)) * 2
    i, j = np.repeat(np.arange(3), 8), np.tile(np.arange(8), 3)
    seen = truth_poses[i].inverse() @ jnp.asarray(truth_landmarks[j])
    ranges = np.linalg.norm(seen, axis=1)
    start = truth_poses.rplus(jnp.asarray(rng.normal(size=(3, 6)) * 0.05))
    poses = Var(SE3(jnp.concatenate([truth_poses[:1].parameters(), start[1:].parameters()])),
                fixed=[0], name="poses")  # fmt: skip
    landmarks = Var(jnp.asarray(truth_landmarks + rng.normal(size=(8, 3)) * 0.1), name="points")
    factor = bearing_range_factor(poses[i], landmarks[j], seen, ranges, sigmas=(0.01, 0.01, 0.1))
    result = FactorGraph([factor]).solve()
    assert result.status_name == "CONVERGED" and float(result.cost) < 1e-16
    np.testing.assert_allclose(result.values[1], truth_landmarks, atol=1e-7)
    np.testing.assert_allclose(result.values[0].parameters(), truth_poses.parameters(), atol=1e-7)


def test_factor_input_errors():
    poses = Var(SE2.identity((2,)), name="poses")
    points = Var(jnp.ones((3, 2)), name="points")
    points3 = Var(jnp.ones((3, 3)), name="points3")
    i, j = np.array([0, 1]), np.array([0, 2])
    good = dict(bearings=np.array([0.1, 0.2]), ranges=np.array([1.0, 2.0]))
    with pytest.raises(TypeError, match="'bearing_range': the pose Var must hold SE2 or SE3"):
        bearing_range_factor(points[i], points[j], **good)
    with pytest.raises(ValueError, match=r"SE2 poses need landmarks of shape \(n, 2\), got"):
        bearing_range_factor(poses[i], points3[j], **good)
    with pytest.raises(TypeError, match="landmarks have dtype float32, the poses float64"):
        bearing_range_factor(poses[i], Var(jnp.ones((3, 2), jnp.float32))[j], **good)
    with pytest.raises(ValueError, match=r"bearings must be SO2 or angles of shape \(2,\)"):
        bearing_range_factor(poses[i], points[j], np.zeros(3), good["ranges"])
    with pytest.raises(TypeError, match="SE2 poses need SO2 bearings, got S2"):
        bearing_range_factor(poses[i], points[j], S2.from_vector(jnp.ones((2, 3))), [1.0, 2.0])
    with pytest.raises(ValueError, match="bearing 1 is not finite"):
        bearing_range_factor(poses[i], points[j], [0.1, np.nan], good["ranges"])
    with pytest.raises(ValueError, match="range 0 is not finite"):
        bearing_range_factor(poses[i], points[j], good["bearings"], [np.inf, 1.0])
    with pytest.raises(ValueError, match="sigmas must be positive and finite"):
        bearing_range_factor(poses[i], points[j], **good, sigmas=(0.1, 0.0))
    with pytest.raises(ValueError, match=r"sigmas must have shape \(2,\) or \(m, 2\)"):
        bearing_range_factor(poses[i], points[j], **good, sigmas=(0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match="give sigmas or one of"):
        bearing_range_factor(poses[i], points[j], **good, sigmas=(1, 1), information=np.eye(2))
    poses3 = Var(SE3.identity((2,)), name="poses3")
    with pytest.raises(ValueError, match="bearing 0 is not finite .or a zero vector"):
        bearing_range_factor(poses3[i], points3[j], np.zeros((2, 3)), good["ranges"])
    factor = bearing_range_factor(poses3[i], points3[j], np.ones((2, 3)), good["ranges"])
    np.testing.assert_allclose(np.asarray(factor.data[0].parameters()), 1 / np.sqrt(3))


# ---- GTSAM as the oracle ------------------------------------------------------------------------


def gtsam_pose(gtsam, matrix):
    if matrix.shape == (3, 3):
        return gtsam.Pose2(matrix[0, 2], matrix[1, 2], np.arctan2(matrix[1, 0], matrix[0, 0]))
    return gtsam.Pose3(gtsam.Rot3(matrix[:3, :3]), matrix[:3, 3])


def gtsam_pose2_to_pose2(gtsam, what, pose, other):
    """`Pose2::bearing(Pose2)` / `range(Pose2)` and their Jacobians, which GTSAM's Python wrapper
    leaves out, through `BearingFactorPose2` / `RangeFactorPose2` (measured 0, unit noise: the
    error is the prediction, its linearization the Jacobians)."""
    values = gtsam.Values()
    values.insert(0, pose)
    values.insert(1, other)
    noise = gtsam.noiseModel.Unit.Create(1)
    if what == "bearing":
        factor = gtsam.BearingFactorPose2(0, 1, gtsam.Rot2(0.0), noise)
    else:
        factor = gtsam.RangeFactorPose2(0, 1, 0.0, noise)
    A, b = factor.linearize(values).jacobian()
    value = -b[0]
    return ([np.cos(value), np.sin(value)] if what == "bearing" else value), A[:, :3], A[:, 3:]


@pytest.mark.parametrize("name", list(SPECS))
def test_bearing_and_range_match_gtsam(name):
    """`Pose2` / `Pose3` `bearing` and `range` of points and poses: values and both Jacobians at
    every regime (lieax's converted: Pose3 tangents rotation first, Unit3's basis)."""
    gtsam = pytest.importorskip("gtsam")
    spec = SPECS[name]
    out, points, others = results(name)
    count, three = len(points), spec.space == 3
    for index, regime in enumerate(pose_regimes(spec)):
        pose = gtsam_pose(gtsam, spec.expm(pose_tangents(spec)[index]))
        other = gtsam_pose(gtsam, spec.expm(others[index]))
        for what in OPERATIONS:
            for kind, target in (("point", points[index]), ("pose", other)):
                case = out[f"{what}-{kind}"]
                rows = 2 if what == "bearing" and three else 1
                if kind == "pose" and not three:
                    value, H1, H2 = gtsam_pose2_to_pose2(gtsam, what, pose, other)
                else:
                    H1 = np.zeros((rows, spec.dim), order="F")
                    H2 = np.zeros((rows, spec.dim if kind == "pose" else spec.space), order="F")
                    value = getattr(pose, what)(target, H1, H2)
                ours = [diagonal_blocks(block, count)[0][index] for block in case["fwd"]]
                if what == "bearing" and three:
                    direction = S2(jnp.asarray(case["value"][index]))
                    ours = [s2_jacobian_to_gtsam(J, row_direction=direction) for J in ours]
                    value = value.point3()
                elif what == "bearing" and isinstance(value, gtsam.Rot2):
                    value = [value.c(), value.s()]
                if three:
                    ours[0] = se3_jacobian_to_gtsam(ours[0], rows=False)
                    if kind == "pose":
                        ours[1] = se3_jacobian_to_gtsam(ours[1], rows=False)
                what_ = f"{name}.{what}({kind}) at {regime}"
                np.testing.assert_allclose(case["value"][index], value, atol=1e-12, err_msg=what_)
                np.testing.assert_allclose(ours[0], H1, atol=1e-9, err_msg=f"{what_}: H1")
                np.testing.assert_allclose(ours[1], H2, atol=1e-9, err_msg=f"{what_}: H2")


def test_factor_matches_gtsam():
    """`BearingRangeFactor2D`: the same error and whitened Jacobian (GTSAM's linearization);
    `BearingRangeFactor3D` with equal bearing sigmas: the same error, with measured directions
    ~0.3 rad, ~170° and random angles from the predicted ones."""
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(15)
    for dim, group in ((2, SE2), (3, SE3)):
        spec = SPECS[group.__name__]
        poses = group.exp(jnp.asarray(random_tangents(spec, 5, seed=16)))
        landmarks = jnp.asarray(rng.normal(size=(5, dim)) * 3)
        ranges = rng.uniform(0.5, 4, 5)
        sigmas = np.array([0.05, 0.2] if dim == 2 else [0.05, 0.05, 0.2])
        if dim == 2:
            bearings = rng.uniform(-np.pi, np.pi, 5)
            measured = (SO2.from_angle(jnp.asarray(bearings)), jnp.asarray(ranges))
        else:
            seen = np.asarray(poses.inverse() @ jnp.asarray(landmarks))
            # directions ~0.3 rad, ~170° and random angles from the predicted ones
            vectors = np.concatenate(
                [
                    seen[:2]
                    + 0.3 * rng.normal(size=(2, 3)) * np.linalg.norm(seen[:2], axis=1)[:, None],
                    rng.normal(size=(3, 3)),
                ]
            )
            vectors[2] = -seen[2] + 0.2 * np.cross(seen[2], [0, 0, 1.0])
            measured = (S2.from_vector(jnp.asarray(vectors)), jnp.asarray(ranges))
        errors = np.asarray(jax.jit(jax.vmap(bearing_range_error))(poses, landmarks, measured))
        if dim == 2:
            blocks = jax.jit(jax.vmap(lieax.graph.bearing_range_jacobians_2d))(
                poses, landmarks, measured
            )[1]
            whitened = np.concatenate(blocks, axis=2) / sigmas[:, None]
        costs = 0.5 * np.sum((errors / sigmas) ** 2, axis=1)
        matrices = np.asarray(poses.as_matrix())
        noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        for k in range(5):
            pose = gtsam_pose(gtsam, matrices[k])
            values = gtsam.Values()
            values.insert(0, pose)
            values.insert(1, np.asarray(landmarks[k]))
            if dim == 2:
                factor = gtsam.BearingRangeFactor2D(
                    0, 1, gtsam.Rot2.fromAngle(bearings[k]), ranges[k], noise
                )
            else:
                factor = gtsam.BearingRangeFactor3D(0, 1, gtsam.Unit3(vectors[k]), ranges[k], noise)
            np.testing.assert_allclose(costs[k], factor.error(values), rtol=1e-12)
            if dim == 2:
                gtsam_whitened, _ = factor.linearize(values).jacobian()
                np.testing.assert_allclose(gtsam_whitened, whitened[k], atol=1e-10)
