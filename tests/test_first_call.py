"""The first call (issue 30): building a problem compiles nothing, a first solve compiles a few
programs (one per structure and options, and a couple of small ones), constructors on concrete
inputs agree with the kernels, and `lieax.enable_compilation_cache` fills its directory.

Compilations are counted with JAX's monitoring events (one `backend_compile_duration` per XLA
program). The documented workflows are built and solved in a fresh process (one for the
module), where nothing is compiled yet: in this one, another test may already have compiled the
same small programs."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _compilations import compilations

from lieax import SE2, SE3, SO2, SO3, Sim3

# The child: in one fresh process, each documented workflow at a small size, built (which
# compiles nothing) and solved (the programs counted): the README's first example, the docs'
# factor graph as written there (docs/factor-graphs.md), a g2o pose graph, a BAL problem, the
# IMU smoother of examples/inertial_navigation.py (intervals of different sample counts), ICP
# and GICP; then it enables the persistent cache and runs one small jitted lieax program.
CHILD = textwrap.dedent(
    """
    import importlib.util, json, re, sys
    import jax
    compiled = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **kw: compiled.append(kw.get("fun_name"))
        if event == "/jax/core/compile/backend_compile_duration" else None)

    def take():
        names = list(compiled)
        compiled.clear()
        return names

    import numpy as np

    import lieax
    from lieax.factorgraph import Factor, FactorGraph, Var, marginal_covariances

    folder, root = sys.argv[1], sys.argv[2]
    jax.config.update("jax_enable_x64", True)
    report = {"import": take()}

    def python_blocks(path):
        with open(root + "/" + path, encoding="utf-8") as file:
            return re.findall(r"^```python\\n(.*?)^```", file.read(), flags=re.S | re.M)

    exec(python_blocks("README.md")[0], {"__name__": "readme"})
    report["readme_first"] = take()

    source = python_blocks("docs/factor-graphs.md")[0]
    docs = {"__name__": "docs"}
    exec(source[: source.index("result = graph.solve(")], docs)
    report["readme_graph"] = take()
    graph, points = docs["graph"], docs["points"]
    result = graph.solve(eliminate=points)
    marginal_covariances(graph, result.values, points, [0])
    report["readme_graph_solve"] = take()

    g2o = folder + "/small.g2o"
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
    lieax.graph.optimize(pose_graph)
    report["g2o_solve"] = take()

    generated = lieax.ba.synthetic_bal(3, 20, 60, seed=0).problem
    lieax.ba.write_bal(folder + "/small.txt", generated)
    problem = lieax.ba.read_bal(folder + "/small.txt")
    pose, intrinsics = problem.camera_variables(np.float64)
    cameras = Var((pose, intrinsics), name="cameras")
    landmarks = Var(problem.points, name="points")
    reprojection = Factor(
        lieax.ba.camera_residual,
        (cameras[problem.camera_indices], landmarks[problem.point_indices]),
        problem.observations, jacobian_fn=lieax.ba.camera_jacobians, name="reprojection")
    bal_graph = FactorGraph([reprojection], check_gauge=False)
    report["bal"] = take()
    bal_graph.solve(eliminate=landmarks, solver=lieax.lstsq.LevenbergMarquardt.gtsam(scaling="clipped"), termination=lieax.lstsq.Termination.gtsam(max_iterations=5))
    report["bal_solve"] = take()

    spec = importlib.util.spec_from_file_location(
        "inertial_navigation", root + "/examples/inertial_navigation.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    data = example.simulate(7, np.random.default_rng(0), rate=20)
    imu_params = example.params()
    kept = [20, 18, 19, 20, 17, 16]  # samples per interval: a stream that drops some
    streams = {name: [s[:n] for s, n in zip(data[name], kept)] for name in ("accel", "gyro")}
    report["imu"] = take()
    pim = lieax.imu.preintegrate_intervals(imu_params, dt=data["dt"], **streams)
    imu_graph, _ = example.build_graph(data, pim, imu_params)
    imu_graph.solve(termination=lieax.lstsq.Termination.gtsam(max_iterations=5))
    report["imu_solve"] = take()

    source, target, normals, _ = lieax.icp.synthetic_pair(
        300, rotation_deg=10.0, translation=0.1, noise=0.002, same_samples=False, seed=0)
    report["icp"] = take()
    lieax.icp.point_to_plane(source, target, target_normals=normals,
                             max_correspondence_distance=0.2, max_iterations=10)
    report["icp_solve"] = take()
    lieax.icp.gicp(source, target, max_correspondence_distance=0.2, max_iterations=10)
    report["gicp_solve"] = take()

    report["cache_dir"] = str(lieax.enable_compilation_cache(folder + "/cache"))
    jax.block_until_ready(jax.jit(lambda x: lieax.SO3.exp(x).log())(np.ones(3)))
    print("REPORT " + json.dumps(report))
    """
)

# The most XLA programs each workflow's first solve compiles at the child's sizes (a regression
# that adds a program fails here): one program per (structure, options) (the marginal
# covariances run the solve's), plus the IMU preintegration's and GICP's covariances'. The README's first example
# is eager user code: one program per group operation and per `jax.numpy` check (15).
PROGRAMS = {
    "readme_first": 16,
    "readme_graph_solve": 1,
    "g2o_solve": 1,
    "bal_solve": 1,
    "imu_solve": 2,
    "icp_solve": 1,
    "gicp_solve": 2,
}


@pytest.fixture(scope="module")
def fresh_process(tmp_path_factory):
    """The child's report (a fresh process: nothing compiled before it)."""
    folder = tmp_path_factory.mktemp("first_call")
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(folder), root], capture_output=True, text=True, env=env
    )
    assert done.returncode == 0, done.stderr[-3000:]
    line = next(x for x in done.stdout.splitlines() if x.startswith("REPORT "))
    return folder, json.loads(line[len("REPORT ") :])


@pytest.mark.parametrize("build", ["import", "readme_graph", "g2o", "bal", "imu", "icp"])
def test_building_compiles_nothing(fresh_process, build):
    """Importing lieax, and building the docs' factor graph as written there, a g2o pose graph, a
    BAL problem, the IMU smoother's data and generated ICP clouds, compile no XLA program."""
    _, report = fresh_process
    assert report[build] == []


@pytest.mark.parametrize("workflow", sorted(PROGRAMS))
def test_first_solve_compiles_few_programs(fresh_process, workflow):
    """Each workflow's first call compiles at most its `PROGRAMS` count of XLA programs."""
    _, report = fresh_process
    names = report[workflow]
    assert len(names) <= PROGRAMS[workflow], names


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
