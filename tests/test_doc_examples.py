"""The code examples of the README and the documentation pages run as written.

Each page's ``python`` blocks run in order in a fresh Python process, as a reader pastes them into
one session (the blocks of a page share their names). A block marked in the page's source by an HTML
comment on the line before it runs in a process of its own (``<!-- example: own process (why) -->``,
for code that must start before anything computes with JAX) or not at all
(``<!-- example: not run (why) -->``, for code that needs more than one process or machine); the
reason is part of the mark, and the blocks not run are listed here. Reference: the examples
themselves, independent of the tests that check the same functions' values.
"""

import json
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
PAGES = sorted(str(path.relative_to(ROOT)) for path in [ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
FENCE = re.compile(r"^```python\n(.*?)^```", re.S | re.M)
MARK = re.compile(r"<!-- example: (own process|not run) \((.+?)\) -->\s*$")

# Blocks that no single process can run, with the test that runs the same steps instead.
NOT_RUN = {
    ("docs/guides/batching.md", 4): "tests/test_distributed.py runs the recipe in two processes",
}


def examples(page: str) -> list[tuple[int, str, str | None]]:
    """``(number, code, mark)`` of each python block of `page`, numbered from 1."""
    text = (ROOT / page).read_text()
    blocks = []
    for number, match in enumerate(FENCE.finditer(text), start=1):
        before = text[: match.start()].rstrip("\n").rsplit("\n", 1)[-1]
        mark = MARK.match(before)
        blocks.append((number, match.group(1), mark.group(1) if mark else None))
    return blocks


PAGES_WITH_CODE = [page for page in PAGES if examples(page)]

RUNNER = """
import json, sys
blocks = json.load(open(sys.argv[1]))
namespace = {"__name__": "__main__"}
for name, code in blocks:
    exec(compile(code, name, "exec"), namespace)
"""


def run_blocks(page, blocks, cwd):
    script = cwd / "blocks.json"
    script.write_text(json.dumps([(f"{page}, example {number}", code) for number, code in blocks]))
    env = {**os.environ, "MPLBACKEND": "Agg", "XDG_CACHE_HOME": str(cwd / "cache")}
    result = subprocess.run(
        [sys.executable, "-c", RUNNER, str(script)], cwd=cwd, env=env, capture_output=True, text=True
    )
    assert result.returncode == 0, (
        f"{page}: an example failed\n{result.stdout[-2000:]}\n{result.stderr[-4000:]}"
    )


def test_every_page_with_code_is_checked():
    """The pages of the guides, the getting-started page and the README all hold examples; a page
    that lost its blocks (a changed fence) would otherwise drop out of the check unnoticed."""
    for page in ["README.md", "docs/getting-started.md", "docs/guides/fitting.md", "docs/guides/scenes.md"]:
        assert page in PAGES_WITH_CODE
    marked = {
        (page, number) for page in PAGES_WITH_CODE for number, _, mark in examples(page) if mark == "not run"
    }
    assert marked == set(NOT_RUN)


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES_WITH_CODE)
def test_examples_run(page, tmp_path):
    together = []
    for number, code, mark in examples(page):
        if mark == "not run":
            continue
        if mark == "own process":
            alone = tmp_path / f"alone{number}"
            alone.mkdir()
            run_blocks(page, [(number, code)], alone)
        else:
            together.append((number, code))
    if together:
        run_blocks(page, together, tmp_path)
