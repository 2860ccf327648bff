"""The `noisestop` sub-commands, a module per command family: each registers its arguments
and a handler that calls the packages (imported inside the handler, so `noisestop --help`
stays free of torch and Mitsuba). `arguments` holds the argument types they share."""
from __future__ import annotations

import argparse

from . import bench, dataset, evaluate, render, scenes, serve, train


def register(sub: argparse._SubParsersAction) -> None:
    """Every sub-command, in the order `noisestop --help` lists them."""
    scenes.register_scenes(sub)
    dataset.register(sub)
    scenes.register_features(sub)
    train.register(sub)
    evaluate.register(sub)
    render.register(sub)
    serve.register(sub)
    bench.register(sub)
