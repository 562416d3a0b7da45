"""lieax.sharding on 8 virtual CPU devices: sharded runs equal unsharded ones, are split over
every device, compile once, and communicate only where they must.

JAX fixes its device count when it starts, and this pytest process has started it with one device;
so every sharded check runs in one subprocess that sets
`XLA_FLAGS=--xla_force_host_platform_device_count=8` before importing JAX (this file, run as a
script), and prints its measurements as JSON for the tests here to assert on. Sizes are tiny but
for the residual-axis problem (80,000 point pairs), whose run time is still small next to the
compilations.
"""

import json
import os
import re
import subprocess
import sys

import pytest

DEVICES = 8
TOLERANCE = 1e-10  # float64
COLLECTIVES = ("all-reduce", "all-gather", "all-to-all", "collective-permute", "reduce-scatter")


# ---- the subprocess ------------------------------------------------------------------------------


def _collectives(compiled_text):
    """`{kind: [elements moved by each instruction]}` of the collectives in a compiled program."""
    pattern = re.compile(r"= (\(.*?\)|\S+) (" + "|".join(COLLECTIVES) + r")(?:-start)?\(")
    found = {}
    for shapes, kind in pattern.findall(compiled_text):
        elements = 0
        for dims in re.findall(r"[a-z]+\d*\[([\d,]*)\]", shapes):
            size = 1
            for d in filter(None, dims.split(",")):
                size *= int(d)
            elements += size
        found.setdefault(kind, []).append(elements)
    return found


def _layout(array, mesh):
    """How an output is laid out: spec, the devices holding shards, and the shards' rows."""
    return {
        "spec": [None if a is None else str(a) for a in array.sharding.spec],
        "same_mesh": array.sharding.mesh == mesh,
        "devices": sorted(shard.device.id for shard in array.addressable_shards),
        "rows": sorted({shard.data.shape[0] for shard in array.addressable_shards}),
        "shape": list(array.shape),
    }


