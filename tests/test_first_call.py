"""The first call (issue 30): building a problem compiles nothing, constructors on concrete inputs
agree with the kernels, and `lieax.enable_compilation_cache` fills its directory.

Compilations are counted with JAX's monitoring events (one `backend_compile_duration` per XLA
program). The README's factor graph, a g2o file and a BAL problem are built in a fresh process
(one for the module), where nothing is compiled yet: in this one, another test may already have
compiled the same small programs."""

import contextlib
import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax import SE2, SE3, SO2, SO3, Sim3

_COMPILED = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, **kw: (
        _COMPILED.append(kw.get("fun_name"))
        if event == "/jax/core/compile/backend_compile_duration"
        else None
    )
)


@contextlib.contextmanager
def compilations():
    """The names of the XLA programs compiled inside the block."""
    start = len(_COMPILED)
    found = []
    yield found
    found.extend(_COMPILED[start:])


# The child: the README's factor graph, as written there up to `FactorGraph(...)`, then a g2o file
# and a BAL problem; it prints the programs each build compiled, then enables the persistent cache
# and runs one small jitted lieax program.
CHILD = textwrap.dedent(
    """
    import json, sys
    import jax
    compiled = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **kw: compiled.append(kw.get("fun_name"))
        if event == "/jax/core/compile/backend_compile_duration" else None)

    def take():
        names = list(compiled)
        compiled.clear()
        return names

    import jax.numpy as jnp
    import numpy as np

    import lieax
    from lieax import SE2
    from lieax.factorgraph import Factor, FactorGraph, Var

    jax.config.update("jax_enable_x64", True)
    report = {"import": take()}

    # The README's user code (eager jax.numpy: it compiles as any JAX code does).
    truth = SE2.exp(jnp.array([[k, 0.1 * k, 0.2 * k] for k in range(5)], dtype=float))
    marks = jnp.array([[1.0, 2.0], [3.0, -1.0], [4.5, 1.5]])
    i, j = np.arange(4), np.arange(1, 5)
    seen_by, seen = np.array([0, 1, 2, 2, 3, 4]), np.array([0, 0, 1, 2, 1, 2])
    start_poses, start_points = truth.rplus(0.1 * jnp.ones((5, 3))), marks + 0.3
    z_between, z_prior = truth[i].between(truth[j]), truth[:1]
    z_landmark = jax.vmap(lambda x, p: x.inverse() @ p)(truth[seen_by], marks[seen])
    take()

    # lieax's building: Var, indexing, Factor, FactorGraph.
    poses = Var(start_poses, name="poses")
    points = Var(start_points, name="points")

    def between(a, b, z):
        return z.between(a.between(b)).log()

    def prior(x, z):
        return z.between(x).log()

    def landmark(x, p, z):
        return x.inverse() @ p - z

    graph = FactorGraph([
        Factor(between, (poses[i], poses[j]), z_between,
               sqrt_information=np.diag([10.0, 10.0, 20.0])),
        Factor(prior, (poses[np.array([0])],), z_prior, information=1e4 * np.eye(3)),
        Factor(landmark, (poses[seen_by], points[seen]), z_landmark,
               loss=lieax.lstsq.Huber(0.5)),
    ])
    report["readme_graph"] = take()

    g2o = sys.argv[1] + "/small.g2o"
    with open(g2o, "w") as file:
        file.write("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\\n")
        file.write("VERTEX_SE3:QUAT 1 1 0.1 0 0 0 0.0998 0.995\\n")
        file.write("VERTEX_SE3:QUAT 2 2 0.2 0 0 0 0.198 0.98\\n")
        for a, b in ((0, 1), (1, 2), (0, 2)):
            file.write(f"EDGE_SE3:QUAT {a} {b} 1 0 0 0 0 0.0998 0.995 "
                       "100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 400 0 0 400 0 400\\n")
    pose_graph = lieax.graph.read_g2o(g2o)
    lieax.graph.to_factor_graph(pose_graph)
    report["g2o"] = take()

    generated = lieax.ba.synthetic_bal(3, 20, 60, seed=0).problem
    lieax.ba.write_bal(sys.argv[1] + "/small.txt", generated)
    problem = lieax.ba.read_bal(sys.argv[1] + "/small.txt")
    pose, intrinsics = problem.camera_variables(jnp.float64)
    cameras = Var((pose, intrinsics), name="cameras")
    landmarks = Var(problem.points, name="points")
    reprojection = Factor(
        lieax.ba.camera_residual,
        (cameras[problem.camera_indices], landmarks[problem.point_indices]),
        problem.observations, jacobian_fn=lieax.ba.camera_jacobians, name="reprojection")
    FactorGraph([reprojection], check_gauge=False)
    report["bal"] = take()

    report["cache_dir"] = str(lieax.enable_compilation_cache(sys.argv[1] + "/cache"))
    jax.block_until_ready(jax.jit(lambda x: lieax.SO3.exp(x).log())(jnp.ones(3)))
    print("REPORT " + json.dumps(report))
    """
)


