"""Helpers shared by the tests (imported as `tests.support.<module>`), and the paths they use."""
from __future__ import annotations

from pathlib import Path

#: the repository root (the packages noisefeat, learning, renderer, service live here)
ROOT = Path(__file__).resolve().parents[2]
#: committed test data
FIXTURES = ROOT / "tests" / "fixtures"
#: the small committed dataset: 4 scenes x 16 blocks x 16 levels of 64x64 frames (`make fixture`)
FIXTURE_DATASET = FIXTURES / "dataset"
