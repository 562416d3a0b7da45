"""`jit`: `jax.jit` compiled with XLA's classic CPU fusion emitters, for the point-cloud programs
and the factor-graph loop, and with single-threaded dots for the factor-graph loop.

XLA's CPU backend emits each fused kernel through its newer MLIR "fusion emitters" by default.
The point-cloud programs (the ICP loop, the normals, the GICP covariances) are long chains of
elementwise work and variadic reductions over the rows; with the classic emitters
(`xla_cpu_use_fusion_emitters=False`) XLA compiles them in 13-36% less time, and the ICP loop
runs 2-9% faster, the others within noise (jaxlib 0.10.2, 2-core x86-64, the bunny, LiDAR and
Kinect scans; `benchmarks/cpu_emitters.py` measures both in one process). The first
point-to-plane call on a 25k-point LiDAR pair, target normals estimated, took 2.2-2.3 s against
2.7-3.0 s without them (fresh processes, alternating). The option is set per program, not for
the process.

The factor-graph loop (`lieax.factorgraph`'s `solve`, and `lieax.graph.optimize`, which runs it)
and its marginal-covariance program use them too: their first calls are dominated by XLA's
compilation, which the classic emitters cut by a third to a half, against a warm solve within
about 10% either way (issue 30; measured 2026-12-04 on the 2-core machine under load 6-8,
compile time, then the warm median of the two programs interleaved in one process,
classic / default: the docs' five-pose factor graph 1.8-2.1 / 3.8 s; intel 2.8 / 4.1 s and
1.11x; smallGrid3D 6.0 / 9.1 s and 0.84x; sphere2500 6.6 / 8.9 s and 1.07x; tinyGrid3D 4.3 /
8.4 s and 1.11x (0.4 ms); M3500 3.7 / 4.7 s and 1.03x; Ladybug-49 bundle adjustment
1.6 / 2.6 s, 0.15 s both. An earlier measurement, on the pose-graph loop of that time, had
found tinyGrid3D 0.78 -> 1.01x GTSAM's time and sphere2500 0.66 -> 0.74x).

The factor-graph loop also computes its dots on the thread that runs the program
(`SOLVER_LOOP_OPTIONS`: `xla_cpu_multi_thread_eigen=False`). Its dots are small (per-factor
Jacobian products, 3x3 to 15x15 blocks, batched), and XLA's multi-threaded Eigen path hands each
to its intra-op pool: on the 2-core machine the loop ran, warm, in one process against the same
loop with XLA's default (2026-12-05, medians of 5 interleaved rounds), tinyGrid3D 281 -> 226 us
pinned and 311 -> 239 us unpinned, smallGrid3D 7.69 -> 6.32 ms and 8.58 -> 7.32 ms, sphere2500
161 -> 139 ms and 155 -> 144 ms, intel 5.19 -> 5.17 ms and 5.98 -> 6.07 ms; `under_load.py`'s
bundle adjustment at Ladybug-49 size 187-200 -> 159-195 ms idle and the IMU smoother 61-96 ->
54-58 ms (three processes each, alternating). The point-cloud programs measured the same either
way (`under_load.py`'s ICP and GICP rows within noise), so they keep XLA's default. The dense and
multifrontal factorizations call LAPACK, whose threads `lieax._threads` sets, not Eigen.

The options are XLA's debug options, and an XLA that does not know one refuses to compile
("No such compile option"): the first program compiled with it finds that out, and from then on
the programs that ask for it compile with XLA's defaults (`known()` tells for the classic
emitters; an empty program compiled as a probe cost every process 0.1 s). Other backends do not
use them (not measured on one here). JAX takes compile options only for a program compiled on its
own, not one staged into an enclosing `jit` or loop (whose own options then apply) or transformed
(`grad`, `vmap`, which may stage it): a call on traced values, or made while a program is being
staged, runs a plain `jax.jit`.
"""

import functools

import jax

from . import _executable_store as executable_store

CLASSIC_CPU_EMITTERS = {"xla_cpu_use_fusion_emitters": False}
SOLVER_LOOP_OPTIONS = {**CLASSIC_CPU_EMITTERS, "xla_cpu_multi_thread_eigen": False}


_REFUSED = set()  # the options this XLA refused


def known() -> bool:
    """Whether this XLA compiles with `CLASSIC_CPU_EMITTERS`, as far as a compilation has told
    (True until one refuses them)."""
    return not _REFUSED.intersection(CLASSIC_CPU_EMITTERS)


def jit(fun=None, *, options=None, fingerprint=None, before_run=None, **jit_options):
    """`jax.jit(fun, **jit_options)` compiled with XLA's `options` (default
    `CLASSIC_CPU_EMITTERS`) where this XLA knows them all, else with XLA's defaults (as a
    decorator too, with or without arguments), its programs kept by `lieax._executable_store`
    while that is on (`fingerprint()` names what `fun` closes over, `before_run()` prepares
    what a loaded program reads: see `_executable_store.Programs`). The result's
    `_cache_size()` counts the compilations of both variants and the store's (the tests count
    recompilation)."""
    if fun is None:
        return functools.partial(
            jit, options=options, fingerprint=fingerprint, before_run=before_run, **jit_options
        )
    options = dict(CLASSIC_CPU_EMITTERS if options is None else options)
    chosen = jax.jit(fun, compiler_options=options, **jit_options)
    default = jax.jit(fun, **jit_options)
    stored = executable_store.Programs(
        chosen, fun, dict(jit_options, compiler_options=options), fingerprint, before_run
    )
    refusals = []

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if executable_store.traced(args, kwargs) or not known() or _REFUSED.intersection(options):
            return default(*args, **kwargs)
        try:
            result = stored.run(args, kwargs)
            return chosen(*args, **kwargs) if result is executable_store.NOT_SERVED else result
        except jax.errors.JaxRuntimeError as error:  # raised by the compilation, before any run
            refused = {o for o in options if f"compile option: '{o}'" in str(error)}
            if not refused:
                raise
            _REFUSED.update(refused)
            refusals.append(refused)
            return default(*args, **kwargs)

    # (JAX keeps an entry for the refused compilation too: not a program)
    call._cache_size = lambda: (
        chosen._cache_size() - len(refusals) + default._cache_size() + stored.compiled
    )
    return call
