"""The optimize stage's shape (issue 33 items 1-2), held to the code: the stage function a table
of contents, no module over 800 lines, one fitting loop beside the main loop's, one eq. 6."""

import ast
import inspect
import re
from pathlib import Path

import recon
from recon.optimize import loop

RECON = Path(recon.__file__).parent
OPTIMIZE = RECON / "optimize"


def test_no_module_over_800_lines():
    long = {str(p.relative_to(RECON)): n for p in RECON.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 800}
    assert not long, long


def test_optimize_capture_reads_as_a_table_of_contents():
    src = inspect.getsource(loop.optimize_capture)
    assert len(src.splitlines()) <= 120
    body = ast.parse(src).body[0].body
    phases = [line.strip() for line in src.splitlines() if line.strip().startswith("# ----")]
    assert [p.split(":")[0].strip("# -") for p in phases] == ["inputs", "run(s)", "selections", "outputs"], phases
    branches = sum(isinstance(n, (ast.If, ast.For, ast.While, ast.Try)) for s in body for n in ast.walk(s))
    assert branches <= 2, branches


def _optimize_sources():
    return {p.name: p.read_text() for p in OPTIMIZE.glob("*.py")}


def test_one_fitting_loop_beside_the_main_loop():
    """Backward passes only in fitting.fit and the main loop's iteration; the rate decay and
    Adam's construction for a fit written once (the main loop's, the camera refinement's and
    the loop's imaging terms' optimizers step inside the main loop)."""
    src = _optimize_sources()
    assert {n for n, s in src.items() if ".backward()" in s} == {"fitting.py", "iteration.py"}
    assert {n for n, s in src.items() if re.search(r"0\.1 \*\* \(", s)} == {"fitting.py"}


def test_eq6_written_once():
    src = _optimize_sources()
    assert {n for n, s in src.items() if re.search(r"\)\.abs\(\) \* w", s)} == {"objective.py"}
    assert src["objective.py"].count(".abs() * weights") == 1
