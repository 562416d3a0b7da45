"""First call: what a user waits for in a fresh process, workflow by workflow (issue 30).

Every measurement runs in a fresh subprocess (nothing compiled, nothing cached in memory). Per
workflow, three processes:

1. **cold** (JAX's persistent cache off): the seconds to `import lieax` (after `import jax`, whose
   own import is reported apart), to build the problem, the first call (tracing, XLA compilation
   and the first solve) and the warm call (the best of two more calls), and the number of XLA
   compilations and their seconds while building and during the first call, counted by JAX's
   monitoring events (`/jax/core/compile/backend_compile_duration` per compiled program,
   `/jax/core/compile/jaxpr_trace_duration` per trace, `/jax/compilation_cache/cache_hits` for
   the programs loaded from the persistent cache instead);
2. **cache, first process**: the same with `lieax.enable_compilation_cache(DIR)` on a fresh
   temporary directory, which it fills;
3. **cache, second process**: the same again on that directory: its build + first call, and how
   many programs it still compiled (those JAX does not cache: programs with a Python host
   callback, see `lieax.enable_compilation_cache`). The solve loops come from lieax's store of
   compiled programs (`lieax._executable_store`, which the same call turns on): loaded with no
   trace and no compilation event, they count in neither column but in "loaded from lieax's
   store", beside the traces the second process still made (JAX's cache needs a trace).

Workflows (`--only NAME[,NAME]`; `--quick` shrinks the large ones about tenfold):

- `readme-first`: the README's first example (an SE3 acting on a point, its Jacobians);
- `readme-graph`: the factor-graph example of docs/factor-graphs.md, formerly the README's (build,
  solve, a marginal covariance);
- `icp-demo`: `examples/icp_demo.py`'s registration (generated scene, 4000 points, float64);
- `g2o`: `lieax.graph.optimize` on `intel.g2o` from the shared data (`--data`,
  `LIEAX_DATA_DIR`), else a generated 2D pose graph of the same size;
- `ba`: bundle adjustment at Ladybug-49 size (`lieax.ba.synthetic_bal`: 49 cameras, 7,776
  points, 31,843 observations), as `examples/bundle_adjustment.py`, 20 iterations;
- `imu`: `examples/inertial_navigation.py` with 501 keyframes (500 intervals of 100 samples):
  `preintegrate_intervals` of a stream whose intervals lose 0-4 samples each, the example's
  graph and its solve are the first call, the
  preintegration and the solve the warm call;
- `landmarks`: a 2D landmark graph of 7,000 poses and 151 landmarks, odometry, a prior and a
  bearing-range residual written in plain `jax.numpy` as a user would;
- `gicp`: `lieax.icp.gicp` on the 25k-point LiDAR pair (scan1 to scan0, shared data; the row is
  skipped without it).

    python benchmarks/first_call.py [--only readme-graph,g2o] [--quick] [--json out.json]
                                    [--data ../shared/data]

Times are wall seconds of one run each (a first call happens once per process); on a shared,
busy machine they vary with the load, the compilation counts do not.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import _results

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
MARK = "FIRST_CALL_JSON "
WORKFLOWS = ("readme-first", "readme-graph", "icp-demo", "g2o", "ba", "imu", "landmarks", "gicp")


# ---- the child process: one workflow, one measurement ---------------------------------------------


class Compilations:
    """Counts traces, XLA compilations (and their seconds) and persistent-cache hits from JAX's
    monitoring events; `take()` returns the counts since the last call."""

    def __init__(self, monitoring):
        self.traces = self.compiled = self.hits = 0
        self.seconds = 0.0
        self._pending_hit = False
        monitoring.register_event_listener(self._event)
        monitoring.register_event_duration_secs_listener(self._duration)

    def _event(self, event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            self._pending_hit = True  # the backend-compile duration that follows is a load

    def _duration(self, event, seconds, **_):
        if event == "/jax/core/compile/jaxpr_trace_duration":
            self.traces += 1
        elif event == "/jax/core/compile/backend_compile_duration":
            if self._pending_hit:
                self.hits += 1
                self._pending_hit = False
            else:
                self.compiled += 1
                self.seconds += seconds

    def take(self):
        counts = {
            "traces": self.traces, "compilations": self.compiled,
            "xla_s": round(self.seconds, 3), "cache_hits": self.hits,
        }  # fmt: skip
        self.traces = self.compiled = self.hits = 0
        self.seconds = 0.0
        return counts


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def _ready(tree):
    import jax

    return jax.block_until_ready(tree)


def _load_example(name):
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        name, os.path.join(ROOT, "examples", f"{name}.py")
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# Each workflow: `setup(quick, data_dir)` makes the data (NumPy, not timed as building; None to
# skip the row), `build(data)` the problem, `call(problem)` the first and warm calls.


def readme_first_setup(quick, data_dir):
    return ()


def readme_first_build(_):
    return ()


def readme_first_call(_):
    import jax
    import jax.numpy as jnp

    import lieax

    T_world_body = lieax.SE3.exp(jnp.array([1.0, 0.0, 0.5, 0.1, -0.2, 0.3]))
    p_body = jnp.array([0.2, -0.1, 1.0])
    p_world = T_world_body @ p_body
    jacobians = jax.jit(lieax.jacobian(lambda T, p: T @ p, argnums=(0, 1)))
    J_T, J_p = jacobians(T_world_body, p_body)
    delta = 1e-6 * jnp.array([1.0, -2.0, 0.5, 0.3, 0.1, -0.4])
    moved = T_world_body.rplus(delta) @ p_body
    assert jnp.allclose(moved - p_world, J_T @ delta, atol=1e-12)
    assert jnp.allclose(J_p, T_world_body.rotation().as_matrix())
    assert jnp.allclose(T_world_body.rplus(delta).rminus(T_world_body), delta)
    return jax.block_until_ready(J_T)


def readme_graph_setup(quick, data_dir):
    return ()


def docs_graph_example():
    """The factor-graph example of docs/factor-graphs.md (its first Python block), split into the
    building (up to `FactorGraph(...)`) and the rest (the solve, the checks, a marginal)."""
    import re

    with open(os.path.join(ROOT, "docs", "factor-graphs.md"), encoding="utf-8") as file:
        source = re.search(r"^```python\n(.*?)^```", file.read(), flags=re.S | re.M).group(1)
    split = source.index("result = graph.solve(")
    return source[:split], source[split:]


def readme_graph_build(_):
    """The docs' factor-graph example up to `FactorGraph(...)`, as written there."""
    namespace = {"__name__": "docs_example"}
    exec(compile(docs_graph_example()[0], "docs/factor-graphs.md", "exec"), namespace)
    return namespace["graph"], namespace["points"], namespace["marks"]


