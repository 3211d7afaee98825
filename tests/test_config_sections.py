"""Settings in sections (recon.sections) and their flat keys from before (recon.config)."""

from __future__ import annotations

import dataclasses
import logging
import warnings

import pytest

from recon import config as rc
from recon import sections
from recon.poses import PoseSettings


@dataclasses.dataclass(frozen=True)
class _Inner:
    size: int = 4
    levels: tuple = (1, 2)

    def __post_init__(self):
        if self.size > 100:
            raise ValueError(f"size must be <= 100, got {self.size}")


@dataclasses.dataclass(frozen=True)
class _Other:
    scale: float = 1.0


@sections.sectioned
@dataclasses.dataclass(frozen=True)
class _Settings:
    MOVED = {"old_scale": "other.scale"}

    inner: _Inner = dataclasses.field(default_factory=_Inner)
    other: _Other = dataclasses.field(default_factory=_Other)
    seed: int = 0


def test_leaf_paths_flatten_and_replace():
    assert sections.leaf_paths(_Settings) == {"size": "inner.size", "levels": "inner.levels",
                                              "scale": "other.scale", "old_scale": "other.scale"}
    s = sections.replace(_Settings(), size=8, scale=2.0, seed=3)
    assert s == _Settings(inner=_Inner(8), other=_Other(2.0), seed=3)
    assert sections.flatten(s) == {"size": 8, "levels": (1, 2), "scale": 2.0, "seed": 3}
    assert _Settings(inner={"size": 5}).inner == _Inner(5)  # a section as a mapping
    with pytest.raises(TypeError, match=r"has no setting\(s\) \['sise'\]"):
        sections.replace(_Settings(), sise=8)


def test_flat_python_keywords_still_work_with_a_deprecation_warning():
    with pytest.warns(DeprecationWarning, match="size -> inner.size"):
        s = _Settings(size=8)
    assert s.inner.size == 8
    with pytest.warns(DeprecationWarning, match="size -> inner.size"):
        assert dataclasses.replace(s, size=9).inner == _Inner(9, (1, 2))
    with pytest.warns(DeprecationWarning, match=r"_Settings.size is now _Settings.inner.size"):
        assert s.size == 8
    with pytest.raises(TypeError, match=r"unknown setting\(s\) \['sise'\]"):
        _Settings(sise=8)
    with pytest.raises(AttributeError):
        _Settings().sise  # noqa: B018
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the sections themselves: no warning
        assert _Settings(inner=_Inner(8)) == sections.replace(_Settings(), size=8)


def test_build_settings_takes_sections_and_moves_flat_keys(caplog):
    s = rc.build_settings(_Settings, {"inner": {"size": 8, "levels": [3]}, "seed": 2})
    assert s == _Settings(inner=_Inner(8, (3,)), seed=2)
    with caplog.at_level(logging.WARNING, logger="recon.config"):
        s = rc.build_settings(_Settings, {"size": 7, "old_scale": 3, "_sources": ["p.yaml", "cap/capture.yaml"],
                                          "_key_sources": {"size": "cap/capture.yaml", "old_scale": "cap/capture.yaml"}})
    assert s == _Settings(inner=_Inner(7), other=_Other(3.0))
    lines = [r.getMessage() for r in caplog.records]
    assert "cap/capture.yaml: 'size' is deprecated here: its place is now 'inner.size' (_Settings sections); " \
           "move it there" in lines
    assert any("'old_scale'" in x and "'other.scale'" in x for x in lines) and len(lines) == 2


