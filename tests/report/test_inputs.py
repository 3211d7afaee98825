"""Readers of the optimizer's log/summary and of Snakemake benchmark files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import report_scene

from recon.report.inputs import (
    ReportError,
    loss_curves,
    material_model,
    optimize_phases,
    phase_seconds,
    read_benchmarks,
    read_log,
    read_model,
    read_summary,
    summary_r_min,
)


@pytest.mark.parametrize("record, expected", [
    ({"iter": 3, "loss": 0.2, "t_render": 0.5, "t_backward": 1.5}, {"render": 0.5, "backward": 1.5}),
    ({"render_s": 0.5, "loss_seconds": 0.1, "geometry_time": 2.0}, {"render": 0.5, "loss": 0.1, "geometry": 2.0}),
    ({"time_render": 1.0, "seconds_geometry_processing": 3.0}, {"render": 1.0, "geometry_processing": 3.0}),
    ({"timings": {"render": 0.25, "backward": 0.75, "bad": "x"}}, {"render": 0.25, "backward": 0.75}),
    ({"phases": {"render": {"total": 2.0, "count": 4}}}, {"render": 2.0}),
    ({"iter": 1, "loss": 0.3, "lr": 0.01, "stage": 2, "time": 1.7e9}, {}),
    ({"wall_seconds": 9.0, "phase_seconds": {"render": 1.0, "setup": 2.0}}, {"render": 1.0, "setup": 2.0}),
    ({"wall_seconds": 9.0, "total_time": 3.0, "t_render": 1.0}, {"render": 1.0}),
    ({"t_render": float("nan"), "t_loss": True, "t_backward": "1"}, {}),
])
def test_phase_seconds_spellings(record, expected):
    assert phase_seconds(record) == pytest.approx(expected)


def test_optimize_phases_sums_the_log_and_prefers_the_summary():
    records = [{"t_render": 1.0, "t_loss": 0.5}, {"t_render": 2.0}, {"loss": 0.1}]
    assert optimize_phases(records, {}) == ({"render": 3.0, "loss": 0.5}, "log.jsonl")
    assert optimize_phases(records, {"timings": {"render": 10.0}}) == ({"render": 10.0}, "summary.json")
    assert optimize_phases([{"loss": 1.0}], {}) == ({}, "")


def test_read_log_skips_bad_lines(tmp_path, caplog):
    p = tmp_path / "log.jsonl"
    p.write_text('{"iter": 0, "loss": 1.0}\nnot json\n[1, 2]\n\n{"iter": 1, "loss": 0.5}\n{"iter": 2, "lo')
    with caplog.at_level("WARNING"):
        recs = read_log(p)
    assert recs == [{"iter": 0, "loss": 1.0}, {"iter": 1, "loss": 0.5}]
    assert sum("line skipped" in r.message for r in caplog.records) == 3


def test_read_log_missing_names_the_file(tmp_path):
    with pytest.raises(ReportError, match=str(tmp_path / "log.jsonl").replace(".", r"\.") + ": not found"):
        read_log(tmp_path / "log.jsonl")


def test_read_summary_is_optional(tmp_path):
    assert read_summary(tmp_path / "summary.json") == {}
    (tmp_path / "summary.json").write_text("{broken")
    assert read_summary(tmp_path / "summary.json") == {}
    (tmp_path / "summary.json").write_text(json.dumps({"preset": "draft"}))
    assert read_summary(tmp_path / "summary.json") == {"preset": "draft"}


def test_loss_curves_iterations_restart_per_stage():
    recs = [{"stage": 0, "iteration": 0, "loss": 1.0}, {"stage": 0, "iteration": 1, "loss": 0.9},
            {"stage": 1, "iteration": 0, "loss": 0.8}, {"stage": 1, "iteration": 5, "loss": 0.7},
            {"stage": 2, "iteration": 0, "loss": 0.6}]
    np.testing.assert_array_equal(loss_curves(recs).iteration, [0, 1, 2, 7, 8])


def test_loss_curves():
    recs = [{"iter": 0, "stage": 0, "loss": 1.0, "t_loss": 0.1},
            {"iter": 1, "stage": 0, "loss": 0.5, "loss_mask": 0.2},
            {"note": "remeshed"},
            {"stage": "fine", "loss": 0.25, "loss_s": 3.0}]
    c = loss_curves(recs)
    assert len(c) == 3
    np.testing.assert_array_equal(c.iteration, [0, 1, 2])  # index where 'iter' is missing
    assert c.stage == ["0", "0", "fine"]
    assert list(c.series) == ["loss", "loss_mask"]  # t_loss / loss_s are timings
    np.testing.assert_array_equal(c.series["loss"], [1.0, 0.5, 0.25])
    np.testing.assert_array_equal(np.isnan(c.series["loss_mask"]), [True, False, True])
    assert len(loss_curves([])) == 0


def test_material_model_from_summary_then_log_then_settings():
    settings = {"settings": {"specular_channels": 3, "r_min": 0.05, "lr": 0.1}}
    assert material_model({"material_model": "rgb-specular", **settings}, [{"material_model": "x"}]) == "rgb-specular"
    assert material_model(settings, [{"material_model": "a"}, {"material_model": "b"}, {}]) == "b"
    assert material_model(settings, [{}]) == {"specular_channels": 3, "r_min": 0.05}
    assert material_model({}, [{}]) is None


def test_summary_r_min():
    assert summary_r_min({"settings": {"r_min": 0.05}}) == 0.05
    assert summary_r_min({"r_min": 0.1, "settings": {"r_min": 0.05}}) == 0.1
    assert summary_r_min({"r_min": 2.0}) is None
    assert summary_r_min({"settings": "x"}) is None


def test_read_benchmarks(tmp_path):
    report_scene.write_tsv(tmp_path / "poses.tsv", [2.0, 4.0])
    report_scene.write_tsv(tmp_path / "masks.tsv", [0.5])
    (tmp_path / "broken.tsv").write_text("a\tb\n1\t2\n")
    (tmp_path / "notes.txt").write_text("ignored")
    assert read_benchmarks(tmp_path) == {"poses": 3.0, "masks": 0.5}
    assert read_benchmarks(tmp_path / "absent") == {}
    assert read_benchmarks(None) == {}


def test_read_benchmarks_in_pipeline_order(tmp_path):
    """The stages in the order of recon.stages (optimize before poses by name), others after."""
    for name in ("optimize", "poses", "extra", "check"):
        report_scene.write_tsv(tmp_path / f"{name}.tsv", [1.0])
    assert list(read_benchmarks(tmp_path)) == ["check", "poses", "optimize", "extra"]


def test_read_model_round_trip(scene):
    m = read_model(scene.optimize)
    np.testing.assert_array_equal(m.diffuse, scene.textures["diffuse"])
    np.testing.assert_array_equal(m.mesh.t_pos_idx, scene.mesh.t_pos_idx)
    assert m.specular.shape[2] == 1 and m.roughness.shape[2] == 1


def test_read_model_wrong_channels(tmp_path, scene):
    import shutil

    from recon.io.images import write_exr

    shutil.copytree(scene.optimize, tmp_path / "opt")
    write_exr(tmp_path / "opt" / "roughness.exr", np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ReportError, match=r"roughness\.exr: the roughness map has 3 channel\(s\), expected 1"):
        read_model(tmp_path / "opt")
