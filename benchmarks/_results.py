"""The one format in which benchmarks record their tables for the documentation site.

A benchmark run with `--json PATH` writes one JSON object: the benchmark's name, the command, when
and where it ran, and its tables (a title, column names, rows of cells already formatted as the
printed table shows them, and notes). `docs/_hooks/benchmarks.py` renders every file of
`benchmarks/results/` into the site's benchmarks page, so the published tables are the measured
ones, never pasted by hand.
"""

import datetime
import json
import os
import platform
import sys


def markdown_table(headers, rows):
    """A GitHub markdown table: the first column left-aligned, the others right-aligned (cells
    converted by `str`). Here, not in `_timing`, so that `first_call.py` prints tables without
    importing JAX before it times that import."""
    lines = [
        "| " + " | ".join(headers) + " |",
        "|" + "|".join(["---"] + ["---:"] * (len(headers) - 1)) + "|",
    ]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def machine():
    """A one-line description of this machine: processor, cores, Python and JAX versions."""
    import jax

    return (
        f"{platform.machine()} {platform.processor() or platform.system()}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()}, jax {jax.__version__}, "
        f"{jax.default_backend()}"
    )


def write(path, benchmark, tables, notes="", raw=None):
    """Write `tables` (a list of dicts with `title`, `columns`, `rows` and optional `notes`) of the
    benchmark named `benchmark` to `path` as JSON, with the command line, the UTC time,
    `machine()` and, under `raw`, the unformatted measurements (any JSON value)."""
    for table in tables:
        widths = {len(row) for row in table["rows"]}
        if widths - {len(table["columns"])}:
            raise ValueError(
                f"table {table['title']!r}: rows of {sorted(widths)} cells for "
                f"{len(table['columns'])} columns."
            )
    record = {
        "benchmark": benchmark,
        "command": " ".join(["python", *sys.argv]),
        "utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M"),
        "machine": machine(),
        "notes": notes,
        "tables": tables,
        "raw": raw,
    }
    with open(path, "w", encoding="utf-8") as file:
        json.dump(record, file, indent=1, ensure_ascii=False)
        file.write("\n")
