"""IMU streams as they come (`lieax.imu`): samples as keywords in GTSAM's order, intervals of
different lengths padded with a per-sample mask (`preintegrate(mask=)`) to bucketed lengths
(`preintegrate_intervals`), equal to the unpadded results and compiled once per bucket."""

import jax
import numpy as np
import pytest
from _imu_streams import ARM, BIAS, NOISE, entrywise_over_intervals, stream

import lieax.imu as imu
from lieax import SE3
from lieax.factorgraph import Var

PARAMS = imu.ImuParams.make_u(9.81, **NOISE, body_P_sensor=ARM)
WALK = imu.BiasRandomWalk.isotropic(1e-3, 1e-4)
FIELDS = ("theta", "delta_p", "delta_v", "delta_t", "covariance", "jacobian_bias")

sequential = jax.jit(imu.preintegrate)
associative = jax.jit(imu.preintegrate_associative)
combined = jax.jit(imu.preintegrate_combined)
over_intervals = jax.jit(jax.vmap(imu.preintegrate, in_axes=(None, None)))


def padded(samples, at, rows):
    """`samples` = `(gyro, accel, dt)` spread over `rows` rows, the rows `at` padding (NaN
    samples, `dt = 0`: never read), and the mask."""
    keep = np.ones(rows, bool)
    keep[list(at)] = False
    out = []
    for x, fill in zip(samples, (np.nan, np.nan, 0.0)):
        full = np.full((rows, *x.shape[1:]), fill)
        full[keep] = x
        out.append(full)
    return (*out, keep)


def assert_same(ours, expected, rtol=1e-12):
    for field in FIELDS:
        a, b = np.asarray(getattr(ours, field)), np.asarray(getattr(expected, field))
        scale = np.max(np.abs(b))  # entries that cancel to 1e-6 of the largest: atol
        np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale, err_msg=field)
    assert bool(ours.valid)


def test_masked_padding_equals_unpadded(monkeypatch):
    """Nine samples spread over twelve rows (padding first, inside and last, NaN in the padded
    rows): the sequential scan, the batched scans under `vmap` (3×3 blocks, entrywise), the
    combined 15×15
    covariance and the associative tree each equal their unpadded results to 1e-12 in the
    increments, $\\Delta t$, covariances and bias Jacobians; the derivative with respect to the
    bias through the masked scan (its JVP rule) equals the unpadded one."""
    gyro, accel, dt = stream(3, samples=9)
    g, a, d, keep = padded((gyro, accel, dt), (0, 5, 11), 12)
    plain = dict(accel=accel, gyro=gyro, dt=dt)
    masked = dict(accel=a, gyro=g, dt=d, mask=keep)
    expected = sequential(PARAMS, BIAS, **plain)
    assert_same(sequential(PARAMS, BIAS, **masked), expected)
    batch = {k: np.stack([v, v]) for k, v in masked.items()}
    assert_same(jax.tree.map(lambda x: x[1], over_intervals(PARAMS, BIAS, **batch)), expected)
    entrywise = entrywise_over_intervals(monkeypatch, PARAMS, BIAS, **batch)
    assert_same(jax.tree.map(lambda x: x[1], entrywise), expected)  # to its own rounding
    expected_pim, expected_cov = combined(PARAMS, WALK, BIAS, **plain)
    pim, covariance = combined(PARAMS, WALK, BIAS, **masked)
    assert_same(pim, expected_pim)
    np.testing.assert_allclose(covariance, expected_cov, rtol=0, atol=1e-12 * expected_cov.max())
    assert_same(associative(PARAMS, BIAS, **masked), associative(PARAMS, BIAS, **plain))

    def delta_p(bias, samples):
        return imu.preintegrate(PARAMS, bias, **samples).delta_p

    jacobian = jax.jit(jax.jacfwd(delta_p))
    np.testing.assert_allclose(jacobian(BIAS, masked), jacobian(BIAS, plain), rtol=1e-12)


