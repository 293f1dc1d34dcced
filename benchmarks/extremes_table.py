"""The published table of numerical extremes, regenerated from the test suite.

Runs the test files of ``FILES`` (extreme bodies, long horizons, bad input, gimbal lock) with
``RIGIDJAX_EXTREMES_REPORT`` set: every check records what it measured (``extreme(...)`` in
tests/conftest.py) next to the bound it asserts. Writes
``benchmarks/results/extremes.json`` and ``benchmarks/results/extremes.md`` and replaces the table
between the ``<!-- extremes-table -->`` markers of the documentation page docs/extremes.md.

Usage: python benchmarks/extremes_table.py [--no-docs]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
PAGE = ROOT / "docs" / "extremes.md"  # the documentation page that shows the table
BEGIN, END = "<!-- extremes-table -->", "<!-- /extremes-table -->"
# The test files that record rows. They run in this order, and the table's sections follow the order
# in which their rows are recorded.
FILES = [
    "tests/test_extreme_bodies.py",
    "tests/test_long_horizons.py",
    "tests/test_bad_input.py",
    "tests/test_gimbal_lock.py",
]


def _number(x):
    return "" if x is None else f"{x:.2g}"


def markdown(rows: list[dict]) -> str:
    lines = [
        "| Extreme | Case | What rigidjax does | Measured | Bound (tested) | Advice |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        cells = [
            r["area"],
            r["case"],
            r["behaviour"],
            _number(r["measured"]),
            _number(r["bound"]),
            r["advice"],
        ]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def insert_table(table: str, path: pathlib.Path = PAGE) -> bool:
    """Replace the text between the markers of ``path`` with ``table``; False if it has no markers."""
    text = path.read_text()
    if BEGIN not in text or END not in text:
        return False
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    path.write_text(f"{head}{BEGIN}\n{table}{END}{tail}")
    return True


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--no-docs", "--no-readme", action="store_true", help="do not rewrite the table of docs/extremes.md"
    )
    args = parser.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    report = RESULTS / "extremes.json"
    with tempfile.TemporaryDirectory() as scratch:
        # The tests write their rows beside the results, which change only if every test passed.
        rows_file = pathlib.Path(scratch) / "rows.json"
        env = dict(os.environ, RIGIDJAX_EXTREMES_REPORT=str(rows_file))
        result = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider", *FILES],
            cwd=ROOT,
            env=env,
        )
        if result.returncode != 0:
            sys.exit(f"the extremes tests failed (exit {result.returncode}); the table was not updated")
        rows = json.loads(rows_file.read_text())
    order = {name: i for i, name in enumerate(dict.fromkeys(r["area"] for r in rows))}
    rows.sort(key=lambda r: order[r["area"]])
    report.write_text(json.dumps(rows, indent=1) + "\n")
    table = markdown(rows)
    (RESULTS / "extremes.md").write_text(table)
    print(table)
    if not args.no_docs:
        page = PAGE.relative_to(ROOT)
        if insert_table(table):
            print(f"{page} table updated")
        else:
            print(f"{page} has no {BEGIN} ... {END} markers; table not inserted")


if __name__ == "__main__":
    main()
