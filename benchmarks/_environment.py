"""How a benchmark's process is set up, in one place: its threads (before the libraries load) and
where the shared data is.

Thread pools read their settings when their libraries load, so a benchmark calls one of these at the
top of its module, before it imports JAX, NumPy or a peer:

- `one_core()`: one thread each, on one core (`pgo.py`, `ba.py`, `imu.py`, `cholesky.py`): the
  process pins itself to the last CPU it may use (`LIEAX_BENCH_PIN=0` leaves it unpinned), the BLAS
  and OpenMP pools get one thread (`OPENBLAS_NUM_THREADS`, `OMP_NUM_THREADS`, `MKL_NUM_THREADS`)
  and XLA's CPU client one intra-op thread (`XLA_FLAGS`), each only where the environment does not
  set it already. Pinned, lieax and GTSAM repeat within about 10% from run to run on a 2-core
  machine; unpinned, both keep worker threads that compete for the other core (see `pgo.py`).
- `passive_openmp()`: default threads, but OpenMP's idle threads wait passively (`icp.py`,
  `icp_batch.py`; `OMP_WAIT_POLICY=ACTIVE` overrides): with OpenMP's default policy, Open3D's idle
  threads slowed the lieax call that followed an Open3D call in an interleaved timing (LiDAR pair:
  15.2 ms against 12.6 ms alone), and passive waiting leaves Open3D's own time as it is alone (28.2
  against 28.8 ms).
- `library_defaults()`: a context in which the two above change nothing: `under_load.py` imports
  the other benchmarks' builders in it, so that every library runs with its default settings.

`add_data_dir(parser)` adds `--data-dir` (alias `--data`) to a benchmark's options: the shared data
folder (`shared/data`), by default `LIEAX_DATA_DIR`, else `../shared/data` (from the repository
root); a folder that does not exist is an error that names it.
"""

import contextlib
import os

_ONE_THREAD = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
}
_keep_defaults = False


def one_core():
    """Pin the process to one CPU (unless `LIEAX_BENCH_PIN=0`) and give every thread pool one
    thread (variables already set are kept); nothing inside `library_defaults()`."""
    if _keep_defaults:
        return
    if os.environ.get("LIEAX_BENCH_PIN", "1") != "0" and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {max(os.sched_getaffinity(0))})
    for name, value in _ONE_THREAD.items():
        os.environ.setdefault(name, value)


def passive_openmp():
    """Let OpenMP's idle threads sleep (`OMP_WAIT_POLICY=PASSIVE`, unless set); nothing inside
    `library_defaults()`."""
    if not _keep_defaults:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


@contextlib.contextmanager
def library_defaults():
    """A context in which `one_core` and `passive_openmp` change nothing (for importing another
    benchmark's module as a library)."""
    global _keep_defaults
    before, _keep_defaults = _keep_defaults, True
    try:
        yield
    finally:
        _keep_defaults = before


def add_data_dir(parser):
    """Add `--data-dir` (alias `--data`) to an `argparse` parser: the shared data folder."""

    def folder(path):
        if not os.path.isdir(path):
            raise ValueError(path)
        return path

    folder.__name__ = "data folder"  # argparse's error: "invalid data folder value: '...'"
    parser.add_argument(
        "--data-dir", "--data", dest="data_dir", type=folder,
        default=os.environ.get("LIEAX_DATA_DIR", "../shared/data"),
        help="the shared data folder (default: LIEAX_DATA_DIR, else ../shared/data)",
    )  # fmt: skip
