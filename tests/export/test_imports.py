"""The export package has a one-way import graph: conventions <- gltf, usd <- asset, and no
function-local import of a recon module (which would hide a cycle)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import recon.export

PACKAGE = Path(recon.export.__file__).parent
MODULES = sorted(p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__")


def _local_recon_imports(path: Path) -> list[str]:
    found = []
    for fn in ast.walk(ast.parse(path.read_text())):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            found += [f"{path.name}:{node.lineno} {fn.name}() imports {n}"
                      for n in names if n == "recon" or n.startswith("recon.")]
    return found


def test_no_function_local_recon_imports():
    bad = [line for p in sorted(PACKAGE.glob("*.py")) for line in _local_recon_imports(p)]
    assert not bad, "move these imports to module level (a cycle hides behind them):\n" + "\n".join(bad)


@pytest.mark.parametrize("module", MODULES)
def test_each_module_imports_first(module):
    """Importing any export module first, in a fresh interpreter, works (no partial-module cycle)."""
    proc = subprocess.run([sys.executable, "-c", f"import recon.export.{module}"],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr


def test_detector_sees_a_local_import(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("def f():\n    from recon.export.asset import TEXTURE_FILES\n    return TEXTURE_FILES\n")
    assert _local_recon_imports(p) == ["m.py:2 f() imports recon.export.asset"]
