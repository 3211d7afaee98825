"""recon.logs.stage: the log file ends with the error (after its traceback), the terminal shows the
message without a Python traceback for a user error, with one for a bug (issue 21 item 5, issue 20
item 4). Each case runs a real Python process, as a workflow script runs."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from recon.config import ConfigError
from recon.logs import is_user_error, user_message

SCRIPT = """
import errno, logging, sys, time
from recon.logs import stage
from recon.config import ConfigError
with stage(sys.argv[1]):
    logging.getLogger("recon.test").info("working on it")
    {body}
print("not reached", flush=True)
"""


def _run(tmp_path, body, env=None):
    log = tmp_path / "logs" / "export.log"
    script = tmp_path / "script.py"
    script.write_text(SCRIPT.format(body=body))
    r = subprocess.run([sys.executable, str(script), str(log)], capture_output=True, text=True, timeout=120,
                       env={**os.environ, **(env or {})})
    return r, log


def test_user_error_message_alone_on_terminal_and_last_in_log(tmp_path):
    r, log = _run(tmp_path, "raise ConfigError(\"/data/cap/capture.yaml: optimize.iterations must be positive, got -3\")")
    assert r.returncode == 1
    assert "not reached" not in r.stdout
    assert "Traceback" not in r.stderr
    assert "recon export: error: /data/cap/capture.yaml: optimize.iterations must be positive, got -3" in r.stderr
    assert f"(log: {log})" in r.stderr
    assert "working on it" in r.stderr  # the stage's own log lines still reach the terminal
    text = log.read_text()
    lines = text.rstrip("\n").splitlines()
    assert lines[-1].endswith("ERROR recon.stage: export failed: /data/cap/capture.yaml: optimize.iterations "
                              "must be positive, got -3")
    assert "Traceback (most recent call last)" in text and "raise ConfigError" in text
    assert "working on it" in text


def test_traceback_on_terminal_when_asked(tmp_path):
    r, _ = _run(tmp_path, "raise ConfigError('bad')", env={"RECON_TRACEBACK": "1"})
    assert r.returncode == 1
    assert "Traceback (most recent call last)" in r.stderr and "recon export: error: bad" in r.stderr


def test_full_disk_is_a_user_error(tmp_path):
    r, log = _run(tmp_path, "raise OSError(errno.ENOSPC, 'No space left on device', '/data/results/demo/export')")
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert "No space left on device: '/data/results/demo/export'" in r.stderr
    assert "No space left on device: '/data/results/demo/export'" in log.read_text().splitlines()[-1]


def test_bug_shows_traceback_and_says_so(tmp_path):
    r, log = _run(tmp_path, "1 / 0")
    assert r.returncode == 1
    assert "Traceback (most recent call last)" in r.stderr
    assert "recon export: error: ZeroDivisionError: division by zero" in r.stderr
    assert "bug in recon" in r.stderr
    assert log.read_text().splitlines()[-1].endswith("export failed: ZeroDivisionError: division by zero")


def test_ctrl_c_exits_130_and_logs_it(tmp_path):
    log = tmp_path / "logs" / "masks.log"
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(SCRIPT.format(body="print('ready', flush=True); time.sleep(60)")))
    # SIGINT at its default in the child: a job started in the background of a non-interactive
    # shell (nohup ... &) inherits it ignored, and Python then never raises KeyboardInterrupt
    p = subprocess.Popen([sys.executable, str(script), str(log)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert p.stdout.readline().strip() == "ready"
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130
    assert "Traceback" not in err and "recon masks: interrupted" in err
    assert log.read_text().splitlines()[-1].endswith("masks interrupted")


def test_classification():
    assert is_user_error(ConfigError("x"))
    assert is_user_error(FileNotFoundError(2, "No such file or directory", "/a/b.png"))
    assert not is_user_error(ValueError("numpy said so"))
    assert not is_user_error(KeyError("k"))
    assert user_message(ConfigError("  names the file  ")) == "names the file"
    assert user_message(KeyError("k")) == "KeyError: 'k'"


@pytest.mark.parametrize("name", ["linearize", "masks", "poses", "init_mesh", "uv", "optimize", "export", "report"])
def test_every_workflow_script_runs_its_stage_inside_recon_logs_stage(repo_root, name):
    text = (repo_root / "workflow" / "scripts" / f"{name}.py").read_text()
    assert "with stage(snakemake.log[0]):" in text
    assert "configure(" not in text


def test_a_failing_stage_in_a_real_run(repo_root, tmp_path):
    """Snakemake's "check log file(s) for error details" now holds: the failed rule's log ends
    with the message that names the file; the terminal shows the message, no traceback."""
    from recon.io.images import write_png

    for k in range(3):  # all-black photos: no object can be found in them
        write_png(tmp_path / "caps" / "black" / "images" / f"{k:04d}.png", np.zeros((24, 32, 3)))
    res = tmp_path / "results"
    r = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "1", "--config",
                        f"captures={tmp_path / 'caps'}", f"results={res}", "preset=draft", "--",
                        f"{res}/black/masks/masks.json"], cwd=repo_root, capture_output=True, text=True,
                       timeout=600, env={**os.environ, "PYTHONPATH": str(repo_root)})
    text = r.stdout + r.stderr
    assert r.returncode == 1, text[-3000:]
    rule = re.search(r"^Error in rule (\w+):", text, re.M).group(1)
    log = Path(re.search(r"^\s+log: (\S+) \(check log file\(s\) for error details\)", text, re.M).group(1))
    assert log == res / "black" / "logs" / f"{rule}.log"
    last = log.read_text().rstrip("\n").splitlines()[-1]
    message = re.search(rf"ERROR recon\.stage: {rule} failed: (.+)$", last).group(1)
    # names what to fix: the photos (all black: the check names their folder and the flash)
    assert str(tmp_path / "caps" / "black" / "images") in message and "black" in message
    assert f"recon {rule}: error: {message}" in text and f"(log: {log})" in text
    assert "Traceback" not in text
    assert "Traceback (most recent call last)" in log.read_text()


def test_sigterm_unwinds_the_stage(tmp_path):
    """SIGTERM (Snakemake stopping a job, a batch system's time limit) inside a stage writing its
    folder: exit 143, 'terminated' last in the log, the temporary folder removed and the previous
    result untouched."""
    log = tmp_path / "logs" / "report.log"
    out = tmp_path / "report"
    out.mkdir()
    (out / "index.html").write_text("previous")
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(f"""
        import sys, time
        from recon.io.atomic import atomic_dir
        from recon.logs import stage
        with stage(sys.argv[1]):
            with atomic_dir({str(out)!r}) as tmp:
                (tmp / "index.html").write_text("half")
                print("ready", flush=True)
                time.sleep(60)
    """))
    p = subprocess.Popen([sys.executable, str(script), str(log)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    try:
        assert p.stdout.readline().strip() == "ready"
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 143
    assert "recon report: terminated" in err and "Traceback" not in err
    assert log.read_text().splitlines()[-1].endswith("report terminated")
    assert (out / "index.html").read_text() == "previous"
    assert sorted(q.name for q in tmp_path.iterdir()) == ["logs", "report", "script.py"]
