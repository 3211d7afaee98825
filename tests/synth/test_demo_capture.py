"""The bundled CI capture captures/demo: made by the ``demo`` preset, small, contract-conform."""

import hashlib
import json

import pytest

from recon import sections
from recon.io.cameras import load_cameras
from recon.synth.capture import PRESETS, SynthSettings, make_capture

DEMO_COMMAND = "python -m recon synth captures/demo --preset demo"


@pytest.fixture(scope="module")
def demo(repo_root):
    path = repo_root / "captures" / "demo"
    if not path.is_dir():
        pytest.fail(f"{path} is missing; regenerate it with `{DEMO_COMMAND}`")
    return path


def _hashes(root, skip=()):
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name not in skip}


def test_demo_contract_and_size(demo):
    assert not (demo / "cameras.json").exists()  # the pipeline must run SfM
    images = sorted((demo / "images").glob("*.dng"))
    assert 24 <= len(images) <= 32
    for name in ("mesh.obj", "diffuse.exr", "specular.exr", "roughness.exr", "cameras.json"):
        assert (demo / "gt" / name).is_file()
    cams = load_cameras(demo / "gt" / "cameras.json")
    assert [demo / c.image for c in cams] == images
    assert (cams.frames[0].width, cams.frames[0].height) == (192, 144)
    total = sum(p.stat().st_size for p in demo.rglob("*") if p.is_file())
    assert total < 4 * 2**20, f"captures/demo is {total / 2**20:.2f} MiB"
    meta = json.loads((demo / "gt" / "synth.json").read_text())
    assert meta["command"] == DEMO_COMMAND
    # the bundled files were made by the current demo preset; settings added since then must be
    # at their defaults (which leave the output unchanged)
    preset = json.loads(json.dumps(sections.flatten(PRESETS["demo"])))
    assert {k: preset[k] for k in meta["settings"]} == meta["settings"]
    defaults = json.loads(json.dumps(sections.flatten(SynthSettings())))
    assert {k: preset[k] for k in preset if k not in meta["settings"]} == \
        {k: defaults[k] for k in preset if k not in meta["settings"]}


@pytest.mark.slow
def test_demo_regenerates_bit_identically(demo, tmp_path, drjit_single_thread):
    """Same machine type: the demo preset reproduces every file (the command line in gt/ aside).

    Mitsuba's LLVM backend may round differently on another CPU, so this runs as a slow test.
    On one drjit thread, so that each pixel's samples are added in their own order (with several
    threads the scheduler's order can change a last bit).
    """
    make_capture(tmp_path / "demo", PRESETS["demo"], command=DEMO_COMMAND)
    assert _hashes(tmp_path / "demo") == _hashes(demo)
