"""One readable summary of a pipeline run over many captures: which finished, which failed and why.

The Snakefile's ``onsuccess``/``onerror`` handlers call :func:`write_run_summary` at the end of
every run (also with ``--keep-going``, after the captures that could go on have finished), so a
person running a shelf of captures on a cluster reads one file, ``<results>/summary.md``
(and a machine ``summary.json``), instead of hundreds of job logs.

What it reads, per capture and stage (DESIGN section 2), nothing else:

- ``<results>/<capture>/benchmarks/<stage>.tsv``: Snakemake writes it when the stage's job
  succeeded (a failed job's outputs, this file included, are removed);
- ``<results>/<capture>/logs/<stage>.log``: the stage's log, kept when the job failed; its last
  ERROR line is the stage's own error message;
- the SLURM executor's job logs (``.snakemake/slurm_logs/{rule,group}_*/<capture>/<jobid>.log``,
  kept for failed jobs): a job that SLURM killed (time limit, ``scancel``, memory) says so
  there, in a line of slurmstepd's, while the stage's log just stops.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

from recon.stages import FINAL, NAMES

log = logging.getLogger(__name__)

STAGES = NAMES
"""The stages in pipeline order (:data:`recon.stages.STAGES`, the rules of workflow/rules/)."""

# slurmstepd's line in a job's output when SLURM ends it: "*** JOB 12 ON node CANCELLED AT
# 2026-11-24T15:01:02 DUE TO TIME LIMIT ***" (scancel: "... CANCELLED AT ... ***").
_SLURM_KILLED = re.compile(r"\*\*\* (?:JOB|STEP) [\d.]+ ON \S+ CANCELLED AT (\S+)( DUE TO [A-Z ]+?)? \*\*\*")
_OOM = re.compile(r"oom[-_ ]kill|out of memory", re.IGNORECASE)
_ERROR_LINE = re.compile(r"^\S+ (?:ERROR|CRITICAL) ")
# the last line of a Python traceback ("recon.io.images.ImageError: <message>"), not Snakemake's
# own summary lines ("WorkflowError:", "CalledProcessError in file ...")
_EXCEPTION_LINE = re.compile(r"^(?:[A-Za-z_]\w*\.)*(?!WorkflowError)([A-Za-z_]\w*(?:Error|Exception|Interrupt)): \S.*")


@dataclass
class CaptureStatus:
    """Where one capture stands: ``status`` is "finished", "failed" or "not finished"."""

    capture: str
    status: str
    stages_done: list[str] = field(default_factory=list)
    failed_stage: str | None = None
    reason: str = ""
    log: str | None = None  # the file to read first


def _last_match(lines: list[str], pattern: re.Pattern) -> str | None:
    for line in reversed(lines):
        if pattern.search(line):
            return line.strip()
    return None


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(errors="replace").splitlines()
    except OSError:
        return []


def _slurm_logs(slurm_log_dir: Path | None, stage: str, capture: str) -> list[Path]:
    """The SLURM job logs of ``stage`` for ``capture``, newest last (a rule's or a group's)."""
    if slurm_log_dir is None or not slurm_log_dir.is_dir():
        return []
    found = list(slurm_log_dir.glob(f"rule_{stage}/{capture}/*.log"))
    # a group job's log (profiles/slurm groups stages: recon.stages) sits in group_<name>/ without
    # the capture
    for path in slurm_log_dir.glob("group_*/**/*.log"):
        text = path.read_text(errors="replace")
        if f"rule {stage}:" in text and f"wildcards: capture={capture}\n" in text:
            found.append(path)
    return sorted(found, key=lambda p: p.stat().st_mtime)


def _failure_reason(stage_log: Path, slurm_logs: list[Path]) -> tuple[str, str]:
    """(why the stage failed, the file that says so)."""
    job_log = slurm_logs[-1] if slurm_logs else None
    job_lines = _read_lines(job_log) if job_log else []
    killed = _last_match(job_lines, _SLURM_KILLED)
    if killed:
        m = _SLURM_KILLED.search(killed)
        why = (m.group(2) or "").strip().lower().replace("due to ", "") if m else ""
        what = f"killed by SLURM ({why})" if why else "cancelled in SLURM (scancel or preemption)"
        return f"{what} at {m.group(1) if m else '?'}", str(job_log)
    if _last_match(job_lines, _OOM):
        return "killed by SLURM: out of memory (raise the stage's mem_mb)", str(job_log)
    lines = _read_lines(stage_log)
    error = _last_match(lines, _ERROR_LINE)
    if error:
        return error.split(": ", 1)[-1], str(stage_log)
    for source, src_lines in ((job_log, job_lines), (stage_log, lines)):
        exc = _last_match(src_lines, _EXCEPTION_LINE)
        if exc:  # without the module path: "ImageError: <message>"
            return exc[_EXCEPTION_LINE.match(exc).start(1):], str(source)
    tail = next((line.strip() for line in reversed(lines) if line.strip()), "")
    return (f"stopped without an error message; last log line: {tail}" if tail
            else "stopped without an error message"), str(stage_log)


def capture_status(results: str | os.PathLike, capture: str,
                   slurm_log_dir: str | os.PathLike | None = None) -> CaptureStatus:
    """The :class:`CaptureStatus` of ``capture`` from its files under ``results``."""
    root = Path(results) / capture
    done = [s for s in STAGES if (root / "benchmarks" / f"{s}.tsv").is_file()]
    if (root / FINAL.output("html")).is_file() and FINAL.name in done:
        return CaptureStatus(capture, "finished", done, log=str(root / "report" / "index.html"))
    slurm_dir = Path(slurm_log_dir) if slurm_log_dir else None
    for stage in STAGES:  # the first stage that has a log but did not finish
        stage_log = root / "logs" / f"{stage}.log"
        if stage not in done and stage_log.is_file():
            reason, where = _failure_reason(stage_log, _slurm_logs(slurm_dir, stage, capture))
            return CaptureStatus(capture, "failed", done, stage, reason, where)
    nxt = next((s for s in STAGES if s not in done), None)
    return CaptureStatus(capture, "not finished", done, reason=(
        f"{nxt} did not run (the run was stopped, or a dry run)" if nxt else ""))


def run_summary(results: str | os.PathLike, captures: list[str],
                slurm_log_dir: str | os.PathLike | None = None) -> list[CaptureStatus]:
    """:func:`capture_status` of every capture, in the given order."""
    return [capture_status(results, c, slurm_log_dir) for c in captures]


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def format_summary(statuses: list[CaptureStatus], outcome: str) -> str:
    """The Markdown text of ``summary.md``."""
    counts = {k: sum(s.status == k for s in statuses) for k in ("finished", "failed", "not finished")}
    when = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        f"# Run summary ({when}; Snakemake: {outcome})",
        "",
        f"{len(statuses)} captures: {counts['finished']} finished, {counts['failed']} failed, "
        f"{counts['not finished']} not finished.",
        "",
        "| capture | status | stages done | failed stage | why | read |",
        "|---|---|---|---|---|---|",
    ]
    for s in statuses:
        lines.append(f"| {_cell(s.capture)} | {s.status} | {len(s.stages_done)}/{len(STAGES)} | "
                     f"{s.failed_stage or ''} | {_cell(s.reason)} | {_cell(s.log or '')} |")
    lines += ["", "A failed stage's own log is `<results>/<capture>/logs/<stage>.log`; on SLURM the "
              "job's output is in `.snakemake/slurm_logs/`. Fix the cause and run the same command "
              "again: finished stages are kept, and optimize resumes from its last checkpoint.", ""]
    return "\n".join(lines)


def write_run_summary(results: str | os.PathLike, captures: list[str], outcome: str,
                      slurm_log_dir: str | os.PathLike | None = ".snakemake/slurm_logs") -> Path:
    """Write ``<results>/summary.md`` and ``summary.json`` (atomically); return the .md path.

    ``outcome`` is the run's end as Snakemake saw it ("success" or "error").
    """
    statuses = run_summary(results, captures, slurm_log_dir)
    out = Path(results)
    out.mkdir(parents=True, exist_ok=True)
    md, js = out / "summary.md", out / "summary.json"
    for path, text in ((md, format_summary(statuses, outcome)),
                       (js, json.dumps({"outcome": outcome,
                                        "captures": [asdict(s) for s in statuses]}, indent=1))):
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        tmp.write_text(text)
        os.replace(tmp, path)
    failed = [s.capture for s in statuses if s.status == "failed"]
    log.info("run summary: %s (%d captures, failed: %s)", md, len(statuses), ", ".join(failed) or "none")
    return md
