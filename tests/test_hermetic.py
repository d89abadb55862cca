"""The suite never reads what a run of the workflow left in the checkout (results/, logs/,
.snakemake/, benchmarks/out/), so `snakemake --cores 2` and `python -m pytest -q` pass in either
order: each test runs in its own temporary directory (tests/conftest.py), and no test names the
checkout's run state."""

from __future__ import annotations

import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent

#: the checkout's run state, as a test would name it (``REPO / "results"``, ``ROOT / "logs"``...)
STATE = re.compile(
    r"""\b(?:REPO|ROOT)\s*/\s*["'](?:results|logs|\.snakemake|benchmarks/out)\b"""
    r"""|\b(?:REPO|ROOT)\s*/\s*["']benchmarks["']\s*/\s*["']out\b"""
)
#: a workflow run must name its own directory (``-d``/``--directory`` <tmp>)
SNAKEMAKE_CALL = re.compile(r"""["']-m["'],\s*["']snakemake["']""")


def test_each_test_runs_in_its_own_temporary_directory(tmp_path):
    assert Path.cwd() == tmp_path
    assert not Path.cwd().resolve().is_relative_to(REPO)


def test_no_test_names_the_checkouts_run_state():
    hits = [
        f"{p.name}:{i}: {line.strip()}"
        for p in sorted(TESTS.glob("*.py"))
        if p.name != Path(__file__).name
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if STATE.search(line) and "not (REPO" not in line
    ]
    assert not hits, hits


def test_every_workflow_run_in_the_tests_has_its_own_directory():
    for p in sorted(TESTS.glob("*.py")):
        text = p.read_text()
        if SNAKEMAKE_CALL.search(text):
            assert re.search(r"""["'](?:-d|--directory)["']""", text), p.name
