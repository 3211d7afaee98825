import sys
from pathlib import Path

# the synthetic-capture helper beside these tests
sys.path.insert(0, str(Path(__file__).parent))

import pytest  # noqa: E402


@pytest.fixture
def drjit_single_thread():
    """drjit on one thread for the test (float atomics of the renderer's backward pass in a fixed
    order: the same numbers on every run), the thread count restored after."""
    import drjit as dr

    from recon.mi import load_variant

    load_variant()
    old = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(old)
