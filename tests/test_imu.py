"""IMU preintegration and factors (`lieax.imu`): against GTSAM 4.3's
`PreintegratedImuMeasurements` (`TangentPreintegration`), `ImuFactor` and `CombinedImuFactor` on
random sample streams (`_imu_streams`); bias Jacobians and factor Jacobians against finite
differences; the logarithmic-depth variant against the sequential scan; batching and bad input."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _imu_streams import (
    ARM,
    BIAS,
    NOISE,
    SAMPLES,
    entrywise_over_intervals,
    gtsam_bias,
    gtsam_params,
    gtsam_pose,
    integrate,
    relative,
    stream,
)

import lieax.imu as imu
from lieax import SE3, SO3
from lieax import conventions as cv
from lieax.autodiff import rplus, tangent_dim, unflatten_tangents, value_and_jacobian

PARAMS = imu.ImuParams.make_u(9.81, **NOISE)
PARAMS_ARM = PARAMS._replace(body_P_sensor=ARM)
WALK = imu.BiasRandomWalk(np.diag([1e-4, 2e-4, 3e-4]), np.diag([1e-6, 2e-6, 3e-6]))

sequential = jax.jit(imu.preintegrate)
associative = jax.jit(imu.preintegrate_associative)
combined = jax.jit(imu.preintegrate_combined)
# vmap maps keyword arguments over their axis 0: the samples, per interval; params, bias shared.
over_intervals = jax.jit(jax.vmap(imu.preintegrate, in_axes=(None, None)))
closed_form = jax.jit(imu.imu_jacobians, static_argnames="error_mode")
combined_closed_form = jax.jit(imu.combined_imu_jacobians, static_argnames="error_mode")
MODES = ("logmap", "component_wise")  # GTSAM 4.3's default ImuFactorErrorMode first
residual_and_jacobians = {
    mode: jax.jit(
        value_and_jacobian(functools.partial(imu.imu_residual, error_mode=mode), (0, 1, 2, 3, 4))
    )
    for mode in MODES
}


def vector(pim):
    return np.concatenate([pim.theta, pim.delta_p, pim.delta_v])


# ---- GTSAM ----------------------------------------------------------------------------------------


def gtsam_pim(gtsam, gyro, accel, dt, with_arm=False, error_mode="logmap"):
    params = gtsam_params(
        gtsam, gtsam.PreintegrationParams, with_arm=with_arm, error_mode=error_mode
    )
    return integrate(gtsam.PreintegratedImuMeasurements(params, gtsam_bias(BIAS)), gyro, accel, dt)


def gtsam_bias_jacobians(pim):
    """`[preintegrated_H_biasAcc, preintegrated_H_biasOmega]` (9×6), not wrapped in Python: read
    from the text serialization, where they are the two 9×3 matrices (column-major) in order."""
    tokens = pim.serialize().split()
    blocks = [
        np.array(tokens[k + 2 : k + 29], dtype=float).reshape(3, 9).T
        for k in range(len(tokens) - 1)
        if tokens[k] == "9" and tokens[k + 1] == "3"
    ]
    assert len(blocks) == 2
    return np.concatenate(blocks, axis=1)


@pytest.mark.parametrize("with_arm", [False, True])
def test_preintegration_matches_gtsam(with_arm):
    gtsam = pytest.importorskip("gtsam")
    gyro, accel, dt = stream(0)
    reference = gtsam_pim(gtsam, gyro, accel, dt, with_arm)
    ours = sequential(PARAMS_ARM if with_arm else PARAMS, BIAS, accel=accel, gyro=gyro, dt=dt)
    assert relative(vector(ours), reference.preintegrated()) < 1e-12
    assert relative(ours.delta_R.as_matrix(), reference.deltaRij().matrix()) < 1e-12
    assert relative(ours.delta_v, reference.deltaVij()) < 1e-12
    assert relative(ours.delta_p, reference.deltaPij()) < 1e-12
    assert float(ours.delta_t) == pytest.approx(reference.deltaTij(), rel=1e-14)
    assert relative(ours.covariance, reference.preintMeasCov()) < 1e-9
    assert relative(ours.jacobian_bias, gtsam_bias_jacobians(reference)) < 1e-9
    assert relative(ours.residual_covariance(), reference.residualCovariance()) < 1e-9


@pytest.mark.parametrize("error_mode", MODES)
def test_predict_and_factor_match_gtsam(error_mode):
    r"""`predict` as `PreintegrationBase::predict`; the residual and all five Jacobians, by
    autodiff and in closed form (`imu_jacobians`), as `ImuFactor.evaluateError` in the same
    error mode (the default: GTSAM's default parameters, `Logmap`; `ComponentWise` set in
    GTSAM), pose columns permuted to lieax's $(v, \omega)$; the whitened cost as `error`."""
    gtsam = pytest.importorskip("gtsam")
    gyro, accel, dt = stream(1)
    reference = gtsam_pim(gtsam, gyro, accel, dt, error_mode=error_mode)
    pim = sequential(PARAMS, BIAS, accel=accel, gyro=gyro, dt=dt)
    mode = {} if error_mode == "logmap" else dict(error_mode=error_mode)  # the default: logmap
    rng = np.random.default_rng(2)
    poses = SE3.exp(jnp.asarray(rng.normal(size=(2, 6))))
    pose_i, pose_j = poses[0], poses[1]
    velocity_i, velocity_j = rng.normal(size=(2, 3))
    bias_i = BIAS + 0.01 * rng.normal(size=6)
    bias_g = gtsam_bias(bias_i)

    predicted = reference.predict(gtsam.NavState(gtsam_pose(pose_i), velocity_i), bias_g)
    pose_hat, velocity_hat = imu.predict(pim, pose_i, velocity_i, bias_i, PARAMS)
    assert relative(pose_hat.as_matrix(), predicted.pose().matrix()) < 1e-12
    assert relative(velocity_hat, predicted.velocity()) < 1e-12

    factor = gtsam.ImuFactor(1, 2, 3, 4, 5, reference)
    shapes = (6, 3, 6, 3, 6)
    h = [np.zeros((9, n), order="F") for n in shapes]
    error = factor.evaluateError(
        gtsam_pose(pose_i), velocity_i, gtsam_pose(pose_j), velocity_j, bias_g, *h
    )
    value, jacobians = residual_and_jacobians[error_mode](
        pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, PARAMS
    )
    closed_value, closed = closed_form(
        pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, PARAMS, **mode
    )
    assert relative(value, error) < 1e-12
    assert relative(closed_value, error) < 1e-12
    for k, (ours, mine, theirs) in enumerate(zip(jacobians, closed, h)):
        if shapes[k] == 6 and k != 4:
            theirs = np.asarray(cv.se3_jacobian_from_gtsam(theirs, rows=False))
        assert relative(ours, theirs) < 1e-9, k
        assert relative(mine, theirs) < 1e-9, k
    for seed in range(3, 9):  # more random states: the closed form against GTSAM's
        r = np.random.default_rng(seed)
        states = SE3.exp(jnp.asarray(r.normal(size=(2, 6)) * [5, 5, 5, 1.5, 1.5, 1.5]))
        state = (states[0], *5 * r.normal(size=(1, 3)), states[1], *5 * r.normal(size=(1, 3)))
        bias = BIAS + 0.02 * r.normal(size=6)
        h = [np.zeros((9, n), order="F") for n in shapes]
        theirs_state = (gtsam_pose(state[0]), state[1], gtsam_pose(state[2]), state[3])
        error = factor.evaluateError(*theirs_state, gtsam_bias(bias), *h)
        value, blocks = closed_form(*state, bias, pim, PARAMS, **mode)
        assert relative(value, error) < 1e-10, seed
        for k, (mine, theirs) in enumerate(zip(blocks, h)):
            if k in (0, 2):
                theirs = np.asarray(cv.se3_jacobian_from_gtsam(theirs, rows=False))
            assert relative(mine, theirs) < 1e-10, (seed, k)

    # imu_factor whitens as ImuFactor's noise model: 0.5 |L⁻¹ r|² = error.
    from lieax.factorgraph import Var

    pose_var, vector_var = Var(poses), Var(jnp.asarray([velocity_i, velocity_j]))
    bias_var = Var(jnp.asarray([bias_i, bias_i]))
    i, j = np.array([0]), np.array([1])
    ours_factor = imu.imu_factor(
        jax.tree.map(lambda x: x[None], pim), PARAMS,
        pose_var[i], vector_var[i], pose_var[j], vector_var[j], bias_var[i], **mode,
    )  # fmt: skip
    values = gtsam.Values()
    theirs = (gtsam_pose(pose_i), velocity_i, gtsam_pose(pose_j), velocity_j, bias_g)
    for key, x in enumerate(theirs, 1):
        values.insert(key, x)
    whitened = ours_factor.sqrt_information[0] @ np.asarray(closed_value)
    assert 0.5 * whitened @ whitened == pytest.approx(factor.error(values), rel=1e-9)
    _, blocks = ours_factor.jacobian_fn(pose_i, velocity_i, pose_j, velocity_j, bias_i, pim)
    for mine, expected in zip(blocks, closed):  # the factor's blocks are this mode's
        np.testing.assert_allclose(mine, expected, rtol=0, atol=1e-14)