def test_intervals_compile_once_per_bucket():
    """`preintegrate_intervals` over streams of 9–12 samples per interval and 3 intervals
    (buckets 12 and 3): three calls with different counts compile one program (JAX's
    `backend_compile_duration` events: none after the first call), and every interval equals
    the masked scan of its own samples; the result feeds `imu_factor` (which refused padded
    intervals before masks: "pim 0 is invalid")."""
    compiles = []

    def record(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(event)

    jax.monitoring.register_event_duration_secs_listener(record)
    streams = [stream(20 + k, samples=n) for k, n in enumerate(range(9, 13))]
    calls = ([0, 1, 2], [3, 0, 0], [1, 3, 2])
    counts = []
    programs = imu._intervals._batched._cache_size()  # (other files' streams share the worker)
    for picks in calls:
        before = len(compiles)
        intervals = [streams[k] for k in picks]
        pims = imu.preintegrate_intervals(
            PARAMS,
            BIAS,
            accel=[s[1] for s in intervals],
            gyro=[s[0] for s in intervals],
            dt=[s[2] for s in intervals],
        )
        counts.append(len(compiles) - before)
        for k, (g, a, d) in enumerate(intervals):
            rows = len(d)
            g, a, d, keep = padded((g, a, d), range(rows, 12), 12)
            expected = sequential(PARAMS, BIAS, accel=a, gyro=g, dt=d, mask=keep)
            assert_same(jax.tree.map(lambda x, k=k: x[k], pims), expected, rtol=1e-12)
    assert counts[1:] == [0, 0], counts
    assert imu._intervals._batched._cache_size() - programs <= 1
    poses, vectors, biases = Var(SE3.identity((4,))), Var(np.zeros((4, 3))), Var(np.zeros((4, 6)))
    i, j = np.arange(3), np.arange(1, 4)
    factor = imu.imu_factor(pims, PARAMS, poses[i], vectors[i], poses[j], vectors[j], biases[i])
    assert factor.sqrt_information.shape == (3, 9, 9)


def test_bucket_sizes():
    """Two buckets per doubling, at most a third padded; small sizes are their own."""
    sizes = np.arange(1, 3000)
    buckets = np.array([imu.bucket_size(int(n)) for n in sizes])
    assert np.all(buckets >= sizes) and np.all(np.diff(buckets) >= 0)
    assert np.all((buckets - sizes) / buckets <= 1 / 3 + 1e-12)
    np.testing.assert_array_equal(buckets[:4], [1, 2, 3, 4])
    assert {imu.bucket_size(n) for n in range(7, 14)} == {8, 12, 16}
    assert len(np.unique(buckets[(sizes > 1024) & (sizes <= 2048)])) == 2


def test_samples_are_keywords_and_bad_streams_say_where():
    """A positional call (the old `preintegrate(gyro, accel, dt, bias, params)`) is a
    `TypeError` naming the keywords; a bad mask, and a bad sample of a stream, an `ImuError`
    naming the interval and the sample."""
    gyro, accel, dt = stream(5, samples=8)
    for call in (imu.preintegrate, imu.preintegrate_associative):
        with pytest.raises(TypeError, match="accel=.*gyro=.*dt="):
            call(gyro, accel, dt, BIAS, PARAMS)
    with pytest.raises(TypeError, match="keyword-only, accel="):
        imu.preintegrate_combined(gyro, accel, dt, BIAS, PARAMS, WALK)
    with pytest.raises(TypeError, match="keyword-only"):
        imu.preintegrate(PARAMS, BIAS, accel, gyro=gyro, dt=dt)
    samples = dict(accel=accel, gyro=gyro, dt=dt)
    with pytest.raises(imu.ImuError, match=r"mask must be boolean of shape \(8,\)"):
        imu.preintegrate(PARAMS, BIAS, **samples, mask=np.ones(8))
    with pytest.raises(imu.ImuError, match="mask is all False"):
        imu.preintegrate(PARAMS, BIAS, **samples, mask=np.zeros(8, bool))
    bad = dt.copy()
    bad[3] = 0.0
    with pytest.raises(imu.ImuError, match="sample 3: dt <= 0"):
        imu.preintegrate(PARAMS, BIAS, accel=accel, gyro=gyro, dt=bad)
    keep = np.ones(8, bool)
    keep[3] = False  # a padded sample's dt is not read
    assert bool(imu.preintegrate(PARAMS, BIAS, accel=accel, gyro=gyro, dt=bad, mask=keep).valid)
    with pytest.raises(imu.ImuError, match="interval 1, sample 3: .*dt <= 0"):
        imu.preintegrate_intervals(PARAMS, accel=[accel, accel], gyro=[gyro, gyro], dt=[dt, bad])
    with pytest.raises(imu.ImuError, match=r"interval 0: accel \(8, 3\) and gyro \(7, 3\)"):
        imu.preintegrate_intervals(PARAMS, accel=[accel], gyro=[gyro[:7]], dt=0.01)
    with pytest.raises(imu.ImuError, match=r"bias must be \(6,\) or \(m, 6\)"):
        imu.preintegrate_intervals(PARAMS, np.zeros(3), accel=[accel], gyro=[gyro], dt=0.01)
