"""Tests of the command line, and end-to-end runs across packages."""
