"""`child_output`: a test's Python program run in a fresh process (nothing compiled, no cache
opened), as the first-call and compilation-cache tests need."""

import os
import subprocess
import sys


def child_output(code, *args):
    """The standard output of `python -c code *args` on JAX's CPU backend; raises
    `subprocess.CalledProcessError` (with the child's stderr) when the child fails."""
    return subprocess.run(
        [sys.executable, "-c", code, *map(str, args)],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "JAX_PLATFORMS": "cpu"},
    ).stdout