@pytest.mark.parametrize("error_mode", MODES)
def test_combined_factor_matches_gtsam(error_mode):
    r"""`combined_imu_factor` as GTSAM 4.3's `CombinedImuFactor` (in `error_mode`; anisotropic
    bias random walks; distinct $b_i$, $b_j$) on the same stream: the 15-vector error and all six
    Jacobian blocks in closed form (`combined_imu_jacobians`) after `lieax.conventions` (bias
    rows negated, pose columns permuted), the residual's covariance as its noise model's, and the
    factor's whitened cost $\tfrac12\|R r\|^2$ as GTSAM's `error`."""
    gtsam = pytest.importorskip("gtsam")
    from lieax.factorgraph import Var
    from lieax.imu._factors import _combined_residual_covariance

    gyro, accel, dt = stream(11)
    g_params = gtsam_params(gtsam, gtsam.PreintegrationCombinedParams, error_mode=error_mode)
    g_params.setBiasAccCovariance(np.asarray(WALK.accelerometer_bias_covariance))
    g_params.setBiasOmegaCovariance(np.asarray(WALK.gyroscope_bias_covariance))
    reference = integrate(
        gtsam.PreintegratedCombinedMeasurements(g_params, gtsam_bias(BIAS)), gyro, accel, dt
    )
    pim, covariance = combined(PARAMS, WALK, BIAS, accel=accel, gyro=gyro, dt=dt)
    rng = np.random.default_rng(12)
    poses = SE3.exp(jnp.asarray(rng.normal(size=(2, 6))))
    velocities = rng.normal(size=(2, 3))
    biases = BIAS + 0.01 * rng.normal(size=(2, 6))
    ours = (poses[0], velocities[0], poses[1], velocities[1], biases[0], biases[1])
    theirs = (
        gtsam_pose(poses[0]), velocities[0], gtsam_pose(poses[1]), velocities[1],
        gtsam_bias(biases[0]), gtsam_bias(biases[1]),
    )  # fmt: skip
    factor = gtsam.CombinedImuFactor(1, 2, 3, 4, 5, 6, reference)
    h = [np.zeros((15, n), order="F") for n in (6, 3, 6, 3, 6, 6)]
    error = factor.evaluateError(*theirs, *h)
    flip = np.diag(np.repeat([1.0, -1.0], [9, 6]))  # GTSAM's bias rows are b_i - b_j
    mode = {} if error_mode == "logmap" else dict(error_mode=error_mode)  # the default: logmap
    value, blocks = combined_closed_form(*ours, pim, PARAMS, **mode)
    assert relative(value, flip @ error) < 1e-12
    assert relative(value[9:], biases[1] - biases[0]) < 1e-15
    for k, (mine, expected) in enumerate(zip(blocks, h)):
        expected = flip @ expected
        if k in (0, 2):
            expected = np.asarray(cv.se3_jacobian_from_gtsam(expected, rows=False))
        assert relative(mine, expected) < 1e-9, k
    residual_covariance = _combined_residual_covariance(pim, covariance)
    assert relative(residual_covariance, flip @ factor.noiseModel().covariance() @ flip) < 1e-9

    pose_var, velocity_var = Var(poses, name="poses"), Var(jnp.asarray(velocities))
    bias_var = Var(jnp.asarray(biases), name="biases")
    i, j = np.array([0]), np.array([1])
    ours_factor = imu.combined_imu_factor(
        jax.tree.map(lambda x: x[None], pim), covariance[None], PARAMS,
        pose_var[i], velocity_var[i], pose_var[j], velocity_var[j], bias_var[i], bias_var[j],
        **mode,
    )  # fmt: skip
    values = gtsam.Values()
    for key, x in enumerate(theirs, 1):
        values.insert(key, x)
    whitened = ours_factor.sqrt_information[0] @ np.asarray(value)
    assert 0.5 * whitened @ whitened == pytest.approx(factor.error(values), rel=1e-9)