@pytest.fixture(scope="module")
def fresh_process(tmp_path_factory):
    """The child's report (a fresh process: nothing compiled before it)."""
    folder = tmp_path_factory.mktemp("first_call")
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(folder)], capture_output=True, text=True, env=env
    )
    assert done.returncode == 0, done.stderr[-3000:]
    line = next(x for x in done.stdout.splitlines() if x.startswith("REPORT "))
    return folder, json.loads(line[len("REPORT ") :])


@pytest.mark.parametrize("build", ["import", "readme_graph", "g2o", "bal"])
def test_building_compiles_nothing(fresh_process, build):
    """Importing lieax, and building the README's factor graph (from its user-computed data), a
    g2o pose graph and a BAL problem, compile no XLA program."""
    _, report = fresh_process
    assert report[build] == []


def test_enable_compilation_cache_writes_entries(fresh_process):
    folder, report = fresh_process
    cache = folder / "cache"
    assert report["cache_dir"] == str(cache)
    assert any(cache.iterdir()), "the jitted program was not written to the cache"


def test_default_cache_dir_follows_xdg(monkeypatch, tmp_path):
    from lieax._compilation_cache import default_cache_dir

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "lieax" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "lieax" / "jax"


def _constructors(rng, dtype):
    """`(name, constructor, arguments)` on concrete inputs of shapes no other test uses."""
    angles = [rng.uniform(-3.0, 3.0, 7).astype(dtype) for _ in range(3)]
    rotvecs = rng.normal(size=(7, 3)) * np.array([[1e-9], [1e-4], [1], [2], [3], [3.1], [0]])
    rotvecs = rotvecs.astype(dtype)
    so3 = jax.jit(SO3.exp)(rotvecs)
    se3 = jax.jit(SE3.exp)(rng.normal(size=(7, 6)).astype(dtype))
    se2 = jax.jit(SE2.exp)(rng.normal(size=(7, 3)).astype(dtype))
    noisy = rng.normal(scale=0.01, size=(7, 4, 4)).astype(dtype)
    return [
        ("SO2.from_angle", SO2.from_angle, (angles[0],)),
        ("SE2.from_xy_theta", SE2.from_xy_theta, tuple(angles)),
        ("SE2.from_xy_theta (numbers)", SE2.from_xy_theta, (1.0, 2, angles[2])),
        ("SO3.exp", SO3.exp, (rotvecs,)),
        ("SE3.exp", SE3.exp, (np.concatenate([rotvecs[::-1], rotvecs], -1),)),
        ("SE2.exp", SE2.exp, (np.concatenate([rotvecs[:, :2], rotvecs[:, 2:]], -1),)),
        ("SO3.from_rotvec", SO3.from_rotvec, (rotvecs,)),
        ("SO3.from_rpy", SO3.from_rpy, tuple(angles)),
        ("SO3.from_xyzw", SO3.from_xyzw, (np.roll(np.asarray(so3.parameters()), -1, -1),)),
        ("SO3.from_matrix", SO3.from_matrix, (np.asarray(so3.as_matrix()) + noisy[:, :3, :3],)),
        ("SE3.from_matrix", SE3.from_matrix, (np.asarray(se3.as_matrix()) + noisy,)),
        ("SE2.from_matrix", SE2.from_matrix, (np.asarray(se2.as_matrix()) + noisy[:, :3, :3],)),
        ("SO2.from_matrix", SO2.from_matrix, (noisy[:, :2, :2] + np.eye(2, dtype=dtype),)),
        (
            "SE3.from_rotation_and_translation",
            SE3.from_rotation_and_translation,
            (so3, rng.normal(size=(7, 3)).astype(dtype)),
        ),  # fmt: skip
        (
            "SE2.from_rotation_and_translation",
            SE2.from_rotation_and_translation,
            (SO2(np.asarray(se2.parameters())[:, :2]), rng.normal(size=(1, 2)).astype(dtype)),
        ),  # fmt: skip
        ("SE3(params)", SE3, (np.asarray(se3.parameters()),)),
    ]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_constructors_compile_nothing_and_match_the_kernels(dtype):
    """On concrete inputs every constructor compiles nothing, and gives the kernels' parameters
    (the same constructor under `jit`, where its inputs are traced) in the same dtype, to
    rounding."""
    rng = np.random.default_rng(0)
    cases = _constructors(rng, dtype)
    traced = jax.jit(lambda args: [make(*a).parameters() for _, make, a in cases])(
        [a for _, _, a in cases]
    )
    with compilations() as compiled:
        concrete = [make(*args) for _, make, args in cases]
        identities = [G.identity((7, 1), dtype=dtype) for G in (SO2, SE2, SO3, SE3, Sim3)]
    assert compiled == []
    eps = np.finfo(dtype).eps
    for (name, _, _), element, expected in zip(cases, concrete, traced):
        assert element.dtype == expected.dtype == dtype, name
        np.testing.assert_allclose(
            element.parameters(), expected, rtol=0, atol=8 * eps, err_msg=name
        )
    kernel_identities = jax.jit(
        lambda: [G.exp(jnp.zeros((7, 1, G.tangent_dim), dtype)) for G in (SO2, SE2, SO3, SE3, Sim3)]
    )()
    for element, expected in zip(identities, kernel_identities):
        assert element.dtype == expected.dtype == dtype
        np.testing.assert_array_equal(element.parameters(), expected.parameters())


