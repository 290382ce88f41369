"""Puts tests/ on the import path, so every test folder (unit, integration, deploy) imports the shared test
code as `support` (tests/support/)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
