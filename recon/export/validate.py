"""Format validation of exported assets, for tests and the report.

- :func:`validate_gltf`: the Khronos glTF validator (npm ``gltf-validator``, pinned in
  ``tools/gltf-validator/package-lock.json``; install with
  ``npm ci --prefix tools/gltf-validator``), run by ``node tools/gltf-validator/validate.js``.
- :func:`validate_usdz`: every validator registered with ``pxr.UsdValidation`` (usd-core 26.11
  has no ComplianceChecker / usdchecker).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
from pathlib import Path

log = logging.getLogger(__name__)

__all__ = ["ValidatorUnavailable", "validate_gltf", "gltf_errors", "validate_usdz", "TOOL_DIR"]

TOOL_DIR = Path(__file__).resolve().parents[2] / "tools" / "gltf-validator"
"""Folder of the node script and its pinned npm package (override: ``RECON_GLTF_VALIDATOR``)."""


class ValidatorUnavailable(RuntimeError):
    """The glTF validator (node or its npm package) is not installed; the message says how."""


def _tool_dir() -> Path:
    return Path(os.environ.get("RECON_GLTF_VALIDATOR", TOOL_DIR))


def validate_gltf(path: str | os.PathLike, max_issues: int = 100, timeout: float = 120.0) -> dict:
    """Run the Khronos glTF validator on a .glb/.gltf file and return its report.

    Returns
    -------
    dict
        The validator's JSON report: ``report["issues"]`` has ``numErrors``, ``numWarnings``,
        ``numInfos``, ``numHints`` and ``messages`` (each with ``code``, ``message``,
        ``severity`` 0 = error .. 3 = hint, and ``pointer`` or ``offset``); ``report["info"]``
        summarizes the asset (extensions used, draw calls, ...).

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ValidatorUnavailable
        node, the npm package or the script is missing, or the validator could not run.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    tool = _tool_dir()
    node = shutil.which("node")
    script = tool / "validate.js"
    if node is None:
        raise ValidatorUnavailable(
            "node is not installed; install Node.js (Debian: apt-get install -y nodejs npm), "
            "then npm ci --prefix tools/gltf-validator")
    if not (tool / "node_modules" / "gltf-validator").is_dir() or not script.is_file():
        raise ValidatorUnavailable(
            f"the glTF validator is not installed in {tool}; run: npm ci --prefix {tool}")
    proc = subprocess.run(
        [node, str(script), str(path), str(int(max_issues))],
        capture_output=True, text=True, timeout=timeout, check=False,
    )
    if proc.returncode != 0:
        raise ValidatorUnavailable(f"{path}: the glTF validator failed: {proc.stderr.strip()}")
    return json.loads(proc.stdout)


def gltf_errors(report: dict) -> list[str]:
    """The error messages (severity 0) of a :func:`validate_gltf` report, as strings."""
    return [
        f"{m['code']}: {m['message']} ({m.get('pointer', m.get('offset', ''))})"
        for m in report["issues"]["messages"] if m["severity"] == 0
    ]


def validate_usdz(path: str | os.PathLike, include_warnings: bool = False) -> list[str]:
    """Run every registered ``pxr.UsdValidation`` validator on a USD/USDZ file.

    Parameters
    ----------
    path
        A .usdz (or .usd/.usda/.usdc) file.
    include_warnings
        Also return warnings (errors only by default).

    Returns
    -------
    list of str
        One line per problem, ``"<validator> <ErrorName> [Error|Warn]: message (sites)"``;
        empty when the file passes. A stage that cannot be opened is one error.
    """
    from pxr import Sdf, Tf, Usd, UsdValidation

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    # A layer of the same path opened earlier in this process would be reused as it was.
    layer = Sdf.Layer.Find(str(path))
    if layer is not None:
        layer.Reload(force=True)
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as e:
        return [f"{path}: cannot open the stage ({str(e).strip()})"]
    if stage is None:
        return [f"{path}: cannot open the stage"]
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    wanted = {UsdValidation.ValidationErrorType.Error}
    if include_warnings:
        wanted.add(UsdValidation.ValidationErrorType.Warn)
    out = []
    for e in errors:
        if e.GetType() not in wanted:
            continue
        validator = e.GetValidator()
        vname = validator.GetMetadata().name if validator is not None else "?"
        sites = ", ".join(
            str(s.GetPrim().GetPath()) if s.GetPrim() else str(s.GetLayer().identifier if s.GetLayer() else "")
            for s in e.GetSites()
        )
        out.append(f"{vname} {e.GetName()} [{e.GetType().displayName}]: {e.GetMessage()}"
                   + (f" ({sites})" if sites else ""))
    return out
