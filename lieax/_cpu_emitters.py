"""`jit`: `jax.jit` compiled with XLA's classic CPU fusion emitters, for the point-cloud programs
and the factor-graph loop.

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

The option is one of XLA's debug options, and an XLA that does not know it refuses to compile
("No such compile option"): the first program compiled with it finds that out, and from then on
the programs compile with XLA's defaults (`known()`; an empty program compiled as a probe cost
every process 0.1 s). Other backends do not use it (not measured on one here). JAX takes compile
options only for a program compiled on its own, not one staged into an enclosing `jit` or loop
(whose own options then apply) or transformed (`grad`, `vmap`, which may stage it): a call on
traced values, or made while a program is being staged, runs a plain `jax.jit`.
"""

import functools

import jax

from . import _executable_store as executable_store

CLASSIC_CPU_EMITTERS = {"xla_cpu_use_fusion_emitters": False}


_REFUSED = set()  # the options of `CLASSIC_CPU_EMITTERS` this XLA refused


def known() -> bool:
    """Whether this XLA compiles with `CLASSIC_CPU_EMITTERS`, as far as a compilation has told
    (True until one refuses them)."""
    return not _REFUSED.intersection(CLASSIC_CPU_EMITTERS)


def jit(fun=None, *, fingerprint=None, before_run=None, **jit_options):
    """`jax.jit(fun, **jit_options)` with `CLASSIC_CPU_EMITTERS` where this XLA knows them (as a
    decorator too, with or without arguments), its programs kept by `lieax._executable_store`
    while that is on (`fingerprint()` names what `fun` closes over, `before_run()` prepares
    what a loaded program reads: see `_executable_store.Programs`). The result's
    `_cache_size()` counts the compilations of both variants and the store's (the tests count
    recompilation)."""
    if fun is None:
        return functools.partial(jit, fingerprint=fingerprint, before_run=before_run, **jit_options)
    classic = jax.jit(fun, compiler_options=CLASSIC_CPU_EMITTERS, **jit_options)
    default = jax.jit(fun, **jit_options)
    options = dict(jit_options, compiler_options=CLASSIC_CPU_EMITTERS)
    stored = executable_store.Programs(classic, fun, options, fingerprint, before_run)
    refusals = []

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if executable_store.traced(args, kwargs) or not known():
            return default(*args, **kwargs)
        try:
            result = stored.run(args, kwargs)
            return classic(*args, **kwargs) if result is executable_store.NOT_SERVED else result
        except jax.errors.JaxRuntimeError as error:  # raised by the compilation, before any run
            refused = {o for o in CLASSIC_CPU_EMITTERS if f"compile option: '{o}'" in str(error)}
            if not refused:
                raise
            _REFUSED.update(refused)
            refusals.append(refused)
            return default(*args, **kwargs)

    # (JAX keeps an entry for the refused compilation too: not a program)
    call._cache_size = lambda: (
        classic._cache_size() - len(refusals) + default._cache_size() + stored.compiled
    )
    return call