def readme_graph_call(problem):
    import jax.numpy as jnp

    from lieax.factorgraph import marginal_covariances

    graph, points, marks = problem
    result = graph.solve(eliminate=points)
    _, solved_points = result.values
    assert result.converged and jnp.allclose(solved_points, marks, atol=1e-8)
    return _ready(marginal_covariances(graph, result.values, points, [0]))


def icp_demo_setup(quick, data_dir):
    from lieax import icp

    source, target, normals, _ = icp.synthetic_pair(
        4000, rotation_deg=15.0, translation=0.2, noise=0.002, same_samples=False, seed=0,
    )  # fmt: skip
    return source, target, normals


def icp_demo_build(data):
    """As `examples/icp_demo.py`: the clouds stay NumPy arrays until the registration."""
    import numpy as np

    source, target, normals = (np.asarray(cloud) for cloud in data)
    extent = float(np.linalg.norm(target.max(0) - target.min(0)))
    return source, target, normals, 0.05 * extent


def icp_demo_call(problem):
    from lieax import icp

    source, target, normals, distance = problem
    return _ready(
        icp.point_to_plane(
            source,
            target,
            target_normals=normals,
            max_correspondence_distance=distance,
            max_iterations=30,
        )  # fmt: skip
    )


def g2o_setup(quick, data_dir):
    path = os.path.join(data_dir or "", "g2o", "intel.g2o")
    if data_dir and os.path.exists(path) and not quick:
        return path
    path = os.path.join(tempfile.mkdtemp(), "generated.g2o")
    _write_pose_graph(path, 170 if quick else 1728)
    return path


