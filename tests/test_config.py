import dataclasses
import logging
import subprocess
import sys

import pytest

from recon import config as rc


@dataclasses.dataclass(frozen=True)
class _Settings:
    size: int = 4
    scale: float = 1.0
    levels: tuple = (1, 2)


def test_build_settings_coerces_and_rejects_unknown(tmp_path):
    s = rc.build_settings(_Settings, {"size": 8, "scale": 2, "levels": [3, 4]})
    assert s == _Settings(8, 2.0, (3, 4))
    with pytest.raises(rc.ConfigError, match=r"unknown _Settings key\(s\) \['sise'\]"):
        rc.build_settings(_Settings, {"sise": 8})


def test_capture_yaml_overrides_preset(tmp_path):
    presets = tmp_path / "presets"
    presets.mkdir()
    (presets / "draft.yaml").write_text("optimize: {iters: 10, spp: 2}\n")
    (presets / "accurate.yaml").write_text("optimize: {iters: 1000, spp: 16}\n")
    cap = tmp_path / "cap"
    cap.mkdir()
    assert rc.stage_settings("optimize", "draft", cap, presets)["iters"] == 10
    (cap / "capture.yaml").write_text("preset: accurate\noptimize: {spp: 64}\nlight_intensity: 3.0\n")
    s = rc.stage_settings("optimize", "draft", cap, presets)
    assert (s["iters"], s["spp"], s["_preset"]) == (1000, 64, "accurate")
    poses = rc.stage_settings("poses", "draft", cap, presets)
    assert poses["light_intensity"] == 3.0 and str(cap / "capture.yaml") in poses["_sources"]
    # the light goes to the poses stage only (it writes it into poses/cameras.json)
    assert all("light_intensity" not in rc.stage_settings(s, "draft", cap, presets)
               for s in rc.STAGES if s != "poses")


@pytest.mark.parametrize(
    "text, match",
    [
        ("bogus: 1\n", r"unknown key\(s\) \['bogus'\]"),
        ("preset: fast\n", "preset must be one of"),
        ("optimize: 3\n", "'optimize' must be a mapping"),
        ("optimize: [1\n", "not valid YAML"),
        ("light_intensity: -2\n", "light_intensity must be a positive number, got -2"),
        ("light_intensity: bright\n", "light_intensity must be a positive number, got 'bright'"),
        ("light_intensity: 2\nposes: {light_intensity: 3}\n",
         r"light_intensity 2 and poses\.light_intensity 3 differ; give the light intensity once"),
    ],
)
def test_bad_capture_yaml_names_the_file(tmp_path, text, match):
    (tmp_path / "capture.yaml").write_text(text)
    with pytest.raises(rc.ConfigError, match=match) as e:
        rc.read_capture_yaml(tmp_path)
    assert "capture.yaml" in str(e.value)


def test_repository_presets_are_valid():
    for preset in rc.PRESETS:
        data = rc.load_preset(preset)
        assert set(data) <= set(rc.STAGES)


def test_discover_captures(tmp_path):
    with pytest.raises(rc.ConfigError, match="does not exist"):
        rc.discover_captures(tmp_path / "nope")
    with pytest.raises(rc.ConfigError, match="no capture folders"):
        rc.discover_captures(tmp_path)
    (tmp_path / "b" / "images").mkdir(parents=True)
    (tmp_path / "a" / "images").mkdir(parents=True)
    (tmp_path / "notes").mkdir()
    assert rc.discover_captures(tmp_path) == ["a", "b"]


def _snakemake(repo_root, *args):
    return subprocess.run(
        [sys.executable, "-m", "snakemake", "-n", "--cores", "1", *args],
        cwd=repo_root, capture_output=True, text=True, timeout=300,
    )


def test_snakemake_rejects_wrong_config_key_and_value(repo_root, tmp_path):
    (tmp_path / "c" / "images").mkdir(parents=True)
    r = _snakemake(repo_root, "--config", f"captures={tmp_path}", f"results={tmp_path}/r", "presett=draft")
    assert r.returncode != 0
    assert "presett" in (r.stdout + r.stderr)
    r = _snakemake(repo_root, "--config", f"captures={tmp_path}", f"results={tmp_path}/r", "preset=fastest")
    assert r.returncode != 0
    assert "fastest" in (r.stdout + r.stderr)


def test_folders_without_images_are_named_when_skipped(tmp_path, caplog):
    """A folder beside the captures that has no images/ is skipped with a warning naming it, and
    a hint when its photos lie directly in it (issue 21 item 9)."""
    from recon.config import discover_captures

    (tmp_path / "good" / "images").mkdir(parents=True)
    (tmp_path / "stray").mkdir()
    for name in ("0001.JPG", "0002.dng", "notes.txt"):
        (tmp_path / "stray" / name).write_bytes(b"x")
    (tmp_path / "empty").mkdir()
    (tmp_path / ".cache").mkdir()
    (tmp_path / "README.md").write_text("my captures")
    with caplog.at_level(logging.WARNING, logger="recon"):
        assert discover_captures(tmp_path) == ["good"]
    warnings = sorted(r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING)
    assert len(warnings) == 2, warnings
    assert warnings[0] == f"{tmp_path / 'empty'}: no images/ folder, so it is not a capture and is skipped"
    assert warnings[1].startswith(f"{tmp_path / 'stray'}: no images/ folder")
    assert "2 photo(s) (0001.JPG, 0002.dng): move them into " + str(tmp_path / "stray" / "images") in warnings[1]


class _Job:
    """The parts of Snakemake's injected ``snakemake`` object that job_settings reads."""

    def __init__(self, captures, resources):
        self.config = {"captures": str(captures), "preset": "draft"}
        self.wildcards = dataclasses.make_dataclass("W", ["capture"])("cap")
        self.resources = resources


@pytest.mark.parametrize("resources, variant", [
    ({}, None), ({"gpu": 0}, None), ({"gpu": 1}, "cuda_ad_rgb"), ({"gpu": "2"}, "cuda_ad_rgb"),
    ({"gres": "gpu:1"}, "cuda_ad_rgb"), ({"gres": "gpu:a100:2"}, "cuda_ad_rgb"),
    ({"gres": "tmpfs:10G"}, None), ({"gres": "gpus_are_not_this:1"}, None), (None, None),
])
def test_job_variant_follows_the_gpu_resource(resources, variant):
    assert rc.job_variant(resources) == variant


def test_job_settings_render_optimize_on_the_job_gpu(tmp_path):
    cap = tmp_path / "caps" / "cap"
    cap.mkdir(parents=True)
    assert rc.job_settings("optimize", _Job(tmp_path / "caps", {"gpu": 1}))["variant"] == "cuda_ad_rgb"
    assert "variant" not in rc.job_settings("optimize", _Job(tmp_path / "caps", {}))
    assert "variant" not in rc.job_settings("report", _Job(tmp_path / "caps", {"gpu": 1}))
    # a variant the settings name wins
    (cap / "capture.yaml").write_text("optimize:\n  variant: llvm_ad_rgb\n")
    assert rc.job_settings("optimize", _Job(tmp_path / "caps", {"gpu": 1}))["variant"] == "llvm_ad_rgb"
    with pytest.raises(rc.ConfigError, match="resource gpu='many'"):
        rc.job_variant({"gpu": "many"})
