"""Every notebook runs from a clean kernel with small settings and finishes without an error, so
the notebooks cannot rot (STYLE point 10); the committed notebooks carry their outputs.

Each notebook runs in a fresh kernel of this interpreter (a kernelspec written to a temporary
folder, so a `python3` kernel installed elsewhere on the machine is never picked up), with
`LIEAX_NOTEBOOK_SMALL=1`, which the notebooks read to shrink their sizes, and with
`LIEAX_DATA_DIR` empty, so that they run on the data they generate (as on a machine without the
shared data; their committed outputs show the shared data, and the tests of `lieax.io`, `graph`
and `icp` read it), with `XDG_CACHE_HOME` in a temporary folder (the notebooks turn on the
compilation cache, which the notebooks of one test session share), and with this process's
environment otherwise. A notebook must finish within
`LIEAX_NOTEBOOK_TIME_LIMIT` seconds (default 120: the aim is under a minute on a 2-core CI
machine; the limit leaves room for a loaded one). Errors raised while figures are drawn (after a
cell has run) do not stop the execution, so the outputs are searched for errors as well.
"""

import json
import os
import pathlib
import sys
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
REQUIRED = [
    "01_groups_and_tangents",
    "02_manifold_jacobians",
    "03_batch_icp",
    "04_pose_graphs",
    "05_differentiable_icp",
    "06_factor_graphs",
    "07_inertial_navigation",
]
TIME_LIMIT = float(os.environ.get("LIEAX_NOTEBOOK_TIME_LIMIT", "120"))
MAX_BYTES = 1_000_000
KERNEL = "lieax-test"


@pytest.fixture(scope="module")
def kernel_specs(tmp_path_factory):
    """A folder with one kernelspec: this interpreter, small settings."""
    folder = tmp_path_factory.mktemp("kernels")
    cache = tmp_path_factory.mktemp("cache")
    (folder / KERNEL).mkdir()
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "lieax tests (this interpreter)",
        "language": "python",
        # the notebooks' `enable_compilation_cache()` writes here, not in the user's home
        "env": {"LIEAX_NOTEBOOK_SMALL": "1", "LIEAX_DATA_DIR": "", "XDG_CACHE_HOME": str(cache)},
    }
    (folder / KERNEL / "kernel.json").write_text(json.dumps(spec))
    return folder


def error_outputs(notebook):
    """`(cell index, ename: evalue)` of every error output."""
    return [
        (index, f"{output.get('ename')}: {output.get('evalue')}")
        for index, cell in enumerate(notebook.cells)
        for output in cell.get("outputs", [])
        if output.get("output_type") == "error"
    ]


def test_every_notebook_is_there():
    assert [path.stem for path in NOTEBOOKS] == REQUIRED


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda path: path.stem)
def test_notebook_is_committed_with_outputs(path):
    import nbformat

    assert path.stat().st_size < MAX_BYTES, f"{path.name} is {path.stat().st_size} bytes"
    notebook = nbformat.read(path, as_version=4)
    first = notebook.cells[0]
    assert first.cell_type == "markdown" and first.source.startswith("# "), "opens with a title"
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    counts = [cell.get("execution_count") for cell in code]
    assert counts == list(range(1, len(code) + 1)), f"not executed top to bottom: {counts}"
    assert not error_outputs(notebook)
    assert any("image/png" in output.get("data", {}) for cell in code for output in cell.outputs)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda path: path.stem)
def test_notebook_runs(path, kernel_specs):
    # (imported here, not while pytest collects the file on every worker)
    import nbclient
    import nbformat
    from jupyter_client import KernelManager
    from jupyter_client.kernelspec import KernelSpecManager

    notebook = nbformat.read(path, as_version=4)
    manager = KernelManager(
        kernel_name=KERNEL, kernel_spec_manager=KernelSpecManager(kernel_dirs=[str(kernel_specs)])
    )
    client = nbclient.NotebookClient(
        notebook, km=manager, timeout=TIME_LIMIT, resources={"metadata": {"path": str(path.parent)}}
    )
    start = time.perf_counter()
    client.execute()
    elapsed = time.perf_counter() - start
    assert not error_outputs(notebook)
    assert elapsed < TIME_LIMIT, f"{path.name} took {elapsed:.0f} s"
