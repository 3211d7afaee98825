"""The report's interactive 3D view: Google's ``<model-viewer>`` shipped inside report/.

The report must open offline and from ``file://``. Browsers refuse ``fetch()`` of local files
from a ``file://`` page, so the glTF binary is also written as a classic script
(``asset.glb.js``, the file's bytes in base64) that the page turns into a Blob URL; the UMD
build of model-viewer (three.js bundled, no module imports) is copied beside it. Both work
the same over ``http://``.

The bundle comes from ``tools/report-viewer`` (``npm ci --prefix tools/report-viewer``, run by
``scripts/setup.sh``), which pins ``@google/model-viewer``.
"""

from __future__ import annotations

import base64
import os
import shutil
from pathlib import Path

from recon.report.inputs import ReportError

BUNDLE_NAME = "model-viewer-umd.min.js"
DEFAULT_VIEWER_DIST = (Path(__file__).resolve().parents[2] / "tools" / "report-viewer" / "node_modules"
                       / "@google" / "model-viewer" / "dist")
GLB_SCRIPT_GLOBAL = "RECON_ASSET_GLB_BASE64"


def find_bundle(viewer_js: str | os.PathLike | None = None) -> Path:
    """The model-viewer UMD bundle: ``viewer_js`` when given, else the pinned npm copy."""
    path = Path(viewer_js) if viewer_js else DEFAULT_VIEWER_DIST / BUNDLE_NAME
    if not path.is_file():
        raise ReportError(
            f"{path}: model-viewer's bundle not found; install it with "
            "`npm ci --prefix tools/report-viewer` (scripts/setup.sh does this), or set the "
            "report setting viewer_js to a copy of @google/model-viewer's dist/" + BUNDLE_NAME
        )
    return path


def install_viewer(folder: str | os.PathLike, glb: str | os.PathLike,
                   viewer_js: str | os.PathLike | None = None) -> dict[str, str]:
    """Copy the bundle and the glb into ``folder`` and write ``asset.glb.js``.

    Returns the file names by role: ``bundle``, ``glb``, ``glb_script``.
    """
    glb = Path(glb)
    if not glb.is_file():
        raise ReportError(f"{glb}: not found; the report needs the export stage's asset.glb (run it first)")
    data = glb.read_bytes()
    if len(data) < 12 or data[:4] != b"glTF":
        raise ReportError(f"{glb}: not a glTF binary (no 'glTF' magic); rerun the export stage")
    folder = Path(folder)
    bundle = find_bundle(viewer_js)
    shutil.copyfile(bundle, folder / BUNDLE_NAME)
    shutil.copyfile(glb, folder / "asset.glb")
    (folder / "asset.glb.js").write_text(
        f'window.{GLB_SCRIPT_GLOBAL} = "{base64.b64encode(data).decode("ascii")}";\n', encoding="ascii")
    return {"bundle": BUNDLE_NAME, "glb": "asset.glb", "glb_script": "asset.glb.js"}


def viewer_html(names: dict[str, str], alt: str) -> str:
    """The ``<model-viewer>`` element and the script that gives it the embedded glb."""
    from html import escape

    return f"""<model-viewer id="asset-view" camera-controls interaction-prompt="none"
  shadow-intensity="0" exposure="1" alt="{escape(alt)}"></model-viewer>
<p class="note">Drag to orbit, scroll to zoom. <a href="{escape(names['glb'])}" download>Download asset.glb</a></p>
<script>
(function () {{
  const viewer = document.getElementById('asset-view');
  const b64 = window.{GLB_SCRIPT_GLOBAL};
  const bytes = Uint8Array.from(atob(b64), c => c.charCodeAt(0));
  viewer.src = URL.createObjectURL(new Blob([bytes], {{type: 'model/gltf-binary'}}));
}})();
</script>"""


def viewer_head(names: dict[str, str]) -> str:
    """The ``<script>`` tags that load model-viewer and the embedded glb (classic scripts)."""
    from html import escape

    return (f'<script src="{escape(names["bundle"])}"></script>\n'
            f'<script src="{escape(names["glb_script"])}"></script>')