def test_build_settings_refuses_what_names_no_place():
    with pytest.raises(rc.ConfigError, match=r"unknown _Settings key\(s\) \['sise'\]; valid keys: inner, other, "
                                             r"seed \(in sections: inner, other"):
        rc.build_settings(_Settings, {"sise": 8})
    with pytest.raises(rc.ConfigError, match=r"unknown _Settings.inner key\(s\) \['sise'\]"):
        rc.build_settings(_Settings, {"inner": {"sise": 8}})
    with pytest.raises(rc.ConfigError, match="_Settings section 'inner' must be a mapping"):
        rc.build_settings(_Settings, {"inner": 8})
    with pytest.raises(rc.ConfigError, match=r"_Settings.inner setting 'size' must be a whole number, got 'big'"):
        rc.build_settings(_Settings, {"size": "big"})
    with pytest.raises(rc.ConfigError, match=r"invalid _Settings.inner \(size must be <= 100"):
        rc.build_settings(_Settings, {"inner": {"size": 101}})
    with pytest.raises(rc.ConfigError, match=r"x.yaml: _Settings gives 'size' \(8\) and 'inner.size' \(9\); "
                                             r"keep 'inner.size' only"):
        rc.build_settings(_Settings, {"size": 8, "inner": {"size": 9}}, "x.yaml")


def _capture(tmp_path, preset_text, capture_text, stage="poses"):
    presets = tmp_path / "presets"
    presets.mkdir(parents=True)
    (presets / "draft.yaml").write_text(preset_text)
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "capture.yaml").write_text(capture_text)
    return rc.stage_settings(stage, "draft", cap, presets), cap


def test_capture_sections_merge_key_by_key_and_name_their_file(tmp_path):
    values, cap = _capture(tmp_path, "poses: {features: {max_image_size: 800, sift_upsample: 2}}\n",
                           "poses: {features: {sift_upsample: 3}, matching: {matcher: ordered}}\n")
    s = rc.build_settings(PoseSettings, values)
    assert (s.features.max_image_size, s.features.sift_upsample, s.matching.matcher) == (800, 3, "ordered")
    values, cap = _capture(tmp_path / "b", "poses: {}\n", "poses: {matching: {min_num_inliers: -1}}\n")
    with pytest.raises(rc.ConfigError, match=r"capture.yaml: PoseSettings.matching setting 'min_num_inliers' "
                                             r"must not be negative"):
        rc.build_settings(PoseSettings, values)


def test_flat_key_of_an_old_capture_yaml_still_works(tmp_path, caplog):
    values, cap = _capture(tmp_path, "poses: {features: {sift_upsample: 1, max_image_size: 800}}\n",
                           "poses: {sift_upsample: 2, seed: 4}\n")
    with caplog.at_level(logging.WARNING, logger="recon.config"):
        s = rc.build_settings(PoseSettings, values)
    assert (s.features.sift_upsample, s.features.max_image_size, s.seed) == (2, 800, 4)  # the capture's wins
    assert [r.getMessage() for r in caplog.records] == [
        f"{cap / 'capture.yaml'}: 'sift_upsample' is deprecated here: its place is now 'features.sift_upsample' "
        "(PoseSettings sections); move it there"]
    values, cap = _capture(tmp_path / "b", "poses: {}\n", "poses: {min_num_inliers: -1}\n")
    with pytest.raises(rc.ConfigError, match=r"capture.yaml: PoseSettings.matching setting 'min_num_inliers' "
                                             r"must not be negative"):
        rc.build_settings(PoseSettings, values)


def test_no_settings_class_over_40_fields():
    from recon.optimize.settings import OptimizeSettings
    from recon.synth.settings import SynthSettings

    def classes(cls):
        yield cls
        for sub in sections.section_types(cls).values():
            yield from classes(sub)

    for top in (PoseSettings, SynthSettings, OptimizeSettings):
        for cls in classes(top):
            assert len(dataclasses.fields(cls)) <= 40, (cls.__name__, len(dataclasses.fields(cls)))


# ---- OptimizeSettings ----
def _optimize(tmp_path, preset_text, capture_text):
    return _capture(tmp_path, preset_text, capture_text, stage="optimize")


