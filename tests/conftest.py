"""Test configuration: float64 by default (float32 tests pass `dtype=jnp.float32` explicitly).

The group registry, regimes, operations and tolerances live in `registry.py` next to this file.
"""

import gc
import importlib.metadata
import os

# The checks run on tiny matrices, so the test suite's time is almost all XLA compilation of many
# small jitted programs. Unoptimized code generation compiles them 3x faster (and gains nothing at
# these sizes); multithreaded BLAS only adds overhead (scipy.linalg.logm is 30x slower with
# threads on a loaded 2-core machine). Set LIEAX_TEST_XLA_OPTIMIZE=1 to test the optimized code
# generation instead.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
if os.environ.get("LIEAX_TEST_XLA_OPTIMIZE") != "1":
    _flags = ["--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true"]
    _jaxlib = tuple(int(part) for part in importlib.metadata.version("jaxlib").split(".")[:2])
    if (0, 10) <= _jaxlib < (0, 11):  # an unknown flag aborts the process: only where tested
        # one LLVM module per program instead of parallel codegen splits: the workers already
        # keep both cores busy, and the splits cost ~10% more compile CPU time
        _flags += [
            "--xla_cpu_use_fusion_emitters=false",
            "--xla_cpu_parallel_codegen_split_count=1",
        ]
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *_flags]).strip()
# JAX writes the Python traceback of every operation (up to 100 frames) into the program's
# locations, which only error dumps read; the innermost frame alone is 4-5% less XLA compile
# time (measured interleaved, December 2026). An environment variable, so that the subprocesses
# and notebook kernels of the tests inherit it.
os.environ.setdefault("JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", "false")
# Tracing and lowering allocate millions of short-lived objects: with Python's default threshold
# (700) the cyclic collector runs every few hundred of them and walks the young ones each time;
# 10,000 makes JAX's tracing 10% and lowering 15% faster (CPU time, interleaved processes, the
# jitted checks of test_jacobians). Collections still run (gc.collect() where a test needs one).
gc.set_threshold(10_000, 10, 10)

import jax

jax.config.update("jax_enable_x64", True)

import pytest
from registry import GROUP_IDS, GROUPS

# The longest files first, so that `-n auto --dist loadfile` (whole files to a worker, which keeps
# their compiled functions shared) ends with short files on both workers instead of one long file
# on one of them (longest-first scheduling; the per-file sums of `--durations=0` with -n 2 on the
# 2-core machine, December 2026; the files under 4 s follow in xdist's order). xdist's own order
# (files with the most tests first) is turned off in `pytest_configure`, or it would replace
# this one.
LONGEST_FIRST = (
    "test_jacobians.py",
    "test_notebooks.py",
    "test_properties.py",
    "test_factorgraph.py",
    "test_groups.py",
    "test_imu.py",
    "test_graph.py",
    "test_icp_search.py",
    "test_autodiff.py",
    "test_cameras.py",
    "test_retractions.py",
    "test_bearing_range.py",
    "test_lstsq.py",
    "test_icp_buckets.py",
    "test_examples.py",
    "test_factorgraph_buckets.py",
    "test_native_cholesky.py",
    "test_icp_derivatives.py",
    "test_native_kdtree.py",
    "test_gicp.py",
    "test_executable_store.py",
    "test_group_edges.py",
    "test_icp.py",
    "test_first_call.py",
    "test_sharding.py",
    "test_lstsq_scaling.py",
    "test_se23.py",
    "test_docs.py",
    "test_icp_invariance.py",
    "test_chain_agreement.py",
    "test_lstsq_faults.py",
    "test_align.py",
    "test_schur_gram.py",
    "test_conventions.py",
    "test_second_order.py",
    "test_imu_intervals.py",
    "test_ba.py",
    "test_sim3_s2.py",
    "test_lstsq_trust_region.py",
    "test_imu_preintegration.py",
)


def pytest_configure(config):
    """Keep `LONGEST_FIRST` under `--dist loadfile`: pytest-xdist (3.7+) otherwise reorders the
    files by their number of tests."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(items):
    """Reorder the collected tests by file, `LONGEST_FIRST` first (a stable sort: the order within
    a file, and of the other files, is kept)."""
    rank = {name: index for index, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(params=GROUPS, ids=GROUP_IDS)
def spec(request):
    """Each registered group in turn."""
    return request.param