# ---- lieax only -----------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["sequential", "associative"])
@pytest.mark.parametrize("rate_scale", [1.0, 0.0])
def test_bias_jacobians_by_finite_differences(variant, rate_scale):
    """`jacobian_bias` against central differences of re-integration with perturbed biases; at
    `rate_scale=0` the corrected rotation rate is exactly zero (gyro = gyro bias)."""
    integrate = {"sequential": sequential, "associative": associative}[variant]
    gyro, accel, dt = stream(3, rate_scale=rate_scale)
    gyro = gyro + BIAS[3:] * (rate_scale == 0.0)
    samples = dict(accel=accel, gyro=gyro, dt=dt)
    pim = integrate(PARAMS_ARM, BIAS, **samples)
    eps = 1e-6
    columns = [
        (vector(integrate(PARAMS_ARM, BIAS + eps * e, **samples))
         - vector(integrate(PARAMS_ARM, BIAS - eps * e, **samples))) / (2 * eps)
        for e in np.eye(6)
    ]  # fmt: skip
    np.testing.assert_allclose(pim.jacobian_bias, np.stack(columns, 1), atol=1e-8, rtol=1e-6)


def test_associative_agrees_to_first_order_in_dt():
    r"""The group product and GTSAM's tangent recursion are both consistent integrators of
    piecewise constant samples: they differ by $O(\delta t)$, halving when each sample is split
    in two (measured: 3e-6 relative for 60 samples at 5 ms and 1 rad/s)."""
    gyro, accel, dt = stream(4)
    differences = []
    for split in (1, 2):
        samples = dict(
            accel=np.repeat(accel, split, 0),
            gyro=np.repeat(gyro, split, 0),
            dt=np.repeat(dt / split, split),
        )
        a, b = sequential(PARAMS, BIAS, **samples), associative(PARAMS, BIAS, **samples)
        differences.append([
            relative(vector(b), vector(a)),
            relative(b.covariance, a.covariance),
            relative(b.jacobian_bias, a.jacobian_bias),
        ])  # fmt: skip
    differences = np.array(differences)
    assert np.all(differences[0] < 1e-3)
    np.testing.assert_allclose(differences[0] / differences[1], 2.0, rtol=0.05)


def test_associative_is_exact_for_constant_rotation_rate():
    r"""With a constant rate the product $\mathrm{Exp}(\omega\delta t)^N = \mathrm{Exp}(N\omega\delta t)$
    and the tangent recursion $\theta^+ = \theta + J_r^{-1}(\theta)\omega\delta t$ (which keeps
    $\theta \parallel \omega$) agree in $\theta$ exactly (13 samples: padded at two levels)."""
    for samples in (13,):
        gyro = np.tile([[0.3, -0.2, 0.5]], (samples, 1)) + BIAS[3:]
        accel = np.tile([[0.0, 0.0, 9.81]], (samples, 1))
        a = sequential(PARAMS, BIAS, accel=accel, gyro=gyro, dt=0.01)
        b = associative(PARAMS, BIAS, accel=accel, gyro=gyro, dt=0.01)
        np.testing.assert_allclose(b.theta, a.theta, atol=1e-14)
        np.testing.assert_allclose(b.theta, samples * 0.01 * np.array([0.3, -0.2, 0.5]), atol=1e-14)
        assert float(b.delta_t) == pytest.approx(0.01 * samples)


