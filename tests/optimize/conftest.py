import sys
from pathlib import Path

# the synthetic-capture helper beside these tests
sys.path.insert(0, str(Path(__file__).parent))
