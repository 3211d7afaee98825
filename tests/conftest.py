"""Shared fixtures: paths to the repository, the shared real data, and a CPU Mitsuba variant."""

from __future__ import annotations

import os
from pathlib import Path

# before any plugin imports torch: see recon/__init__.py (OpenMP threads must not spin)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# before numpy, scipy or pycolmap load their OpenBLAS (it reads this once), for this process and
# the Snakemake runs it starts: OpenBLAS splits a large product over its threads and waits for
# all of them, so on a busy machine every call waits for a descheduled thread, and the waiting
# threads spin. The (N, 3) x (3, 3) projections of the voxel grids (recon/hull.py, recon/masks/vote.py)
# took 30x the wall seconds beside two busy processes (10 products of 2M points: 4.8 s, 0.14 s on
# one thread) and the tabletop masks of one capture 48 CPU s instead of 13 (issue 30). One thread
# gives the same products (OpenBLAS splits the rows, not the sums): the masks and initial mesh
# of a test capture are byte-identical. This is the tests' setting (the pipeline keeps OpenBLAS's
# default threads for a user; torch uses MKL and is not affected).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the repository; tests that need it skip when it is missing."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (it sits beside the repository in CI)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the CPU variant (tests never depend on a GPU)."""
    from recon.mi import load_variant

    return load_variant("llvm_ad_rgb")


@pytest.fixture
def drjit_single_thread():
    """drjit on one thread for the test, the thread count restored after.

    With several threads drjit's scatter-adds (the film's pixel sums, the backward pass's
    gradients) run in an order the scheduler picks, so the same render can differ in the last
    bits between two calls (tests/_float_sums.py). Tests whose property is bit equality of two
    computations ("zero offset is the collocated kernel bit for bit", "the same settings give the
    same files", "a resumed run ends where an uninterrupted one does") take this fixture; tests
    that compare within a tolerance derive it from the sums instead."""
    import drjit as dr

    from recon.mi import load_variant

    load_variant()
    old = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(old)


# ---- --cpu-durations=N: the tests that cost the most CPU seconds ----
# pytest's --durations reports wall time, which on a shared or busy machine says more about the
# neighbours than about the test. This reports the CPU seconds (user + system) each test phase
# took in this process, its drjit/torch threads and the subprocesses it waited for (Snakemake
# runs), so the suite's cost can be measured, and cut, under any load.
def pytest_addoption(parser):
    parser.addoption("--cpu-durations", type=int, default=None, metavar="N",
                     help="show the N test phases that took the most CPU seconds (0: all)")


def _cpu_seconds() -> float:
    import resource

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


_CPU_PHASES: list[tuple[float, str, str]] = []


# Each phase's CPU seconds go into the test's report (``user_properties``), which pytest-xdist
# carries from the worker that ran the test to the main process that prints the summary.
def _record_cpu(item, phase: str, seconds: float) -> None:
    item.user_properties.append((f"cpu_seconds_{phase}", seconds))


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    t0 = _cpu_seconds()
    yield
    _record_cpu(item, "setup", _cpu_seconds() - t0)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    t0 = _cpu_seconds()
    yield
    _record_cpu(item, "call", _cpu_seconds() - t0)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item):
    t0 = _cpu_seconds()
    yield
    _record_cpu(item, "teardown", _cpu_seconds() - t0)


def pytest_runtest_logreport(report):
    for key, seconds in report.user_properties:
        if key == f"cpu_seconds_{report.when}":
            _CPU_PHASES.append((seconds, report.when, report.nodeid))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    n = config.getoption("--cpu-durations")
    if n is None:
        return
    rows = sorted(_CPU_PHASES, reverse=True)
    total = sum(r[0] for r in rows)
    terminalreporter.write_sep("=", f"slowest {n or 'all'} test phases by CPU seconds (all phases: {total:.1f} s)")
    for cpu, phase, nodeid in rows[:n] if n else rows:
        terminalreporter.write_line(f"{cpu:8.2f}s {phase:<8} {nodeid}")
