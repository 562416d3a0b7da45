"""The code passes the repository's ruff rules (pyproject.toml: pyflakes, pycodestyle, isort,
pyupgrade, bugbear) and is `ruff format`ted, so style never needs a review comment."""

import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
PATHS = ["lieax", "tests", "benchmarks", "examples"]


def _ruff(*args):
    """`ruff` of the test extra (`python -m ruff` runs the binary its wheel ships)."""
    command = [sys.executable, "-m", "ruff", *args, *PATHS]
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True)


def test_ruff_check():
    result = _ruff("check", "--no-cache")
    assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_format():
    result = _ruff("format", "--check", "--no-cache")
    assert result.returncode == 0, result.stdout + result.stderr
