"""MkDocs hooks of the rigidjax site.

- The command-line reference (cli.md) is generated from the parsers of the ``rigidjax`` command:
  each ``<!-- cli-help: COMMAND -->`` marker becomes that command's ``--help`` text.
- Each notebook of notebooks/ becomes a page (its markdown and code cells) and is offered for
  download beside it. Where the tests have executed it (docs/_executed/, written by
  tests/test_notebooks.py), the page shows its outputs too: printed text and figures.
- Figures made by the benchmarks (benchmarks/results/) are copied into the site under figures/.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re

from mkdocs.structure.files import File

ROOT = pathlib.Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "notebooks"
EXECUTED = ROOT / "docs" / "_executed"
FIGURES = {"figures/work_precision.png": ROOT / "benchmarks" / "results" / "work_precision.png"}
CLI_MARKER = re.compile(r"<!-- cli-help: ?([a-z ]*?) ?-->")


def on_files(files, config):
    for dest, src in FIGURES.items():
        files.append(File.generated(config, dest, abs_src_path=str(src)))
    for notebook in sorted(NOTEBOOKS.glob("*.ipynb")):
        files.append(File.generated(config, f"notebooks/{notebook.name}", abs_src_path=str(notebook)))
        files.append(File.generated(config, f"notebooks/{notebook.stem}.md", content=notebook_page(notebook)))
    return files


def notebook_page(path: pathlib.Path) -> str:
    """The notebook as markdown: markdown cells as they are, code cells as python blocks, and after
    each code cell its outputs when an executed copy newer than the notebook exists."""
    executed = EXECUTED / path.name
    with_outputs = executed.is_file() and executed.stat().st_mtime >= path.stat().st_mtime
    cells = json.loads((executed if with_outputs else path).read_text())["cells"]
    parts = []
    for i, cell in enumerate(cells):
        source = "".join(cell["source"]).rstrip()
        if not source:
            continue
        if cell["cell_type"] == "markdown":
            parts.append(source)
            if i == 0:  # after the title cell
                parts.append(_run_note(path, with_outputs))
        elif cell["cell_type"] == "code":
            parts.append(f"```python\n{source}\n```")
            parts.extend(_outputs(cell.get("outputs", [])))
    return "\n\n".join(parts) + "\n"


def _run_note(path: pathlib.Path, with_outputs: bool) -> str:
    download = f'[download {path.name}]({path.name}), then `pip install -e ".[notebooks]"` and run all cells'
    if with_outputs:
        return (
            f'!!! note "Run it"\n    The outputs below are from the test run that executed this notebook. '
            f"To run it yourself: {download} in Jupyter. Its `assert`s check the numbers it shows."
        )
    return (
        f'!!! note "Run it"\n    This page shows the notebook\'s text and code; its figures and numbers '
        f"appear when you run it: {download} in Jupyter. The tests execute every notebook, and its "
        "`assert`s check the numbers it shows."
    )


def _outputs(outputs: list[dict]) -> list[str]:
    """Printed text as a plain block, figures as embedded PNG images; other kinds are left out."""
    parts = []
    for out in outputs:
        data = out.get("data", {})
        if out.get("output_type") == "stream" and out.get("name") == "stdout":
            text = "".join(out["text"]).rstrip()
        elif "image/png" in data:
            png = "".join(data["image/png"]).replace("\n", "")
            parts.append(f'<img alt="figure" src="data:image/png;base64,{png}">')
            continue
        elif "text/plain" in data and out.get("output_type") == "execute_result":
            text = "".join(data["text/plain"]).rstrip()
        else:
            continue
        if text:
            parts.append("```text\n" + text.replace("```", "` ` `") + "\n```")
    return parts


def cli_help(command: str) -> str:
    from rigidjax._cli.parser import build_parser

    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal width: a fixed width for the page
    parser = build_parser()
    if not command:
        return parser.format_help()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command].format_help()


def on_page_markdown(markdown, page, config, files):
    if page.file.src_uri != "cli.md":
        return markdown
    return CLI_MARKER.sub(lambda m: f"```text\n{cli_help(m.group(1).strip()).rstrip()}\n```", markdown)
