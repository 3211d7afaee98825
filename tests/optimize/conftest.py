import sys
from pathlib import Path

# the synthetic-capture helper beside these tests (drjit_single_thread: tests/conftest.py)
sys.path.insert(0, str(Path(__file__).parent))
