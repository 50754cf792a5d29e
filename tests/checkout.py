"""Where the checkout's files are, for tests at any depth under tests/ (imported by them; the pytest
config puts this folder on sys.path). The root is the folder holding pyproject.toml, found by walking
up, so a test file can move between folders without its paths changing."""

from __future__ import annotations

from pathlib import Path

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
SCENARIOS = ROOT / "scenarios"
TEST_DATA = ROOT / "tests" / "data"
