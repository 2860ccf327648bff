"""The exceptions every package raises for inputs that are not there, each a ValueError.

Why: the Python API (DESIGN "Python API": `learning.load_model`, `learning.read_stack`,
`renderer.render`) promises ValueError for a bad argument, and a path naming nothing is one;
subclassing FileNotFoundError too keeps code that catches that working.
"""
from __future__ import annotations


class InputNotFound(ValueError, FileNotFoundError):
    """A file or directory an argument names (model bundle, stack, scene file, reference,
    token file) is not there."""