def test_constructors_keep_their_derivatives():
    """Traced inputs take the kernels: derivatives through the constructors match central
    differences."""

    def f(angles):
        roll, pitch, yaw = angles
        return jnp.sum(
            SO3.from_rpy(roll, pitch, yaw).as_matrix()
            * SE3.from_rotation_and_translation(SO3.exp(angles), angles).as_matrix()[:3, :3]
        ) + jnp.sum(SE2.from_xy_theta(roll, pitch, yaw).as_matrix() ** 2 * yaw)

    angles, step = np.array([0.3, -0.2, 1.1]), 1e-6
    shifted = jax.jit(jax.vmap(f))(angles + step * np.concatenate([np.eye(3), -np.eye(3)]))
    numeric = (shifted[:3] - shifted[3:]) / (2 * step)
    np.testing.assert_allclose(jax.jit(jax.grad(f))(angles), numeric, rtol=1e-7, atol=1e-8)


def test_constructor_errors_are_unchanged():
    with pytest.raises(TypeError, match=r"SE2.from_xy_theta: arguments of different dtypes"):
        SE2.from_xy_theta(np.zeros(2, np.float32), np.zeros(2), 0.0)
    with pytest.raises(ValueError, match=r"SE2.from_xy_theta: batch shapes"):
        SE2.from_xy_theta(np.zeros(2), np.zeros(3), 0.0)
    with pytest.raises(ValueError, match=r"SO3.from_matrix matrix must have shape"):
        SO3.from_matrix(np.eye(4))
    with pytest.raises(TypeError, match=r"floating dtype"):
        SO2.from_angle(np.arange(3))
