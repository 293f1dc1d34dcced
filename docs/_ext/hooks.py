"""MkDocs hooks of the rigidjax site.

- The command-line reference (cli.md) is generated from the parsers of the ``rigidjax`` command:
  each ``<!-- cli-help: COMMAND -->`` marker becomes that command's ``--help`` text.
- Each notebook of notebooks/ becomes a page (its markdown and code cells; the outputs appear when
  it is run) and is offered for download beside it.
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
    """The notebook as markdown: markdown cells as they are, code cells as python blocks."""
    cells = json.loads(path.read_text())["cells"]
    parts = []
    for i, cell in enumerate(cells):
        source = "".join(cell["source"]).rstrip()
        if not source:
            continue
        if cell["cell_type"] == "markdown":
            parts.append(source)
            if i == 0:  # after the title cell
                parts.append(
                    f'!!! note "Run it"\n    This page shows the notebook\'s text and code; its figures and '
                    f"numbers appear when you run it: [download {path.name}]({path.name}), then "
                    '`pip install -e ".[notebooks]"` and run all cells in Jupyter. The tests execute '
                    "every notebook, and its `assert`s check the numbers it shows."
                )
        elif cell["cell_type"] == "code":
            parts.append(f"```python\n{source}\n```")
    return "\n\n".join(parts) + "\n"


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
