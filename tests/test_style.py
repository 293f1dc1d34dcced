"""The code is linted and formatted as pyproject.toml says, so style never drifts between commits:
``ruff check`` and ``ruff format --check`` over the package, the tests and the benchmarks (ruff is
pinned in the ``test`` extra; formatting changes between its releases)."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PATHS = ["rigidjax", "tests", "benchmarks"]


@pytest.mark.parametrize("command", [["check"], ["format", "--check"]], ids=["lint", "format"])
def test_ruff(command):
    result = subprocess.run(
        [sys.executable, "-m", "ruff", *command, *PATHS], cwd=ROOT, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout + result.stderr
