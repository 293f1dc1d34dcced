"""The documentation site: `mkdocs build --strict` passes (no broken link, no missing API object, no
warning of any kind), and the API reference documents every public name, each with a docstring.

The docs packages are part of the test extra, so these tests run wherever the tests run."""

from __future__ import annotations

import importlib
import os
import pathlib
import re
import subprocess
import sys

import griffe
import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
NAMESPACES = (
    "rigidjax",
    "rigidjax.kinematics",
    "rigidjax.elliptic",
    "rigidjax.solvers",
    "rigidjax.convert",
    "rigidjax.plot",
)
DIRECTIVE = re.compile(r"^:::\s+(\S+)", re.MULTILINE)


def _public_names():
    return [(ns, name) for ns in NAMESPACES for name in importlib.import_module(ns).__all__]


def _api_pages():
    return {page: page.read_text() for page in sorted((DOCS / "api").glob("*.md"))}


@pytest.mark.slow  # a full mkdocs build (~10 s); the pages' own checks stay in the fast tier
def test_site_builds_strictly_without_warnings(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    log = result.stdout + result.stderr
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{log}"
    warnings = [line for line in log.splitlines() if re.match(r"\s*(WARNING|ERROR)\b", line)]
    assert not warnings, "\n".join(warnings)
    for page in ("index.html", "conventions/index.html", "api/simulate/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    html = (tmp_path / "site" / "api" / "simulate" / "index.html").read_text()
    assert "rigidjax.simulate" in html and "Arguments:" in html  # the docstring was rendered
    assert ":func:" not in html and ":class:" not in html  # Sphinx roles became links or code
    cli = (tmp_path / "site" / "cli" / "index.html").read_text()
    for command in ("simulate", "fit", "bench"):  # the help texts, generated from the parsers
        assert f"usage: rigidjax {command}" in cli, command
    for notebook in (ROOT / "notebooks").glob("*.ipynb"):  # each notebook as a page, and its file
        assert (tmp_path / "site" / "notebooks" / notebook.stem / "index.html").is_file(), notebook.name
        assert (tmp_path / "site" / "notebooks" / notebook.name).is_file(), notebook.name


def test_every_public_name_has_a_reference_entry():
    """`::: namespace.name` on an API page, or, for a namespace that re-exports a top-level function
    (rigidjax.kinematics.quat_multiply is rigidjax.quat_multiply), the top-level entry and the name
    on the namespace's page."""
    pages = _api_pages()
    directives = {path: page for page, text in pages.items() for path in DIRECTIVE.findall(text)}
    missing = []
    for ns, name in _public_names():
        path = f"{ns}.{name}"
        if path in directives:
            continue
        obj = getattr(importlib.import_module(ns), name)
        same = [p for p in directives if p.startswith("rigidjax.") and _lookup(p) is obj]
        namespace_page = [page for page, text in pages.items() if f"`{ns}`" in text and f"`{name}`" in text]
        if not (same and namespace_page):
            missing.append(path)
    assert not missing, f"public names without an API reference entry: {missing}"


def test_the_reference_overview_lists_the_whole_top_level():
    """docs/api/index.md says its table holds ``rj.__all__``: it left out Gyrostat, use_cpu_cores and
    use_compilation_cache."""
    import rigidjax

    table = [line for line in (DOCS / "api" / "index.md").read_text().splitlines() if line.startswith("| [")]
    listed = set(re.findall(r"`(\w+)`", "\n".join(table)))
    assert listed == set(rigidjax.__all__), (set(rigidjax.__all__) - listed, listed - set(rigidjax.__all__))


def test_every_reference_entry_is_a_public_name():
    public = {f"{ns}.{name}" for ns, name in _public_names()} | set(NAMESPACES)
    stray = [p for text in _api_pages().values() for p in DIRECTIVE.findall(text) if p not in public]
    assert not stray, f"API pages document names that are not public: {stray}"


@pytest.fixture(scope="module")
def package():
    return griffe.load("rigidjax", search_paths=[str(ROOT)], resolve_aliases=True)


def test_every_public_name_has_a_docstring(package):
    undocumented = []
    for ns, name in _public_names():
        path = f"{ns}.{name}"[len("rigidjax.") :]
        obj = package[path]
        docstring = obj.docstring.value.strip() if obj.docstring else ""
        if not docstring:
            undocumented.append(f"{ns}.{name}")
    assert not undocumented, f"public names without a docstring: {undocumented}"


def _lookup(path):
    module, _, name = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return None


def test_extremes_page_shows_the_recorded_table(tmp_path):
    """benchmarks/extremes_table.py writes its table between the markers of docs/extremes.md; the page
    shows the table the benchmarks last recorded (benchmarks/results/extremes.md)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import extremes_table
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    assert extremes_table.PAGE == DOCS / "extremes.md"
    text = extremes_table.PAGE.read_text()
    recorded = (ROOT / "benchmarks" / "results" / "extremes.md").read_text()
    assert f"{extremes_table.BEGIN}\n{recorded}{extremes_table.END}" in text
    page = tmp_path / "page.md"
    page.write_text(f"head\n{extremes_table.BEGIN}\nold\n{extremes_table.END}\ntail\n")
    assert extremes_table.insert_table("| new |\n", page)
    assert page.read_text() == f"head\n{extremes_table.BEGIN}\n| new |\n{extremes_table.END}\ntail\n"
    page.write_text("no markers")
    assert not extremes_table.insert_table("| new |\n", page)


def test_the_extremes_counted_in_the_readme_and_the_overview_are_the_tables():
    """The README and the docs' overview count the table's rows and those with a measured value
    and a bound: they said 170 of 192 after the table had grown to 173."""
    rows = [line for line in (DOCS / "extremes.md").read_text().splitlines() if line.startswith("| ")]
    cells = [[cell.strip() for cell in row.strip().strip("|").split("|")] for row in rows[1:]]
    bounded = sum(1 for row in cells if row[3] and row[4])
    assert rows[0].startswith("| Extreme |") and len(cells) > 100
    for page in (ROOT / "README.md", DOCS / "index.md"):
        text = " ".join(page.read_text().split())
        assert f"{len(cells)} numerical extremes, {bounded} measured against a tested bound" in text or (
            f"a table of {len(cells)} extremes" in text
            and f"{bounded} measured against a tested bound" in text
        ), page


def test_readme_is_short_and_its_links_resolve():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.encode()) <= 10_000, f"README.md is {len(readme.encode())} bytes; keep it under 10 KB"
    for command in (
        'pip install -e ".[plot]" && rigidjax simulate',
        'pip install -e ".[test]" && python -m pytest -q',
        'python -m pytest -m "not slow"',
    ):
        assert command in readme, command
    links = [link for link in re.findall(r"\]\(([^)#\s]+)", readme) if "://" not in link]
    assert links
    broken = [link for link in links if not (ROOT / link).exists()]
    assert not broken, f"README.md links to missing files: {broken}"


def test_notebook_pages_show_the_outputs_of_an_executed_copy(tmp_path, monkeypatch):
    """A notebook's page shows printed text and figures from its executed copy (written by the
    notebook tests), and only the code when the copy is missing or older than the notebook."""
    import base64
    import importlib.util
    import json

    spec = importlib.util.spec_from_file_location("rigidjax_docs_hooks", DOCS / "_ext" / "hooks.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    monkeypatch.setattr(hooks, "EXECUTED", tmp_path / "executed")
    (tmp_path / "executed").mkdir()
    png = base64.b64encode(b"\x89PNG\r\n\x1a\n not really an image").decode()

    def notebook(outputs):
        cells = [
            {"cell_type": "markdown", "metadata": {}, "source": ["# Title"]},
            {
                "cell_type": "code",
                "metadata": {},
                "execution_count": None,
                "source": ["print(1)"],
                "outputs": outputs,
            },
        ]
        return json.dumps({"cells": cells, "metadata": {}, "nbformat": 4, "nbformat_minor": 5})

    source = tmp_path / "demo.ipynb"
    source.write_text(notebook([]))
    assert "```text" not in hooks.notebook_page(source) and "appear when you run it" in hooks.notebook_page(
        source
    )
    executed = tmp_path / "executed" / "demo.ipynb"
    executed.write_text(
        notebook(
            [
                {"output_type": "stream", "name": "stdout", "text": ["period 304.2 days\n"]},
                {
                    "output_type": "display_data",
                    "metadata": {},
                    "data": {"image/png": png, "text/plain": ["<Figure>"]},
                },
            ]
        )
    )
    os.utime(executed, (source.stat().st_mtime + 10,) * 2)
    page = hooks.notebook_page(source)
    assert "```python\nprint(1)\n```" in page
    assert "```text\nperiod 304.2 days\n```" in page
    assert f'src="data:image/png;base64,{png}"' in page and "<Figure>" not in page
    os.utime(executed, (source.stat().st_mtime - 10,) * 2)  # stale: the notebook changed since
    assert "period 304.2" not in hooks.notebook_page(source)