def _write_pose_graph(path, n):
    """A g2o file of `n` 2D poses (intel's size by default): a random walk of 1 m steps, odometry
    and one loop closure per ten poses (noise 0.05 m / 0.01 rad), poses from dead reckoning."""
    import numpy as np

    rng = np.random.default_rng(0)
    theta = np.cumsum(rng.normal(0.0, 0.2, n))
    xy = np.cumsum(np.stack([np.cos(theta), np.sin(theta)], 1), 0)
    i = np.concatenate([np.arange(n - 1), rng.integers(0, n - 20, n // 10)])
    j = np.concatenate([np.arange(1, n), i[n - 1 :] + rng.integers(5, 20, n // 10)])
    d, c, s = xy[j] - xy[i], np.cos(theta[i]), np.sin(theta[i])
    measured = np.stack(
        [c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], theta[j] - theta[i]], 1
    )
    measured += rng.normal(0.0, 1.0, measured.shape) * np.array([0.05, 0.05, 0.01])
    start = xy + rng.normal(0.0, 0.3, xy.shape)
    with open(path, "w") as file:
        for k in range(n):
            file.write(f"VERTEX_SE2 {k} {start[k, 0]:.9g} {start[k, 1]:.9g} {theta[k]:.9g}\n")
        for a, b, (x, y, t) in zip(i, j, measured):
            file.write(f"EDGE_SE2 {a} {b} {x:.9g} {y:.9g} {t:.9g} 400 0 0 400 0 10000\n")


def g2o_build(path):
    import lieax

    return lieax.graph.read_g2o(path)


def g2o_call(graph):
    import lieax

    return _ready(lieax.graph.optimize(graph))


def ba_setup(quick, data_dir):
    from lieax import ba

    sizes = (10, 780, 3200) if quick else ba.SYNTHETIC_PRESETS["ladybug-49"]
    return ba.synthetic_bal(*sizes, seed=0).problem


def ba_build(problem):
    """As `examples/bundle_adjustment.py`'s `solve`."""
    import jax.numpy as jnp

    from lieax import ba
    from lieax import factorgraph as fg

    pose, intrinsics = problem.camera_variables(jnp.float64)
    cameras = fg.Var((pose, intrinsics), name="cameras")
    points = fg.Var(problem.points, name="points")
    reprojection = fg.Factor(
        ba.camera_residual,
        (cameras[problem.camera_indices], points[problem.point_indices]),
        problem.observations,
        jacobian_fn=ba.camera_jacobians,
        name="reprojection",
    )
    return fg.FactorGraph([reprojection], check_gauge=False), points


def ba_call(problem):
    from lieax.lstsq import LevenbergMarquardt, Termination

    graph, points = problem
    marquardt = LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen")
    termination = Termination.gtsam(max_iterations=20)
    return _ready(graph.solve(eliminate=points, solver=marquardt, termination=termination))


def imu_setup(quick, data_dir):
    import numpy as np

    example = _load_example("inertial_navigation")
    return example, example.simulate(51 if quick else 501, np.random.default_rng(0))


def imu_build(data):
    """The IMU parameters, and the samples as a stream delivers them: each interval loses 0-4 of
    its last samples (dropped samples), so the intervals hold different numbers of samples."""
    import numpy as np

    example, simulated = data
    rng = np.random.default_rng(1)
    counts = simulated["gyro"].shape[1] - rng.integers(0, 5, len(simulated["gyro"]))
    stream = {
        name: [samples[:count] for samples, count in zip(simulated[name], counts)]
        for name in ("gyro", "accel")
    }
    return {"example": example, "data": simulated, "params": example.params(), **stream}


def imu_call(problem):
    """Preintegration of the stream in one call (`preintegrate_intervals`: padded, masked, one
    program per bucket), then (the first time) the example's graph, then its solve."""
    import lieax

    data, imu_params = problem["data"], problem["params"]
    pim = lieax.imu.preintegrate_intervals(
        imu_params, accel=problem["accel"], gyro=problem["gyro"], dt=data["dt"]
    )
    if "graph" not in problem:
        problem["graph"], _ = problem["example"].build_graph(data, pim, imu_params)
    from lieax.lstsq import Termination

    return _ready(problem["graph"].solve(termination=Termination.gtsam(max_iterations=50)))


def landmarks_setup(quick, data_dir):
    """A robot driving 0.5 m steps with turning rates of a smooth random walk, 151 landmarks
    scattered along its path; each pose measures the bearing and range of its two nearest
    landmarks (and every landmark is seen at least twice). Odometry noise 0.02 m / 0.002 rad,
    bearing 0.01 rad, range 0.05 m; the start is dead reckoning, the landmarks 0.5 m off."""
    import numpy as np

    rng = np.random.default_rng(0)
    n, m = (700, 31) if quick else (7000, 151)
    theta = np.cumsum(np.convolve(rng.normal(0.0, 0.05, n), np.ones(20) / 20, "same"))
    xy = np.cumsum(0.5 * np.stack([np.cos(theta), np.sin(theta)], 1), 0)
    anchors = rng.choice(n, m, replace=False)
    marks = xy[anchors] + rng.normal(0.0, 3.0, (m, 2))
    distance = np.linalg.norm(xy[:, None] - marks[None], axis=-1)
    seen = np.argsort(distance, axis=1)[:, :2]
    pairs = {(int(p), int(k)) for p in range(n) for k in seen[p]}
    for k in range(m):
        pairs |= {(int(p), k) for p in np.argsort(distance[:, k])[:2]}
    pose_of, mark_of = np.array(sorted(pairs)).T
    local = marks[mark_of] - xy[pose_of]
    c, s = np.cos(theta[pose_of]), np.sin(theta[pose_of])
    lx, ly = c * local[:, 0] + s * local[:, 1], -s * local[:, 0] + c * local[:, 1]
    bearing_range = np.stack([np.arctan2(ly, lx), np.hypot(lx, ly)], 1)
    bearing_range += rng.normal(0.0, 1.0, bearing_range.shape) * np.array([0.01, 0.05])
    dx, dy = np.diff(xy[:, 0]), np.diff(xy[:, 1])
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    odometry = np.stack([c * dx + s * dy, -s * dx + c * dy, np.diff(theta)], 1)
    odometry += rng.normal(0.0, 1.0, odometry.shape) * np.array([0.02, 0.02, 0.002])
    heading = np.concatenate([[theta[0]], theta[0] + np.cumsum(odometry[:, 2])])
    step = np.stack(
        [
            np.cos(heading[:-1]) * odometry[:, 0] - np.sin(heading[:-1]) * odometry[:, 1],
            np.sin(heading[:-1]) * odometry[:, 0] + np.cos(heading[:-1]) * odometry[:, 1],
        ],
        1,
    )
    start = np.concatenate([xy[:1], xy[:1] + np.cumsum(step, 0)])
    return {
        "start": (start, heading), "first": (xy[0], theta[0]), "odometry": odometry,
        "marks": marks + rng.normal(0.0, 0.5, marks.shape), "pose_of": pose_of,
        "mark_of": mark_of, "bearing_range": bearing_range,
    }  # fmt: skip


def bearing_range_residual(pose, landmark, z):
    """The user's residual: the landmark's bearing (wrapped) and range in the pose's frame, in
    plain `jax.numpy` on the pose's parameters `(cos, sin, x, y)`."""
    import jax.numpy as jnp

    c, s, x, y = pose.parameters()
    dx, dy = landmark[0] - x, landmark[1] - y
    lx, ly = c * dx + s * dy, -s * dx + c * dy
    bearing = jnp.arctan2(ly, lx) - z[0]
    return jnp.stack([jnp.arctan2(jnp.sin(bearing), jnp.cos(bearing)), jnp.hypot(lx, ly) - z[1]])


def landmarks_build(data):
    import numpy as np

    import lieax
    from lieax.factorgraph import Factor, FactorGraph, Var

    (xy, heading), (xy0, theta0) = data["start"], data["first"]
    n = len(heading)
    poses = Var(lieax.SE2.from_xy_theta(xy[:, 0], xy[:, 1], heading), name="poses")
    marks = Var(data["marks"], name="landmarks")
    i, j = np.arange(n - 1), np.arange(1, n)
    odometry = data["odometry"]
    measured = lieax.SE2.from_xy_theta(odometry[:, 0], odometry[:, 1], odometry[:, 2])
    graph = FactorGraph([
        Factor(lambda a, b, z: z.between(a.between(b)).log(), (poses[i], poses[j]), measured,
               sqrt_information=np.diag([50.0, 50.0, 500.0]), name="odometry"),
        Factor(lambda x, z: z.between(x).log(), (poses[np.array([0])],),
               lieax.SE2.from_xy_theta(xy0[:1], xy0[1:], np.array([theta0])),
               sqrt_information=1e3 * np.eye(3), name="prior"),
        Factor(bearing_range_residual, (poses[data["pose_of"]], marks[data["mark_of"]]),
               data["bearing_range"], sqrt_information=np.diag([100.0, 20.0]),
               name="bearing_range"),
    ])  # fmt: skip
    return graph


def landmarks_call(graph):
    return _ready(graph.solve(throw=False))


def gicp_setup(quick, data_dir):
    import numpy as np

    path = os.path.join(data_dir or "", "clouds", "lidar_scans_0_1_2", "scans.npz")
    if not data_dir or not os.path.exists(path):
        return None
    with np.load(path) as scans:
        source, target = scans["scan1"], scans["scan0"]
    if quick:
        source, target = source[::10], target[::10]
    return source, target


def gicp_build(data):
    """The clouds as NumPy arrays, as read (`gicp` transfers them)."""
    import numpy as np

    return tuple(np.asarray(cloud) for cloud in data)


def gicp_call(clouds):
    from lieax import icp

    return _ready(icp.gicp(*clouds, max_correspondence_distance=1.0))


def child(name, quick, data_dir, cache_dir):
    """Measures one workflow in this (fresh) process; prints one JSON line."""
    start = time.perf_counter()
    import jax

    import_jax = time.perf_counter() - start
    counts = Compilations(jax.monitoring)
    jax.config.update("jax_enable_x64", True)
    start = time.perf_counter()
    import lieax

    import_lieax = time.perf_counter() - start
    if cache_dir:
        lieax.enable_compilation_cache(cache_dir)
    row = {"workflow": name, "import_jax_s": import_jax, "import_lieax_s": import_lieax}
    row["import"] = counts.take()
    key = name.replace("-", "_")
    setup, build, call = (globals()[f"{key}_{part}"] for part in ("setup", "build", "call"))
    data, row["setup_s"] = _timed(lambda: setup(quick, data_dir))
    if data is None:
        print(MARK + json.dumps({"workflow": name, "skipped": "no shared data"}), flush=True)
        return
    row["setup"] = counts.take()
    problem, row["build_s"] = _timed(lambda: build(data))
    row["build"] = counts.take()
    result, row["first_s"] = _timed(lambda: call(problem))
    row["status"] = getattr(result, "status_name", None)
    row["first"] = counts.take()
    row["store_loads"] = lieax._executable_store.loads()
    row["warm_s"] = min(_timed(lambda: call(problem))[1] for _ in range(2))
    print(MARK + json.dumps(row), flush=True)


# ---- the parent: fresh processes per measurement, the table ---------------------------------------


def measure(name, quick, data_dir, cache_dir=None):
    command = [sys.executable, os.path.abspath(__file__), "--child", name]
    command += ["--quick"] * quick + (["--data", data_dir] if data_dir else [])
    command += ["--cache-dir", cache_dir] if cache_dir else []
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [ROOT, env.get("PYTHONPATH")]))
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=ROOT)
    for line in done.stdout.splitlines():
        if line.startswith(MARK):
            return json.loads(line[len(MARK) :])
    raise RuntimeError(f"{name} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")


def measure_workflow(name, quick, data_dir):
    try:
        return _measure_workflow(name, quick, data_dir)
    except RuntimeError as error:  # the row reports it; the other workflows still run
        return {"skipped": str(error).splitlines()[-1][:200]}


def _measure_workflow(name, quick, data_dir):
    cold = measure(name, quick, data_dir)
    if "skipped" in cold:
        return cold
    with tempfile.TemporaryDirectory() as cache_dir:
        writer = measure(name, quick, data_dir, cache_dir)
        reader = measure(name, quick, data_dir, cache_dir)
    return {"cold": cold, "cache_first_process": writer, "cache_second_process": reader}


HEADERS = [
        "workflow", "import lieax", "build", "compiles (build)", "compiles (1st call)",
        "XLA s (1st call)", "cold 1st call", "2nd process, cache: build + 1st call",
    "not cached (compiled in 2nd)", "2nd: traces / loaded from lieax's store", "warm call",
]  # fmt: skip


def table_rows(results):
    """One row of formatted cells per workflow, under `HEADERS`."""
    rows = []
    for name, result in results.items():
        if "skipped" in result:
            rows.append([name, f"skipped: {result['skipped']}"] + [""] * (len(HEADERS) - 2))
            continue
        cold, second = result["cold"], result["cache_second_process"]
        cells = [
            name,
            f"{cold['import_lieax_s']:.2f} s",
            f"{cold['build_s']:.2f} s",
            str(cold["build"]["compilations"]),
            f"{cold['first']['compilations']} ({cold['first']['traces']} traces)",
            f"{cold['first']['xla_s']:.2f}",
            f"{cold['first_s']:.2f} s",
            f"{second['build_s'] + second['first_s']:.2f} s",
            f"{second['build']['compilations'] + second['first']['compilations']} of "
            f"{sum(second[p]['compilations'] + second[p]['cache_hits'] for p in ('build', 'first'))}",
            f"{second['build']['traces'] + second['first']['traces']} / {second['store_loads']}",
            f"{cold['warm_s']:.3f} s",
        ]
        rows.append(cells)
    return rows


def write_record(path, results, quick):
    """The table in the format of the documentation's benchmarks page (`_results.write`)."""
    title = "First call, fresh processes" + (" (--quick sizes)" if quick else "")
    notes = (
        "Compilations and XLA seconds from JAX's monitoring events; the second process runs with "
        "`lieax.enable_compilation_cache` on the directory the first filled."
    )
    tables = [{"title": title, "columns": HEADERS, "rows": table_rows(results)}]
    _results.write(path, "first_call", tables, notes=notes, raw=results)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", help=f"comma-separated workflows of {', '.join(WORKFLOWS)}")
    parser.add_argument("--quick", action="store_true", help="about tenfold smaller problems")
    parser.add_argument("--json", help="write the measurements to this file")
    parser.add_argument("--data", default=os.environ.get("LIEAX_DATA_DIR"), help="shared data")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--cache-dir", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        return child(args.child, args.quick, args.data, args.cache_dir)
    names = WORKFLOWS if not args.only else tuple(args.only.split(","))
    unknown = sorted(set(names) - set(WORKFLOWS))
    if unknown:
        parser.error(f"unknown workflows {unknown}; choose from {WORKFLOWS}")
    results = {}
    for name in names:
        results[name] = measure_workflow(name, args.quick, args.data)
        print(f"{name} done", file=sys.stderr, flush=True)
        if args.json:  # after each workflow, so that an interrupted run keeps what it measured
            write_record(args.json, results, args.quick)
    print(_results.markdown_table(HEADERS, table_rows(results)))
    return results


if __name__ == "__main__":
    main()
