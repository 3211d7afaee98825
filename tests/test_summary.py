"""recon.summary: the run summary from the files a run leaves (tests/workflow/test_slurm.py runs it
on a real cluster; these cases build the files a run leaves in each situation)."""

from __future__ import annotations

import json

import pytest

from recon.summary import STAGES, capture_status, write_run_summary

BENCH = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n1.0\t0:00:01\t100\t1\t1\t1\t0\t0\t50\t0.5\n"


def _finish(results, capture, stages):
    for s in stages:
        (results / capture / "benchmarks").mkdir(parents=True, exist_ok=True)
        (results / capture / "benchmarks" / f"{s}.tsv").write_text(BENCH)
        (results / capture / "logs").mkdir(parents=True, exist_ok=True)
        (results / capture / "logs" / f"{s}.log").write_text(f"10:00:00 INFO recon.{s}: done\n")
    if "report" in stages:
        (results / capture / "report").mkdir(parents=True, exist_ok=True)
        (results / capture / "report" / "index.html").write_text("<html></html>")


def test_finished_failed_and_not_started(tmp_path):
    results = tmp_path / "results"
    _finish(results, "good", STAGES)
    _finish(results, "bad", STAGES[:2])
    (results / "bad" / "logs" / "masks.log").write_text(
        "10:00:01 INFO recon.masks: 12 images\n"
        "10:00:02 ERROR recon.logs: masks failed: /c/bad/images/0003.png: empty mask; give masks/0003.png\n")
    md = write_run_summary(results, ["good", "bad", "later"], "error", slurm_log_dir=None)
    data = json.loads((results / "summary.json").read_text())
    by = {c["capture"]: c for c in data["captures"]}
    assert by["good"]["status"] == "finished" and by["good"]["stages_done"] == list(STAGES)
    assert by["bad"]["status"] == "failed" and by["bad"]["failed_stage"] == "masks"
    assert by["bad"]["reason"] == "masks failed: /c/bad/images/0003.png: empty mask; give masks/0003.png"
    assert by["bad"]["log"].endswith("bad/logs/masks.log")
    assert by["later"]["status"] == "not finished" and "check did not run" in by["later"]["reason"]
    text = md.read_text()
    assert "3 captures: 1 finished, 1 failed, 1 not finished." in text
    assert "| bad | failed | 2/9 | masks | masks failed: /c/bad/images/0003.png: empty mask" in text


@pytest.mark.parametrize("line, expected", [
    ("slurmstepd: error: *** JOB 17 ON vm CANCELLED AT 2026-11-24T14:50:02 DUE TO TIME LIMIT ***",
     "killed by SLURM (time limit) at 2026-11-24T14:50:02"),
    ("slurmstepd: error: *** JOB 18 ON vm CANCELLED AT 2026-11-24T14:51:30 ***",
     "cancelled in SLURM (scancel or preemption) at 2026-11-24T14:51:30"),
    ("slurmstepd: error: Detected 1 oom_kill event in StepId=19.0.", "out of memory"),
])
def test_a_job_killed_by_slurm_says_so(tmp_path, line, expected):
    results, slurm = tmp_path / "results", tmp_path / "slurm_logs"
    _finish(results, "cap", STAGES[:5])
    (results / "cap" / "logs" / "optimize.log").write_text("10:00:00 INFO recon.optimize.loop: stage 0\n")
    job_log = slurm / "rule_optimize" / "cap" / "17.log"
    job_log.parent.mkdir(parents=True)
    job_log.write_text(f"rule optimize:\n    wildcards: capture=cap\n{line}\n")
    st = capture_status(results, "cap", slurm)
    assert st.status == "failed" and st.failed_stage == "optimize"
    assert expected in st.reason and st.log == str(job_log)


def test_a_grouped_job_is_found_by_its_capture(tmp_path):
    """profiles/slurm groups linearize..uv: the group job's log has no capture folder."""
    results, slurm = tmp_path / "results", tmp_path / "slurm_logs"
    (results / "a" / "logs").mkdir(parents=True)
    (results / "a" / "logs" / "linearize.log").write_text("10:00:00 INFO recon.linearize: reading\n")
    group = slurm / "group_prepare_init_mesh_linearize_masks_poses_uv"
    group.mkdir(parents=True)
    (group / "30.log").write_text("rule linearize:\n    wildcards: capture=b\nall good\n")
    (group / "31.log").write_text("rule linearize:\n    wildcards: capture=a\n"
                                  "slurmstepd: error: *** JOB 31 ON n1 CANCELLED AT 2026-11-24T15:00:00 DUE TO TIME LIMIT ***\n")
    st = capture_status(results, "a", slurm)
    assert st.failed_stage == "linearize" and "time limit" in st.reason and st.log.endswith("31.log")


def test_a_traceback_without_an_error_line(tmp_path):
    results = tmp_path / "results"
    (results / "c" / "logs").mkdir(parents=True)
    (results / "c" / "logs" / "linearize.log").write_text(
        "Traceback (most recent call last):\n  File \"x.py\", line 1\nValueError: bad black level\n")
    st = capture_status(results, "c")
    assert st.reason == "ValueError: bad black level"


def test_the_error_in_a_job_log(tmp_path):
    """Without an ERROR line in the stage's log, the traceback's last line in the job's output."""
    results, slurm = tmp_path / "results", tmp_path / "slurm_logs"
    (results / "d" / "logs").mkdir(parents=True)
    (results / "d" / "logs" / "linearize.log").write_text("15:20:33 INFO recon.linearize.stage: 6 images\n")
    group = slurm / "group_prepare_init_mesh_linearize_masks_poses_uv"
    group.mkdir(parents=True)
    (group / "54.log").write_text(
        "rule linearize:\n    wildcards: capture=d\nTraceback (most recent call last):\n"
        "recon.io.images.ImageError: /c/d/images/0002.exr: not a readable OpenEXR file\n"
        "CalledProcessError in file \"/w/workflow/rules/linearize.smk\", line 23:\n"
        "Error in rule linearize:\nWorkflowError:\nAt least one job did not complete successfully.\n")
    st = capture_status(results, "d", slurm)
    assert st.reason == "ImageError: /c/d/images/0002.exr: not a readable OpenEXR file"
    assert st.log.endswith("54.log")
