"""Project-wide rules checked on the source: import layout, documentation."""
