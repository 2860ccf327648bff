"""The live render: the adaptive progressive loop (`adaptive`, `session`, `passloop`), the
tracer (`blocks`, `wavefront`), its budget, checkpoint, outputs and report (renderer/README.md)."""
