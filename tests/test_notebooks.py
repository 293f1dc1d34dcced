"""Executes every notebook in notebooks/ top to bottom, so that none can rot.

Each ``notebooks/*.ipynb`` is one test case (new notebooks are picked up by name). The kernel runs
in a separate process with the interpreter that runs pytest: a kernelspec named ``python3`` that
points at ``sys.executable`` is written to a temporary ``JUPYTER_PATH`` directory, which takes
precedence over any ``python3`` kernel installed elsewhere on the machine. A cell that raises (the
notebooks ``assert`` the numbers they show) fails the test. An executed notebook is kept, with its
outputs, in ``docs/_executed/`` (not committed): the documentation site shows those outputs. The
committed notebooks must carry no outputs, and notebooks/README.md must have a line for each.
nbclient, nbformat and ipykernel are in the ``test`` extra: a missing one is an error here, not a
skip.
"""

import json
import sys
from pathlib import Path

import nbclient
import nbformat
import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parent.parent / "notebooks"
# Executed copies, with their outputs, for the documentation site (docs/_ext/hooks.py renders them).
EXECUTED_DIR = Path(__file__).resolve().parent.parent / "docs" / "_executed"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
CELL_TIMEOUT_S = 300


@pytest.fixture
def python3_kernel(tmp_path, monkeypatch):
    """A ``python3`` kernelspec for this interpreter, found before any other ``python3`` kernel."""
    spec_dir = tmp_path / "jupyter" / "kernels" / "python3"
    spec_dir.mkdir(parents=True)
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (rigidjax tests)",
        "language": "python",
    }
    (spec_dir / "kernel.json").write_text(json.dumps(spec))
    monkeypatch.setenv("JUPYTER_PATH", str(tmp_path / "jupyter"))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    return "python3"


def test_kernel_is_this_interpreter(python3_kernel):
    """The notebooks run with the interpreter (and so the environment) that runs pytest."""
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell("import sys; print(sys.prefix)")])
    nbclient.NotebookClient(nb, kernel_name=python3_kernel, timeout=CELL_TIMEOUT_S).execute()
    printed = nb.cells[0].outputs[0]["text"].strip()
    assert printed == sys.prefix  # the same virtual environment (executables may be symlinks)


def test_notebooks_exist():
    assert NOTEBOOKS, f"no notebooks found in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    dirty = [
        i
        for i, cell in enumerate(nb.cells)
        if cell.cell_type == "code" and (cell.get("outputs") or cell.get("execution_count") is not None)
    ]
    assert not dirty, f"{path.name}: cells {dirty} carry outputs or execution counts; strip them"
    assert nb.metadata.get("kernelspec", {}).get("name") == "python3", path.name


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_listed_in_readme(path):
    readme = (NOTEBOOK_DIR / "README.md").read_text()
    assert f"({path.name})" in readme, f"notebooks/README.md has no link line for {path.name}"


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs(path, python3_kernel):
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb,
        kernel_name=python3_kernel,
        timeout=CELL_TIMEOUT_S,
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as err:
        pytest.fail(f"{path.name} failed:\n{err}", pytrace=False)
    outputs = [out for cell in nb.cells if cell.cell_type == "code" for out in cell.outputs]
    errors = [out for out in outputs if out.output_type == "error"]
    assert not errors, f"{path.name}: {errors}"
    images = sum("image/png" in out.get("data", {}) for out in outputs)
    assert images > 0, f"{path.name} drew no figure"
    EXECUTED_DIR.mkdir(exist_ok=True)
    partial = EXECUTED_DIR / f".{path.name}.partial"
    nbformat.write(nb, partial)
    partial.replace(EXECUTED_DIR / path.name)  # whole or not at all: the site never reads half a file
