"""A Markdown report tying a run's figures and numbers together."""

from __future__ import annotations

import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

from ._io import _timestamp, atomic_write_text, fojax_version


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table (floats with 4 significant digits)."""
    head = "| " + " | ".join(str(h) for h in headers) + " |"
    sep = "|" + "|".join("---" for _ in headers) + "|"
    body = ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in rows]
    return "\n".join([head, sep, *body])


def write_report(
    folder,
    *,
    title: str,
    summary: str = "",
    numbers: Mapping[str, Any] | None = None,
    tables: Mapping[str, tuple[Sequence[str], Sequence[Sequence[Any]]]] | None = None,
    figures: Mapping[str, Any] | None = None,
    files: Mapping[str, Any] | None = None,
    sections: Mapping[str, str] | None = None,
    filename: str = "report.md",
    overwrite: bool = False,
) -> pathlib.Path:
    """Write ``<folder>/report.md`` (atomically, never clobbering unless `overwrite`).

    **Arguments:**

    - `folder`: the results folder (figures and files are linked relative to it).
    - `title`: the report's heading.
    - `summary`: a paragraph under the title.
    - `numbers`: ``{name: value}`` listed as a two-column table ("Key numbers").
    - `tables`: ``{caption: (headers, rows)}``.
    - `figures`: ``{caption: png_path}``, embedded as images.
    - `files`: ``{description: path}`` of saved designs/metrics, listed as links.
    - `sections`: ``{heading: markdown text}`` appended verbatim.
    - `filename`, `overwrite`: the file name inside `folder` and whether to replace it.

    **Returns:** the path of the report.
    """
    folder = pathlib.Path(folder)

    def rel(p) -> str:
        return pathlib.Path(os.path.relpath(pathlib.Path(p), folder)).as_posix()

    out = [f"# {title}", "", f"_fojax {fojax_version()}, written {_timestamp()}_", ""]
    if summary:
        out += [summary.strip(), ""]
    if numbers:
        out += ["## Key numbers", "", markdown_table(["quantity", "value"], list(numbers.items())), ""]
    for caption, (headers, rows) in (tables or {}).items():
        out += [f"## {caption}", "", markdown_table(headers, rows), ""]
    if figures:
        out += ["## Figures", ""]
        for caption, p in figures.items():
            out += [f"### {caption}", "", f"![{caption}]({rel(p)})", ""]
    if files:
        out += ["## Files", ""]
        out += [f"- [{rel(p)}]({rel(p)}): {d}" for d, p in files.items()]
        out.append("")
    for heading, text in (sections or {}).items():
        out += [f"## {heading}", "", text.strip(), ""]
    return atomic_write_text(folder / filename, "\n".join(out), overwrite=overwrite)