def _sharded_checks():  # runs in the subprocess, with 8 devices
    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)

    import lieax
    import lieax.lstsq
    from lieax import icp, sharding

    compilations = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **kw: (
            compilations.append(event)
            if event == "/jax/core/compile/backend_compile_duration"
            else None
        )
    )

    def compiles_of(call):
        before = len(compilations)
        out = jax.block_until_ready(call())
        return out, len(compilations) - before

    def max_diff(a, b):
        return max(
            float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64))))
            for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
        )

    report = {"devices": jax.device_count()}
    mesh = sharding.batch_mesh()

    # -- a batch of least-squares problems (13: padded to 16), x0 shared (in_axes None) --------
    def residual(pose, data):
        source, target = data
        return jax.vmap(lambda p, q: pose @ p - q)(source, target)

    def solve(data, x0):
        return lieax.lstsq.least_squares(residual, x0, data, throw=False)

    problems, points = 13, 40
    keys = jax.random.split(jax.random.key(0), 3)
    source = jax.random.normal(keys[0], (problems, points, 3))
    truth = lieax.SE3.exp(0.6 * jax.random.normal(keys[1], (problems, 6)))
    target = jax.vmap(lambda pose, cloud: pose @ cloud)(truth, source)
    target = target + 0.01 * jax.random.normal(keys[2], target.shape)
    x0 = lieax.SE3.identity()
    reference = jax.jit(jax.vmap(solve, in_axes=(0, None)))((source, target), x0)

    data, valid = sharding.shard_batch((source, target), mesh, pad=True)
    try:
        sharding.shard_batch((source, target), mesh)
        uneven_error = None
    except ValueError as error:
        uneven_error = str(error)
    solve_sharded = sharding.batch_map(solve, mesh, in_axes=(0, None))
    solutions, first = compiles_of(lambda: solve_sharded(data, x0))
    keys = jax.random.split(jax.random.key(1), 2)
    other = sharding.shard_batch(
        (jax.random.normal(keys[0], data[0].shape), jax.random.normal(keys[1], data[1].shape)),
        mesh,
    )
    _, second = compiles_of(lambda: solve_sharded(other, x0))
    head = jax.tree_util.tree_map(lambda a: a[:problems], solutions)
    report["lstsq_batch"] = {
        "value_diff": max_diff(head.value, reference.value),
        "cost_diff": max_diff(head.cost, reference.cost),
        "same_iterations": bool(np.array_equal(head.iterations, reference.iterations)),
        "same_status": bool(np.array_equal(head.status, reference.status)),
        "converged": int(np.sum(np.asarray(reference.status) == 0)),
        "valid": np.asarray(valid).tolist(),
        "uneven_error": uneven_error,
        "layout": _layout(solutions.value.parameters(), mesh),
        "input_layout": _layout(data[0], mesh),
        "compilations": [first, second],
        "collectives": _collectives(solve_sharded.lower(data, x0).compile().as_text()),
    }

    # -- batched ICP over padded clouds of different sizes ---------------------------------------
    pairs = [
        icp.synthetic_pair(120 + 15 * i, rotation_deg=6.0, translation=0.05, noise=0.002, seed=i)
        for i in range(DEVICES)
    ]
    clouds = [icp.pad_clouds([pair[j] for pair in pairs]) for j in range(3)]
    (sources, source_mask), (targets, target_mask), (normals, _) = clouds

    def register(s, sm, t, tm, n):
        return icp.point_to_plane(
            s,
            t,
            target_normals=n,
            source_mask=sm,
            target_mask=tm,
            max_correspondence_distance=0.1,
            throw=False,
        )

    batch = (sources, source_mask, targets, target_mask, normals)
    reference = jax.jit(jax.vmap(register))(*batch)
    register_sharded = sharding.batch_map(register, mesh)
    sharded_batch = sharding.shard_batch(batch, mesh)
    results, first = compiles_of(lambda: register_sharded(*sharded_batch))
    truths = lieax.SE3(jnp.stack([pair[3].parameters() for pair in pairs]))
    report["icp_batch"] = {
        "transform_diff": max_diff(results.transform, reference.transform),
        "fitness_diff": max_diff(results.fitness, reference.fitness),
        "rmse_diff": max_diff(results.inlier_rmse, reference.inlier_rmse),
        "same_correspondences": bool(
            np.array_equal(results.correspondences, reference.correspondences)
        ),
        "same_iterations": bool(np.array_equal(results.iterations, reference.iterations)),
        "same_status": bool(np.array_equal(results.status, reference.status)),
        "error_to_truth": max_diff(
            lieax.rminus(results.transform, truths), jnp.zeros((DEVICES, 6))
        ),
        "layout": _layout(results.transform.parameters(), mesh),
        "correspondence_layout": _layout(results.correspondences, mesh),
        "compilations": [first],
        "collectives": _collectives(register_sharded.lower(*sharded_batch).compile().as_text()),
    }

    # -- one problem with many residuals, split along the residual axis --------------------------
    pairs_count = 80_000
    keys = jax.random.split(jax.random.key(2), 4)
    source = jax.random.normal(keys[0], (pairs_count, 3))
    T_target_source = lieax.SE3.exp(jnp.array([0.3, -0.2, 0.1, 0.4, -0.3, 0.2]))
    target = T_target_source @ source + 0.01 * jax.random.normal(keys[1], (pairs_count, 3))
    target = target.at[:800].add(jax.random.normal(keys[2], (800, 3)))  # 1% outliers
    loss = lieax.lstsq.Huber(0.03)
    reference = lieax.lstsq.least_squares(
        residual, lieax.SE3.identity(), (source, target), loss=loss
    )

    residual_mesh = sharding.batch_mesh(axis_name="residual")
    sharded_residual = sharding.shard_residuals(residual, residual_mesh)
    pairs_sharded = sharding.shard_batch((source, target), residual_mesh)

    def solve_residual_sharded(data):
        return lieax.lstsq.least_squares(sharded_residual, lieax.SE3.identity(), data, loss=loss)

    solve_jitted = jax.jit(solve_residual_sharded)
    solution, first = compiles_of(lambda: solve_jitted(pairs_sharded))
    residuals = sharded_residual(reference.value, pairs_sharded)
    report["residual_axis"] = {
        "value_diff": max_diff(solution.value, reference.value),
        "relative_cost_diff": abs(float(solution.cost) / float(reference.cost) - 1.0),
        "same_iterations": int(solution.iterations) == int(reference.iterations),
        "iterations": int(reference.iterations),
        "status": int(solution.status),
        "residual_layout": _layout(residuals, residual_mesh),
        "compilations": [first],
        "collectives": _collectives(solve_jitted.lower(pairs_sharded).compile().as_text()),
        "tangent_dim": 6,
    }

    # -- the same with a prior on the pose: a residual leaf that is not split ------------------
    T_prior = lieax.SE3.exp(jnp.array([0.25, -0.2, 0.1, 0.4, -0.3, 0.25]))

    def with_prior(data_residual):
        return lambda pose, data: (data_residual(pose, data), 10.0 * lieax.rminus(pose, T_prior))

    losses = (loss, None)
    reference = lieax.lstsq.least_squares(
        with_prior(residual), lieax.SE3.identity(), (source, target), loss=losses
    )
    solve_jitted = jax.jit(
        lambda data: lieax.lstsq.least_squares(
            with_prior(sharded_residual), lieax.SE3.identity(), data, loss=losses
        )
    )
    solution = solve_jitted(pairs_sharded)
    report["residual_axis_with_prior"] = {
        "value_diff": max_diff(solution.value, reference.value),
        "relative_cost_diff": abs(float(solution.cost) / float(reference.cost) - 1.0),
        "same_iterations": int(solution.iterations) == int(reference.iterations),
        "status": int(solution.status),
        "collectives": _collectives(solve_jitted.lower(pairs_sharded).compile().as_text()),
        "tangent_dim": 6,
    }
    return report