def test_optimize_flat_keys_of_an_old_capture_yaml_still_work(tmp_path, caplog):
    """A flat key (``spp``) and a renamed one (``refine_cameras``, now ``cameras.refine``) in an
    older capture.yaml: each moved to its place with one line naming the file and the place; the
    capture's value wins over the preset's section."""
    from recon.optimize.settings import OptimizeSettings, settings_from_dict

    values, cap = _optimize(tmp_path, "optimize: {render: {resolution: 64, spp: 2}, cameras: {refine: select}}\n",
                            "optimize: {spp: 8, refine_cameras: 'off', camera_sigma_focal: 0.05, seed: 3}\n")
    with caplog.at_level(logging.WARNING, logger="recon.config"):
        s = settings_from_dict(values)
    assert (s.render.resolution, s.render.spp, s.cameras.refine, s.cameras.sigma_focal, s.seed) == \
        (64, 8, "off", 0.05, 3)
    assert s == sections.replace(OptimizeSettings(), resolution=64, spp=8, refine="off", sigma_focal=0.05, seed=3)
    file = cap / "capture.yaml"
    assert [r.getMessage() for r in caplog.records] == [
        f"{file}: 'spp' is deprecated here: its place is now 'render.spp' (OptimizeSettings sections); move it there",
        f"{file}: 'refine_cameras' is deprecated here: its place is now 'cameras.refine' (OptimizeSettings "
        "sections); move it there",
        f"{file}: 'camera_sigma_focal' is deprecated here: its place is now 'cameras.sigma_focal' "
        "(OptimizeSettings sections); move it there"]


def test_optimize_keys_that_name_no_place_are_refused(tmp_path):
    from recon.optimize.settings import settings_from_dict

    values, cap = _optimize(tmp_path, "optimize: {}\n", "optimize: {sppp: 8}\n")
    with pytest.raises(rc.ConfigError, match=r"capture.yaml: unknown OptimizeSettings key\(s\) \['sppp'\]; valid "
                                             r"keys: .*\(in sections: cameras, imaging, light, loss, material, optim"):
        settings_from_dict(values)
    values, cap = _optimize(tmp_path / "b", "optimize: {}\n", "optimize: {cameras: {refine_cameras: 'off'}}\n")
    with pytest.raises(rc.ConfigError, match=r"unknown OptimizeSettings.cameras key\(s\) \['refine_cameras'\]"):
        settings_from_dict(values)  # inside its section a key has its new name only
    values, cap = _optimize(tmp_path / "c", "optimize: {}\n", "optimize: {render: {spp: 0}}\n")
    with pytest.raises(rc.ConfigError, match=r"capture.yaml: invalid OptimizeSettings.render \(spp must be >= 1"):
        settings_from_dict(values)


def test_optimize_presets_are_written_in_sections():
    """Every preset's optimize section builds without a flat key's warning or a DeprecationWarning."""
    from recon.optimize.settings import OptimizeSettings, settings_from_dict

    for preset in rc.PRESETS:
        assert not sections.move_flat(OptimizeSettings, rc.load_preset(preset)["optimize"])[1], preset
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            settings_from_dict(rc.stage_settings("optimize", preset))


def test_optimize_flat_python_keywords_and_the_flat_record():
    """Flat keywords and reads still work, with a DeprecationWarning naming the place; to_dict()
    records the settings flat under the names from before the sections (summary.json, the
    checkpoints' fingerprint), and settings_from_record builds them back."""
    from recon.optimize import checkpoint
    from recon.optimize.settings import RECORDED_ORDER, OptimizeSettings, settings_from_record

    with pytest.warns(DeprecationWarning, match="refine_cameras -> cameras.refine"):
        s = OptimizeSettings(refine_cameras="off", spp=8)
    assert (s.cameras.refine, s.render.spp) == ("off", 8)
    with pytest.warns(DeprecationWarning, match=r"OptimizeSettings.w_edge is now OptimizeSettings.loss.w_edge"):
        assert s.w_edge == s.loss.w_edge
    record = s.to_dict()
    assert list(record) == list(RECORDED_ORDER)
    assert (record["refine_cameras"], record["spp"], record["imaging_terms"]) == ("off", 8, list(s.imaging.terms))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = settings_from_record(record)
    assert again == s
    assert checkpoint.fingerprint(again.to_dict(), []) == checkpoint.fingerprint(record, [])
    # a record without the keys added later still reads (their defaults)
    assert settings_from_record({k: v for k, v in record.items() if k != "w_imaging"}) == s
