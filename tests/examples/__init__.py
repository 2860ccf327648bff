"""Tests of the examples (examples/, run from a source checkout)."""