def _environment(devices):
    """This process's environment, with `devices` virtual CPU devices and the `lieax` that this
    process imports first on the path (a checkout's, not an installed copy's)."""
    import lieax

    env = dict(os.environ)
    root = os.path.dirname(os.path.dirname(os.path.abspath(lieax.__file__)))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
    env["XLA_FLAGS"] = " ".join(
        [env.get("XLA_FLAGS", ""), f"--xla_force_host_platform_device_count={devices}"]
    ).strip()  # conftest has set the fast-compile flags in os.environ: they are inherited
    env["JAX_PLATFORMS"] = "cpu"
    return env


@pytest.fixture(scope="module")
def report():
    env = _environment(DEVICES)
    completed = subprocess.run(
        [sys.executable, __file__],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert completed.returncode == 0, completed.stderr[-5000:]
    return json.loads(completed.stdout.strip().splitlines()[-1])


# ---- the assertions --------------------------------------------------------------------------


def test_eight_devices(report):
    assert report["devices"] == DEVICES


def _assert_split(layout, rows):
    assert layout["spec"][0] is not None and layout["same_mesh"]
    assert layout["devices"] == list(range(DEVICES))  # every device holds a shard
    assert layout["rows"] == [rows]  # of equal size


def test_batched_least_squares_matches_unsharded(report):
    r = report["lstsq_batch"]
    assert r["converged"] == 13
    assert r["value_diff"] < TOLERANCE and r["cost_diff"] < TOLERANCE
    assert r["same_iterations"] and r["same_status"]
    assert r["valid"] == [True] * 13 + [False] * 3  # 13 problems padded to 16
    assert "pad=True" in r["uneven_error"]  # without pad, an uneven batch is refused


def test_batched_least_squares_is_split_and_compiled_once(report):
    r = report["lstsq_batch"]
    _assert_split(r["input_layout"], 2)
    _assert_split(r["layout"], 2)  # the output sharded like the input
    assert r["compilations"] == [1, 0]  # one compilation; a new batch of the same shape reuses it
    assert r["collectives"] == {}  # every device loops on its own problems


def test_batched_icp_matches_unsharded(report):
    r = report["icp_batch"]
    assert r["transform_diff"] < TOLERANCE
    assert r["fitness_diff"] < TOLERANCE and r["rmse_diff"] < TOLERANCE
    assert r["same_correspondences"] and r["same_iterations"] and r["same_status"]
    assert r["error_to_truth"] < 1e-2


def test_batched_icp_is_split_and_compiled_once(report):
    r = report["icp_batch"]
    _assert_split(r["layout"], 1)
    _assert_split(r["correspondence_layout"], 1)
    assert r["compilations"] == [1]
    assert r["collectives"] == {}


def test_residual_axis_matches_unsharded(report):
    r = report["residual_axis"]
    assert r["status"] == 0
    assert r["value_diff"] < TOLERANCE
    assert r["relative_cost_diff"] < TOLERANCE
    assert r["same_iterations"]


def test_residual_axis_reduces_by_all_reduce(report):
    r = report["residual_axis"]
    _assert_split(r["residual_layout"], 80_000 // DEVICES)
    assert r["compilations"] == [1]
    # only all-reduces, of the cost and the normal equations (1 + n + n^2 numbers, possibly split
    # over a few instructions): the Jacobian (80,000 x 3 x 6) is never gathered
    assert set(r["collectives"]) == {"all-reduce"}
    n = r["tangent_dim"]
    assert sum(r["collectives"]["all-reduce"]) <= 2 * (1 + n + n * n)


def test_residual_axis_with_an_unsplit_leaf_matches_unsharded(report):
    r = report["residual_axis_with_prior"]
    assert r["status"] == 0
    assert r["value_diff"] < TOLERANCE
    assert r["relative_cost_diff"] < TOLERANCE
    assert r["same_iterations"]


def test_residual_axis_with_an_unsplit_leaf_reduces_by_all_reduce(report):
    r = report["residual_axis_with_prior"]
    assert set(r["collectives"]) == {"all-reduce"}
    n = r["tangent_dim"]
    assert sum(r["collectives"]["all-reduce"]) <= 2 * (1 + n + n * n)


# ---- argument checks (in this process, one device; nothing compiles) ---------------------------


def test_argument_errors():
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import AxisType, Mesh

    from lieax import sharding

    mesh = sharding.batch_mesh()
    with pytest.raises(ValueError, match="common leading"):
        sharding.shard_batch((jnp.zeros((4, 3)), jnp.zeros((5, 3))), mesh)
    with pytest.raises(ValueError, match="common leading"):
        sharding.shard_batch((jnp.zeros((4, 3)), jnp.zeros(())), mesh)
    with pytest.raises(ValueError, match="empty"):
        sharding.shard_batch(jnp.zeros((0, 3)), mesh)
    with pytest.raises(ValueError, match="without arrays"):
        sharding.shard_batch((), mesh)
    with pytest.raises(TypeError, match="Mesh"):
        sharding.shard_batch(jnp.zeros((4, 3)), "batch")
    with pytest.raises(ValueError, match="in_axes"):
        sharding.batch_map(lambda a: a, mesh, in_axes=1)
    with pytest.raises(ValueError, match="not an axis"):
        sharding.batch_map(lambda a: a, mesh, axis_name="residual")
    grid = Mesh(np.asarray(jax.devices()).reshape(1, -1), ("a", "b"))
    with pytest.raises(ValueError, match="axis_name"):
        sharding.shard_residuals(lambda x, a: a, grid)
    explicit = Mesh(np.asarray(jax.devices()), ("batch",), axis_types=(AxisType.Explicit,))
    with pytest.raises(ValueError, match="AxisType.Auto"):
        sharding.shard_residuals(lambda x, a: a, explicit)
    tree, valid = sharding.shard_batch({"a": np.arange(3.0)}, mesh, pad=True)  # one device
    assert tree["a"].shape == (3,) and bool(np.all(valid))


# ---- several processes (opt-in: LIEAX_TEST_MULTIHOST=1) ---------------------------------------


def _multihost_checks(process_id, processes, port):  # runs in each of the processes
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(f"localhost:{port}", num_processes=processes, process_id=process_id)
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from jax.experimental import multihost_utils

    import lieax
    import lieax.lstsq
    from lieax import sharding

    def residual(pose, data):
        source, target = data
        return jax.vmap(lambda p, q: pose @ p - q)(source, target)

    def solve(data):
        return lieax.lstsq.least_squares(residual, lieax.SE3.identity(), data, throw=False)

    rng = np.random.default_rng(0)  # the same data on every process
    problems, points = 16, 30
    source = rng.normal(size=(problems, points, 3))
    truth = lieax.SE3.exp(jnp.asarray(0.5 * rng.normal(size=(problems, 6))))
    target = np.asarray(jax.vmap(lambda pose, cloud: pose @ cloud)(truth, jnp.asarray(source)))
    target = target + 0.01 * rng.normal(size=target.shape)
    reference = jax.jit(jax.vmap(solve))((source, target))  # on this process's first device

    mesh = sharding.batch_mesh()
    solve_sharded = sharding.batch_map(solve, mesh)
    whole = solve_sharded(sharding.shard_batch((source, target), mesh))
    part = slice(process_id * problems // processes, (process_id + 1) * problems // processes)
    local = solve_sharded(
        sharding.shard_batch((source[part], target[part]), mesh, process_local=True)
    )
    gathered = [
        np.asarray(multihost_utils.process_allgather(out.value.parameters(), tiled=True))
        for out in (whole, local)
    ]

    pairs = 8000
    pair_source = rng.normal(size=(pairs, 3))
    T_target_source = lieax.SE3.exp(jnp.array([0.3, -0.2, 0.1, 0.4, -0.3, 0.2]))
    pair_target = np.asarray(T_target_source @ jnp.asarray(pair_source))
    pair_target = pair_target + 0.01 * rng.normal(size=pair_target.shape)
    single = lieax.lstsq.least_squares(residual, lieax.SE3.identity(), (pair_source, pair_target))
    residual_mesh = sharding.batch_mesh(axis_name="residual")
    sharded_residual = sharding.shard_residuals(residual, residual_mesh)
    solution = jax.jit(
        lambda data: lieax.lstsq.least_squares(sharded_residual, lieax.SE3.identity(), data)
    )(sharding.shard_batch((pair_source, pair_target), residual_mesh))
    value = np.asarray(solution.value.parameters().addressable_shards[0].data)  # replicated
    expected = np.asarray(reference.value.parameters())
    return {
        "process": process_id,
        "devices": jax.device_count(),
        "local_devices": jax.local_device_count(),
        "whole_batch_diff": float(np.max(np.abs(gathered[0] - expected))),
        "process_local_diff": float(np.max(np.abs(gathered[1] - expected))),
        "residual_axis_diff": float(np.max(np.abs(value - np.asarray(single.value.parameters())))),
    }


@pytest.mark.slow
@pytest.mark.skipif(
    os.environ.get("LIEAX_TEST_MULTIHOST") != "1",
    reason="two JAX processes talking over localhost: set LIEAX_TEST_MULTIHOST=1",
)
def test_two_processes_of_four_devices():
    import socket

    with socket.socket() as probe:  # a free port for the coordinator
        probe.bind(("localhost", 0))
        port = probe.getsockname()[1]
    env = _environment(4)
    runs = [
        subprocess.Popen(
            [sys.executable, __file__, "--process", str(i), "2", str(port)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    for run in runs:
        out, err = run.communicate(timeout=600)
        assert run.returncode == 0, err[-5000:]
        r = json.loads(out.strip().splitlines()[-1])
        assert (r["devices"], r["local_devices"]) == (8, 4)
        assert r["whole_batch_diff"] < TOLERANCE
        assert r["process_local_diff"] < TOLERANCE
        assert r["residual_axis_diff"] < TOLERANCE


if __name__ == "__main__":
    if sys.argv[1:2] == ["--process"]:
        print(json.dumps(_multihost_checks(*map(int, sys.argv[2:5]))))
    else:
        print(json.dumps(_sharded_checks()))