def scan_carries(batch, samples):
    """The number of carried arrays of each `lax.scan` in `vmap(preintegrate)`'s program over
    `batch` intervals of `samples` (traced abstractly: nothing computed)."""
    shape = jax.ShapeDtypeStruct

    def scans(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "scan":
                yield eqn.params["num_carry"]
            for value in eqn.params.values():
                for sub in value if isinstance(value, tuple | list) else (value,):
                    if isinstance(sub, jax.extend.core.ClosedJaxpr):
                        yield from scans(sub.jaxpr)

    closed = jax.make_jaxpr(jax.vmap(imu.preintegrate, in_axes=(None, None)))(
        PARAMS, BIAS, accel=shape((batch, samples, 3), np.float64),
        gyro=shape((batch, samples, 3), np.float64), dt=shape((batch, samples), np.float64),
    )  # fmt: skip
    return list(scans(closed.jaxpr))


def test_batched_scan_dispatch():
    """Under `vmap`, batches of fewer than $2^{23}$ samples run the 3×3-block scan (10 carried
    arrays; it compiles in a third of the time), larger ones the entrywise scan (99 scalars)."""
    assert scan_carries(3, 60) == [10]
    assert scan_carries(1000, 200) == [10]
    assert scan_carries(32768, 255) == [10]
    assert scan_carries(32768, 256) == [99]


@pytest.mark.parametrize("with_arm", [False, True])
def test_vmap_over_intervals_equals_loop(with_arm, monkeypatch):
    """`vmap`, by the batched 3×3-block scan and by the entrywise scan, equals one interval at
    a time (the 3×3-block scan)."""
    params = PARAMS_ARM if with_arm else PARAMS
    streams = [stream(10 + k) for k in range(3)]
    gyro, accel, dt = (np.stack(x) for x in zip(*streams))
    samples = dict(accel=accel, gyro=gyro, dt=dt)
    blocks = over_intervals(params, BIAS, **samples)
    entrywise = entrywise_over_intervals(monkeypatch, params, BIAS, **samples)
    for k, (g, a, d) in enumerate(streams):
        one = sequential(params, BIAS, accel=a, gyro=g, dt=d)
        for field in ("theta", "delta_p", "delta_v", "covariance", "jacobian_bias"):
            expected = getattr(one, field)  # entries that cancel to 1e-6 of the largest: atol
            scale = 1e-12 * np.max(np.abs(expected))
            for batched in (blocks, entrywise):
                np.testing.assert_allclose(
                    getattr(batched, field)[k], expected, rtol=1e-12, atol=scale
                )


@pytest.mark.parametrize("with_arm", [False, True])
def test_float32_under_vmap(with_arm):
    """float32 samples give float32 results (the float64 parameters and sensor pose are cast)
    within float32 rounding of the float64 ones (measured: 3e-7 relative)."""
    params = PARAMS_ARM if with_arm else PARAMS
    gyro, accel, dt = (np.stack(x) for x in zip(*[stream(20 + k) for k in range(2)]))
    gyro32, accel32, dt32, bias32 = (jnp.asarray(x, jnp.float32) for x in (gyro, accel, dt, BIAS))
    single = over_intervals(params, bias32, accel=accel32, gyro=gyro32, dt=dt32)
    double = over_intervals(params, BIAS, accel=accel, gyro=gyro, dt=dt)
    assert bool(single.valid.all())
    for field in ("theta", "delta_p", "delta_v", "covariance", "jacobian_bias"):
        assert getattr(single, field).dtype == jnp.float32
        assert relative(getattr(single, field), getattr(double, field)) < 1e-5


def test_differentiable_batched_and_not():
    """Reverse and forward mode through `preintegrate`, alone and under `vmap` (whose batched scan
    is `custom_vmap`'d; its derivatives are the 3×3-block scan's), agree, and equal central
    differences."""
    gyro, accel, dt = (np.stack(x) for x in zip(*[stream(30 + k, samples=20) for k in range(2)]))
    batched = jax.vmap(imu.preintegrate, in_axes=(None, None))  # the keywords: axis 0

    def one(bias):
        pim = imu.preintegrate(PARAMS_ARM, bias, accel=accel[1], gyro=gyro[1], dt=dt[1])
        return pim.delta_p.sum()

    def both(bias):
        return batched(PARAMS_ARM, bias, accel=accel, gyro=gyro, dt=dt).delta_p[1].sum()

    # `one` and its gradient jitted (one program each, where op-by-op evaluation compiles a
    # program per operation and per shift); `both`'s reverse mode eagerly and jitted
    expected = jax.jit(jax.grad(one))(jnp.asarray(BIAS))
    h = 1e-6
    one_jitted = jax.jit(one)
    differences = [
        (one_jitted(jnp.asarray(BIAS) + h * e) - one_jitted(jnp.asarray(BIAS) - h * e)) / (2 * h)
        for e in np.eye(6)
    ]
    np.testing.assert_allclose(expected, differences, rtol=1e-6, atol=1e-9)
    for derivative in (jax.grad(both), jax.jit(jax.jacfwd(both)), jax.jit(jax.grad(both))):
        np.testing.assert_allclose(derivative(jnp.asarray(BIAS)), expected, rtol=1e-12)


def test_bad_input():
    gyro, accel, dt = stream(5, samples=8)
    with pytest.raises(imu.ImuError, match="mismatched"):
        imu.preintegrate(PARAMS, BIAS, accel=accel[:-1], gyro=gyro, dt=dt)
    with pytest.raises(imu.ImuError, match=r"dt must be a scalar or have shape \(8,\)"):
        imu.preintegrate(PARAMS, BIAS, accel=accel, gyro=gyro, dt=dt[:-1])
    with pytest.raises(imu.ImuError, match=r"bias must be"):
        imu.preintegrate(PARAMS, BIAS[:3], accel=accel, gyro=gyro, dt=dt)
    with pytest.raises(imu.ImuError, match=r"\(samples, 3\)"):
        imu.preintegrate(PARAMS, BIAS, accel=accel[:, :2], gyro=gyro[:, :2], dt=dt)
    with pytest.raises(imu.ImuError, match=r"params.n_gravity must be \(3,\)"):
        imu.preintegrate(
            PARAMS._replace(n_gravity=jnp.zeros(2)), BIAS, accel=accel, gyro=gyro, dt=dt
        )
    bad_gyro = gyro.copy()
    bad_gyro[3, 1] = np.nan
    with pytest.raises(imu.ImuError, match="sample 3: non-finite"):
        imu.preintegrate(PARAMS, BIAS, accel=accel, gyro=bad_gyro, dt=dt)
    bad_dt = dt.copy()
    bad_dt[5] = 0.0
    with pytest.raises(imu.ImuError, match="sample 5: dt <= 0"):
        imu.preintegrate_associative(PARAMS, BIAS, accel=accel, gyro=gyro, dt=bad_dt)
    # Under vmap/jit: a status, and NaN rather than a number.
    batched = over_intervals(
        PARAMS, BIAS, accel=np.stack([accel] * 3), gyro=np.stack([gyro, bad_gyro, gyro]),
        dt=np.stack([dt, dt, bad_dt]),
    )  # fmt: skip
    np.testing.assert_array_equal(batched.valid, [True, False, False])
    assert np.all(np.isfinite(batched.covariance[0]))
    assert np.all(np.isnan(batched.theta[1:])) and np.all(np.isnan(batched.covariance[1:]))


# ---- factor Jacobians by finite differences ----------------------------------------------------

# regime -> (gyro rate scale, rotation error r_θ imposed on pose_j, velocities, rotations of poses)
REGIMES = {
    "random": (1.0, None, "random", "random"),
    "zero_rate": (0.0, None, "random", "random"),
    "identity": (1.0, 0.0, "random", "random"),
    "near_identity_1e-9": (1.0, 1e-9, "random", "random"),
    "small_1e-4": (1.0, 1e-4, "random", "random"),
    "near_pi_1e-4": (1.0, np.pi - 1e-4, "random", "random"),
    "near_pi_1e-6": (1.0, np.pi - 1e-6, "random", "random"),
    "large_interval_rotation": (8.0, None, "random", "random"),
    "pure_translation": (0.0, None, "random", "identity"),
    "at_rest": (0.0, 0.0, "zero", "identity"),
}


def factor_state(regime, seed=6):
    r"""`(args, pim)` of one combined IMU factor in a regime, `args` =
    $(T_i, v_i, T_j, v_j, b_i, b_j)$ (the IMU factor's are the first five): the interval's rate
    scale (0: the corrected rate is exactly zero), $\|r_\theta\|$ imposed through `pose_j`'s
    rotation (`None`: random), zero or random velocities, identity or random pose rotations.
    `at_rest`: a vehicle standing still, its prediction equal to `pose_j` and $b_j = b_i$ (zero
    residual)."""
    rate_scale, angle, velocities, rotations = REGIMES[regime]
    rng = np.random.default_rng(seed)
    gyro, accel, dt = stream(7, rate_scale=rate_scale)
    gyro = gyro + BIAS[3:] * (rate_scale == 0.0)
    if regime == "at_rest":
        accel = np.tile(BIAS[:3] + [0.0, 0.0, 9.81], (SAMPLES, 1))
    pim = sequential(PARAMS, BIAS, accel=accel, gyro=gyro, dt=dt)
    bias_i = BIAS if regime == "at_rest" else BIAS + 0.01 * rng.normal(size=6)
    tangents = rng.normal(size=(2, 6))
    if rotations == "identity":
        tangents[:, 3:] = 0.0
    pose_i, pose_j = SE3.exp(jnp.asarray(tangents[0])), SE3.exp(jnp.asarray(tangents[1]))
    v_i, v_j = (np.zeros(3), np.zeros(3)) if velocities == "zero" else rng.normal(size=(2, 3))
    if regime == "at_rest":
        pose_j, v_j = imu.predict(pim, pose_i, v_i, bias_i, PARAMS)
    elif angle is not None:  # R_j = R_i R_c Exp(r_θ)^{-1}: the rotation error is r_θ
        axis = rng.normal(size=3)
        error = SO3.exp(jnp.asarray(angle * axis / np.linalg.norm(axis)))
        rotation_c = SO3.exp(pim.bias_corrected(bias_i)[:3])
        rotation_j = pose_i.rotation() @ rotation_c @ error.inverse()
        pose_j = SE3.from_rotation_and_translation(rotation_j, pose_j.translation())
    bias_j = bias_i if regime == "at_rest" else bias_i + 0.01 * rng.normal(size=6)
    return (pose_i, v_i, pose_j, v_j, bias_i, bias_j), pim


@functools.partial(jax.jit, static_argnums=0)
def perturbed(residual, args, pim, steps):
    """`residual(args ⊕ step, pim, PARAMS)` for each row of `steps`, right-local tangents (one
    compilation per residual function, shared by every regime)."""

    def f(delta):
        return residual(*rplus(args, unflatten_tangents(args, delta)), pim, PARAMS)

    return jax.vmap(f)(steps)


def numeric_jacobian(residual, args, pim, eps):
    """Central differences of `residual` in the right-local tangents of `args`."""
    steps = eps * np.eye(tangent_dim(args))
    differences = perturbed(residual, args, pim, np.concatenate([steps, -steps]))
    return np.asarray((differences[: len(steps)] - differences[len(steps) :]).T / (2 * eps))


def stacked(blocks):
    rows = np.shape(blocks[0])[0]
    return np.concatenate([np.asarray(b).reshape(rows, -1) for b in blocks], 1)


COMBINED_RESIDUAL = {
    mode: functools.partial(imu.combined_imu_residual, error_mode=mode) for mode in MODES
}


@pytest.mark.parametrize("error_mode", MODES)
@pytest.mark.parametrize("regime", list(REGIMES))
def test_factor_jacobians_by_finite_differences(regime, error_mode):
    r"""The closed-form blocks of `imu_jacobians` and of `combined_imu_jacobians`, and the
    autodiff path (`value_and_jacobian` of `imu_residual`; the logmap residual through `SE23`),
    against central differences of `combined_imu_residual` (float64; the IMU factor's are its
    first 9 rows and 24 columns), and against each other, in both error modes; near $\pi$ the
    step is below the distance to $\pi$ (where `Log` wraps)."""
    args, pim = factor_state(regime)
    value, blocks = closed_form(*args[:5], pim, PARAMS, error_mode=error_mode)
    auto_value, auto_blocks = residual_and_jacobians[error_mode](*args[:5], pim, PARAMS)
    combined_value, combined_blocks = combined_closed_form(
        *args, pim, PARAMS, error_mode=error_mode
    )
    rotation_error = float(np.linalg.norm(value[:3]))
    angle = REGIMES[regime][1]
    if angle is not None:
        assert rotation_error == pytest.approx(angle, abs=1e-12)
    if regime == "at_rest":
        np.testing.assert_allclose(combined_value, 0.0, atol=1e-12)
    eps = 1e-7 if regime.startswith("near_pi") else 1e-6
    numeric = numeric_jacobian(COMBINED_RESIDUAL[error_mode], args, pim, eps)
    analytic = stacked(blocks)
    scale = max(1.0, np.max(np.abs(numeric)))
    np.testing.assert_allclose(analytic, numeric[:9, :24], atol=2e-7 * scale)
    np.testing.assert_allclose(stacked(combined_blocks), numeric, atol=2e-7 * scale)
    np.testing.assert_allclose(value, auto_value, rtol=0, atol=1e-14)
    np.testing.assert_allclose(analytic, stacked(auto_blocks), rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(combined_value, np.concatenate([value, args[5] - args[4]]))


def test_factor_jacobians_batched_and_reverse():
    r"""`vmap(combined_imu_jacobians)` over instances equals the unbatched blocks (its first 9
    rows `imu_jacobians`'), to rounding (a few ulps: XLA fuses the batched products
    differently), and the rows of all six blocks equal reverse-mode derivatives (`jax.vjp`) of
    `combined_imu_residual` in local coordinates."""
    states = [factor_state(regime, seed=20 + k) for k, regime in enumerate(REGIMES)]
    args = jax.tree.map(lambda *x: jnp.stack(x), *[a for a, _ in states])
    pims = jax.tree.map(lambda *x: jnp.stack(x), *[p for _, p in states])
    batched = jax.vmap(imu.combined_imu_jacobians, in_axes=(0, 0, 0, 0, 0, 0, 0, None))
    values, blocks = jax.jit(batched)(*args, pims, PARAMS)
    for k, (one_args, one_pim) in enumerate(states):
        value, one = closed_form(*one_args[:5], one_pim, PARAMS)
        np.testing.assert_allclose(values[k, :9], value, rtol=0, atol=1e-14)
        for b, b_one in zip(blocks, one):
            np.testing.assert_allclose(b[k, :9], b_one, rtol=0, atol=1e-14)
        combined_value, combined_one = combined_closed_form(*one_args, one_pim, PARAMS)
        np.testing.assert_allclose(values[k], combined_value, rtol=0, atol=1e-14)
        np.testing.assert_allclose(
            stacked([b[k] for b in blocks]), stacked(combined_one), atol=1e-14
        )
    one_args, one_pim = states[0]

    def f(delta):
        return imu.combined_imu_residual(
            *rplus(one_args, unflatten_tangents(one_args, delta)), one_pim, PARAMS
        )

    @jax.jit  # one program (op by op, the residual's operations compile one each)
    def reverse_rows(at):
        _, pullback = jax.vjp(f, at)
        return jax.vmap(pullback)(jnp.eye(15))[0]

    rows = reverse_rows(jnp.zeros(tangent_dim(one_args)))
    _, one = combined_closed_form(*one_args, one_pim, PARAMS)
    np.testing.assert_allclose(stacked(one), rows, rtol=0, atol=1e-12)
    rotating = PARAMS._replace(omega_coriolis=jnp.array([0.0, 0.0, 7.29e-5]))
    with pytest.raises(imu.ImuError, match="omega_coriolis"):
        imu.imu_jacobians(*one_args[:5], one_pim, rotating)
    with pytest.raises(imu.ImuError, match="omega_coriolis"):
        imu.combined_imu_jacobians(*one_args, one_pim, rotating)


FUSED_ANGLES = (0.0, 1e-9, 1e-4, 0.3, 0.5 - 1e-9, 0.5 + 1e-9, 1.0, 2.5, np.pi - 1e-4, np.pi - 1e-6)


def fused_local(omega, delta):
    r"""The fused SO3 kernels at `omega` moved by `delta` = $(\delta_e, \delta_l)$, flattened: the
    local coordinates $\mathrm{Log}(q(\omega)^{-1} q(\omega + \delta_e))$ of
    `exp_and_right_jacobian`'s quaternion and its $J_r$, then `log_and_right_jacobian_inverse`
    at $\mathrm{Exp}(\omega) \oplus \delta_l$ (its $\omega$ and $J_r^{-1}$)."""
    from lieax.groups import _so3 as so3

    q0 = so3.exp(omega)
    q, jr = so3.exp_and_right_jacobian(omega + delta[:3])
    local = so3.log(so3.compose(so3.inverse(q0), q))
    log, jr_inv = so3.log_and_right_jacobian_inverse(so3.compose(q0, so3.exp(delta[3:])))
    return jnp.concatenate([local, jr.ravel(), log, jr_inv.ravel()])


@jax.jit
def fused_checks(omegas, eps):
    """For each row of `omegas` (one compilation): the fused kernels' values and the reference
    kernels' (`exp`, `right_jacobian`, `log` and `right_jacobian_inverse` of `Exp(ω)` and of
    `-Exp(ω)`, w < 0), and the forward-mode, reverse-mode and central-difference Jacobians of
    `fused_local` in `delta` at zero."""
    zero, steps = jnp.zeros(6), eps * jnp.eye(6)

    def one(omega):
        rotation, jr = SO3.exp_and_right_jacobian(omega)
        flipped = SO3(-rotation.wxyz)
        fused = (rotation.wxyz, jr, *rotation.log_and_right_jacobian_inverse())
        fused = (*fused, *flipped.log_and_right_jacobian_inverse())
        reference = (SO3.exp(omega).wxyz, SO3.right_jacobian(omega))
        for r in (rotation, flipped):
            reference = (*reference, r.log(), SO3.right_jacobian_inverse(r.log()))
        differences = jax.vmap(lambda d: fused_local(omega, d))(jnp.concatenate([steps, -steps]))
        numeric = (differences[:6] - differences[6:]).T / (2 * eps)
        forward = jax.jacfwd(fused_local, argnums=1)(omega, zero)
        reverse = jax.jacrev(fused_local, argnums=1)(omega, zero)
        return fused, reference, (forward, reverse, numeric)

    return jax.vmap(one)(omegas)


def test_fused_so3_kernels_values_and_derivatives():
    r"""`SO3.exp_and_right_jacobian` and `SO3.log_and_right_jacobian_inverse` equal `exp`,
    `right_jacobian`, `log` and `right_jacobian_inverse` (series elsewhere) at the identity,
    1e-9 and 1e-4 from it, on both sides of their series switch ($\theta = 0.5$), at random
    angles and near $\pi$ (for $q$ and $-q$), vmapped and unbatched; their forward and reverse
    derivatives equal central differences in local coordinates (float64)."""
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(len(FUSED_ANGLES), 3))
    omegas = np.array(FUSED_ANGLES)[:, None] * axes / np.linalg.norm(axes, axis=1)[:, None]
    fused, reference, (forward, reverse, numeric) = fused_checks(jnp.asarray(omegas), 1e-7)
    for name, a, b, atol in zip(
        ("q", "J_r", "log", "J_r^-1", "log(-q)", "J_r^-1(-q)"), fused, reference,
        (1e-15, 3e-16, 1e-15, 5e-16, 1e-15, 5e-16),
    ):  # fmt: skip
        np.testing.assert_allclose(a, b, rtol=0, atol=atol, err_msg=name)
    single_rotation, single_jr = SO3.exp_and_right_jacobian(jnp.asarray(omegas[3]))
    np.testing.assert_allclose(single_rotation.wxyz, fused[0][3], rtol=0, atol=1e-16)
    np.testing.assert_allclose(single_jr, fused[1][3], rtol=0, atol=1e-16)
    np.testing.assert_allclose(fused[1][0], np.eye(3), rtol=0, atol=0)
    assert np.all(np.isfinite(forward)) and np.all(np.isfinite(reverse))
    np.testing.assert_allclose(forward, numeric, rtol=0, atol=2e-7)
    np.testing.assert_allclose(reverse, forward, rtol=0, atol=1e-13)
    # at zero (the Taylor branch): d J_r = -½[dω]×, d J_r^{-1} = ½[dω]×
    x = skew_of([1.0, 0.0, 0.0]).ravel()
    np.testing.assert_allclose(forward[0, 3:12, 0], -0.5 * x, rtol=0, atol=1e-15)
    np.testing.assert_allclose(forward[0, 15:24, 3], 0.5 * x, rtol=0, atol=1e-15)


def skew_of(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def test_bias_random_walk_blocks():
    """The bias random-walk factor's closed-form blocks are $-I$ and $I$ of $b_j - b_i$, as its
    autodiff Jacobian."""
    from lieax.factorgraph import Var
    from lieax.factorgraph._factors import linearize_one

    biases = Var(jnp.zeros((2, 6)))
    factor = imu.bias_random_walk_factor(biases[[0]], biases[[1]], np.array([1.0]), 1e-3, 1e-4)
    b_i, b_j = np.random.default_rng(3).normal(size=(2, 6))
    value, blocks = linearize_one(factor, (b_i, b_j), None)
    auto_value, auto = value_and_jacobian(factor.residual, (0, 1))(b_i, b_j)
    np.testing.assert_allclose(value, b_j - b_i, rtol=1e-15)
    np.testing.assert_allclose(value, auto_value, rtol=1e-15)
    np.testing.assert_array_equal(blocks[0], -np.eye(6))
    np.testing.assert_array_equal(blocks[1], np.eye(6))
    np.testing.assert_array_equal(auto[0], blocks[0])
    np.testing.assert_array_equal(auto[1], blocks[1])


def test_factors_in_a_graph():
    """Three keyframes at rest, their poses known (priors): the solve recovers zero velocities
    and the biases the samples carry (at rest, with the attitude known, all six are observable),
    to the accuracy of the first-order bias correction from the zero bias they were integrated
    at (measured 3e-6; GTSAM's model alike). The first interval is one `combined_imu_factor`,
    the second an `imu_factor` and a `bias_random_walk_factor` (one solve for both kinds)."""
    from lieax.factorgraph import Factor, FactorGraph, Var

    true_bias = np.array([0.03, -0.02, 0.05, 0.002, -0.001, 0.003])
    gyro = np.tile(true_bias[3:], (100, 1))
    accel = np.tile(true_bias[:3] + [0.0, 0.0, 9.81], (100, 1))
    walk = imu.BiasRandomWalk.isotropic(1e-3, 1e-4)
    first, covariance = combined(PARAMS, walk, np.zeros(6), accel=accel, gyro=gyro, dt=0.01)
    second = sequential(PARAMS, np.zeros(6), accel=accel, gyro=gyro, dt=0.01)
    first, second = (jax.tree.map(lambda x: x[None], pim) for pim in (first, second))
    start = SE3.exp(jnp.asarray(0.01 * np.random.default_rng(8).normal(size=(3, 6))))
    poses, velocities = Var(start, name="poses"), Var(jnp.full((3, 3), 0.1), name="velocities")
    biases = Var(jnp.zeros((3, 6)), name="biases")
    i, j, k = np.array([0]), np.array([1]), np.array([2])
    graph = FactorGraph([
        imu.combined_imu_factor(
            first, covariance[None], PARAMS,
            poses[i], velocities[i], poses[j], velocities[j], biases[i], biases[j],
        ),
        imu.imu_factor(second, PARAMS, poses[j], velocities[j], poses[k], velocities[k], biases[j]),
        imu.bias_random_walk_factor(biases[j], biases[k], np.asarray(second.delta_t), 1e-3, 1e-4),
        Factor(lambda x: x.log(), (poses[np.arange(3)],), sqrt_information=1e4 * np.eye(6)),
    ])  # fmt: skip
    result = graph.solve()
    assert result.converged
    _, solved_velocities, solved_biases = result.values
    np.testing.assert_allclose(solved_velocities, 0.0, atol=2e-5)
    np.testing.assert_allclose(solved_biases, np.tile(true_bias, (3, 1)), atol=2e-5)


def test_imu_factors_reject_invalid_input():
    """Invalid intervals, a combined covariance of the wrong shape or not positive definite (no
    bias random walk), non-positive durations: `ImuError`s that say which."""
    from lieax.factorgraph import Var

    gyro, accel, dt = stream(9, samples=4)
    bad = np.array(dt)
    bad[0] = -1.0
    pim = over_intervals(
        PARAMS,
        BIAS,
        accel=np.stack([accel, accel]),
        gyro=np.stack([gyro, gyro]),
        dt=np.stack([dt, bad]),
    )
    poses, vectors = Var(SE3.identity((2,))), Var(jnp.zeros((2, 3)))
    biases = Var(jnp.zeros((2, 6)))
    index = np.array([0, 0])
    with pytest.raises(imu.ImuError, match="pim 1 is invalid"):
        imu.imu_factor(
            pim, PARAMS, poses[index], vectors[index], poses[index], vectors[index], biases[index]
        )
    singular = jax.tree.map(lambda x: x[index], pim)._replace(covariance=np.zeros((2, 9, 9)))
    with pytest.raises(imu.ImuError, match="9x9 covariance is not positive definite"):
        imu.imu_factor(singular, PARAMS, *(poses[index], vectors[index]) * 2, biases[index])
    with pytest.raises(imu.ImuError, match="delta_t"):
        imu.bias_random_walk_factor(biases[index], biases[index], np.array([1.0, 0.0]), 1e-3, 1e-4)
    refs = (poses[index], vectors[index]) * 2 + (biases[index],) * 2
    covariance = np.zeros((2, 15, 15))
    covariance[:, :9, :9] = pim.covariance[0]
    with pytest.raises(imu.ImuError, match="pim 1 is invalid"):
        imu.combined_imu_factor(pim, covariance, PARAMS, *refs)
    valid = jax.tree.map(lambda x: x[index], pim)
    with pytest.raises(imu.ImuError, match=r"covariance must be \(m, 15, 15\) = \(2, 15, 15\)"):
        imu.combined_imu_factor(valid, covariance[:, :9, :9], PARAMS, *refs)
    with pytest.raises(imu.ImuError, match="15x15 covariance is not positive definite"):
        imu.combined_imu_factor(valid, covariance, PARAMS, *refs)
    # With a bias random walk it is accepted: closed-form blocks, autodiff in a rotating frame.
    covariance[:, 9:, 9:] = 1e-6 * np.eye(6)
    assert imu.combined_imu_factor(valid, covariance, PARAMS, *refs).jacobian_fn is not None
    rotating = PARAMS._replace(omega_coriolis=jnp.array([0.0, 0.0, 7.29e-5]))
    assert imu.combined_imu_factor(valid, covariance, rotating, *refs).jacobian_fn is None
