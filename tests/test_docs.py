"""The documentation site builds strictly from the repository, offline, and documents the public API;
its Python examples run as written; the README stays a short front page.

`mkdocs build --strict` turns every warning into an error: a broken link between pages, a missing
notebook, an API reference to a name that does not exist, a malformed benchmark record.
"""

import importlib
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
API_PAGES = {  # module -> the API page that documents it
    "groups": "groups",
    "autodiff": "autodiff",
    "lstsq": "lstsq",
    "factorgraph": "factorgraph",
    "graph": "graph",
    "cameras": "cameras",
    "ba": "ba",
    "imu": "imu",
    "icp": "icp",
    "io": "io",
    "conventions": "conventions",
    "retractions": "misc",
    "optax": "misc",
    "sharding": "misc",
    "viz": "misc",
}


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site, built once for this file's tests into a temporary directory."""
    pytest.importorskip("mkdocs")
    site_dir = tmp_path_factory.mktemp("site")
    environment = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site_dir)]
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, env=environment)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-4000:]
    return site_dir


def test_every_public_function_and_class_has_an_api_entry(site):
    missing = []
    for module_name, page in API_PAGES.items():
        module = importlib.import_module(f"lieax.{module_name}")
        html = (site / "api" / page / "index.html").read_text(encoding="utf-8")
        documented = set(re.findall(r'id="(lieax\.[A-Za-z0-9_.]+)"', html))
        for name in module.__all__:
            documentable = callable(getattr(module, name)) or isinstance(
                getattr(module, name), type
            )
            if documentable and f"lieax.{module_name}.{name}" not in documented:
                missing.append(f"lieax.{module_name}.{name}")
    assert not missing, f"public names without an API entry: {missing}"


def test_every_notebook_is_rendered(site):
    notebooks = sorted(path.stem for path in (ROOT / "notebooks").glob("*.ipynb"))
    assert notebooks
    for name in notebooks:
        assert (site / "notebooks" / name / "index.html").is_file(), name


def test_docs_python_examples_run_as_written():
    """Every ```python block of the pages runs in a fresh namespace (the README's run in
    test_readme.py)."""
    blocks = []
    for page in sorted(DOCS.glob("*.md")):
        text = page.read_text(encoding="utf-8")
        for number, body in enumerate(re.findall(r"^```python\n(.*?)^```", text, re.S | re.M)):
            blocks.append((f"{page}:python-example-{number + 1}", body))
    assert blocks
    for name, source in blocks:
        exec(compile(source, name, "exec"), {"__name__": "docs_example"})


def test_readme_is_a_short_front_page():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text) <= 8000, f"README.md has {len(text)} characters; the manual is docs/"
    for link in re.findall(r"\]\((docs/[^)#]+)", text):
        assert (ROOT / link).exists(), f"README links to missing {link}"
