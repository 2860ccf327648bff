"""A demo model bundle fitted in well under a second and the infer requests a server is sent:
shared by the service tests and, from a source checkout, the benchmarks."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from service.oip import HEADER_LENGTH


def make_demo_bundle(path: str | os.PathLike, seed: int = 0, name: str = "demo", n: int = 160,
                     size: int = 32) -> Path:
    """A DSVM bundle for tests and benches, fitted in well under a second on synthetic blocks
    (smooth colour ramps, as quick images, plus Gaussian noise of random strength; +1 where
    the noise is weak). Its verdicts mean nothing about real renders; its inputs and costs
    are those of a real feature model."""
    from learning.models.bundle import save_model
    from learning.models.estimators import DSVM
    from noisefeat import extract_features
    rng = np.random.default_rng(seed)
    ramp = np.linspace(0.0, 1.0, size, dtype=np.float32)[None, :, None, None]
    quick = (0.1 + 0.6 * rng.random((n, 1, 1, 3), dtype=np.float32) * ramp).repeat(size, 2)
    sigma = rng.uniform(0.0, 0.2, n).astype(np.float32)
    current = quick + sigma[:, None, None, None] * rng.standard_normal(quick.shape, dtype=np.float32)
    X = extract_features(quick) - extract_features(current)
    y = np.where(sigma < 0.05, 1, -1)
    return save_model(DSVM(C=10.0).fit(X, y), path, kind="dsvm", input="features", name=name,
                      training={"data": f"{n} synthetic {size}x{size} blocks (demo)"})



#: the two image inputs of a request, by what the served model reads
IMAGE_INPUTS = {"blocks": ("blocks", "quick"), "halves": ("even", "odd")}


def make_request(blocks: int = 16, size: int = 128, binary: bool = False, seed: int = 0,
                 inputs: str = "blocks") -> tuple[bytes, dict[str, str]]:
    """(body, headers) of one infer request for `blocks` random blocks and their quick images
    (`inputs` 'blocks'), or their two half buffers (`inputs` 'halves')."""
    rng = np.random.default_rng(seed)
    current = rng.random((blocks, size, size, 3), dtype=np.float32)
    other = (0.5 * current + 0.25).astype(np.float32) if inputs == "blocks" else \
        np.clip(current + rng.normal(0, 0.02, current.shape), 0, None).astype(np.float32)
    named = tuple(zip(IMAGE_INPUTS[inputs], (current, other)))
    shape = list(current.shape)
    outputs = [{"name": n, "parameters": {"binary_data": binary}} for n in ("verdict", "score")]
    if not binary:
        tensors = [{"name": n, "shape": shape, "datatype": "FP32", "data": a.ravel().tolist()} for n, a in named]
        return json.dumps({"inputs": tensors, "outputs": outputs}).encode(), \
            {"Content-Type": "application/json"}
    tensors = [{"name": n, "shape": shape, "datatype": "FP32", "parameters": {"binary_data_size": a.nbytes}}
               for n, a in named]
    header = json.dumps({"inputs": tensors, "outputs": outputs}).encode()
    return header + current.tobytes() + other.tobytes(), \
        {"Content-Type": "application/octet-stream", HEADER_LENGTH: str(len(header))}
