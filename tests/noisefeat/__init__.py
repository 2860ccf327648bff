"""Tests of noisefeat."""
