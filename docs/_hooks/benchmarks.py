"""MkDocs hook: the benchmarks page's tables come from the JSON files the benchmarks write.

`benchmarks/results/*.json` (written by `benchmarks/_results.py`'s `write`, one file per benchmark)
replace the `<!-- benchmark results -->` marker of `benchmarks.md`, one section per file, in the
order of the file names. A malformed file fails the build, naming the file.
"""

import json
import pathlib

RESULTS = pathlib.Path(__file__).resolve().parents[2] / "benchmarks" / "results"
MARKER = "<!-- benchmark results -->"


def _table(columns, rows):
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def _section(path):
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        parts = [
            f"## `{record['benchmark']}`",
            f"`{record['command']}`, {record['utc']} UTC, {record['machine']}.",
        ]
        if record.get("notes"):
            parts.append(record["notes"])
        for table in record["tables"]:
            parts.append(f"**{table['title']}**")
            parts.append(_table(table["columns"], table["rows"]))
            if table.get("notes"):
                parts.append(table["notes"])
    except (KeyError, TypeError, ValueError) as error:
        raise ValueError(f"{path}: not a benchmark record ({error!r})") from error
    return "\n\n".join(parts)


def on_page_markdown(markdown, page, **kwargs):
    if page.file.src_uri != "benchmarks.md":
        return markdown
    files = sorted(RESULTS.glob("*.json"))
    sections = [_section(path) for path in files] or ["No results recorded yet."]
    return markdown.replace(MARKER, "\n\n".join(sections))
