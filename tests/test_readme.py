"""The README cannot rot: its Python examples run as written, its Quick start block holds exactly
the two commands CI runs (`.ci/run` reads them with `quick_start_commands`), and the demo script
the first command names runs.

Only the standard library is imported at module level, so that `.ci/run` can import
`quick_start_commands` with a bare `python3` before anything is installed.
"""

import importlib.util
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parent.parent
README = ROOT / "README.md"


def _code_blocks(text):
    """`(language, body)` of every fenced code block, in order."""
    return re.findall(r"^```(\w*)\n(.*?)^```", text, flags=re.S | re.M)


def quick_start_commands(readme=README):
    """The commands of the first code block of the `## Quick start` section (comments and blank
    lines dropped)."""
    text = pathlib.Path(readme).read_text(encoding="utf-8")
    match = re.search(r"^## Quick start\n(.*?)(?=^## |\Z)", text, flags=re.S | re.M)
    if match is None:
        raise ValueError(f"{readme} has no '## Quick start' section.")
    blocks = _code_blocks(match.group(1))
    if not blocks:
        raise ValueError(f"{readme}'s Quick start section has no code block.")
    lines = (line.strip() for line in blocks[0][1].splitlines())
    return [line for line in lines if line and not line.startswith("#")]


def python_examples(readme=README):
    """The ```python blocks of the README, in order."""
    text = pathlib.Path(readme).read_text(encoding="utf-8")
    blocks = [body for language, body in _code_blocks(text) if language == "python"]
    if not blocks:
        raise ValueError(f"{readme} has no python code block.")
    return blocks


def test_quick_start_has_the_demo_and_the_test_command():
    commands = quick_start_commands()
    assert len(commands) == 2, commands
    demo, tests = commands
    assert demo.startswith("pip install -e . && python examples/"), demo
    assert (ROOT / demo.split("python ", 1)[1].split()[0]).is_file(), demo
    assert '".[test]"' in tests and "pytest" in tests, tests


def test_readme_examples_run_as_written():
    """Every Python block (the first example) runs in a fresh namespace."""
    for number, source in enumerate(python_examples(), 1):
        name = f"{README}:python-example-{number}"
        exec(compile(source, name, "exec"), {"__name__": "readme_example"})


def test_demo_script_runs():
    """The demo's `main()` at a small size: the registration recovers the generated motion."""
    demo = quick_start_commands()[0].split("python ", 1)[1].split()[0]
    spec = importlib.util.spec_from_file_location("readme_demo", ROOT / demo)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.__doc__, "the demo needs a module docstring"
    summary = module.main(["--points", "1000"])
    assert summary["rotation_error_deg"] < 0.5
    assert summary["translation_error"] < 0.01
