"""Examples of the product at work, run from a source checkout (not installed, not in the
image): `showcase`, the demo `make run` runs (``python -m examples.showcase``)."""
