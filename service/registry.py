"""The models a server holds, by name, and how one of them answers an inference request.

Every server serves its first model also as `default` (DESIGN.md "HTTP API"). Inference is
called from worker threads: the estimators only read their fitted arrays (libsvm's
predict and StandardScaler.transform keep no state) and the feature base runs under
torch.inference_mode; its per-block-size operator cache is a locked, byte-bounded LRU
(noisefeat.cache) whose worst race is computing one entry twice, and `load` warms it up
(and builds the shared feature base) before the first request arrives. Every model must
answer that warm-up inference, or the server does not start.
"""
from __future__ import annotations

import logging
import math
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from learning.models.bundle import BUNDLED_DIR, MANIFEST, Model, load_model
from learning.models.bundle_check import read_manifest
from learning.models.noise_target import tau_range
from learning.names import DEFAULT_TAU
from learning.stoprule import check_offset
from noisefeat.base import MIN_SIZE

from .oip import ApiError, ModelMetadata, TensorMetadata

log = logging.getLogger(__name__)

DEFAULT = "default"
PLATFORM = "noisestop-sklearn"
PLATFORM_IMAGE = "noisestop-torch"     # the transfer baselines: a torchvision base + a torch head
INPUT_NAMES = ("blocks", "quick", "features")
OUTPUTS = {"verdict": "INT8", "score": "FP32"}
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def bundle_name(path: str | None) -> str:
    """The name a bundle's manifest gives it (None: the bundled model)."""
    where = BUNDLED_DIR if path is None else Path(path)
    if where.is_file() and where.name == MANIFEST:    # as load_model: the manifest names its bundle
        where = where.parent
    manifest = where / MANIFEST
    if not manifest.is_file():
        if path is None:
            raise FileNotFoundError(
                f"no model is bundled with this noisestop ({BUNDLED_DIR} holds no {MANIFEST}): "
                f"pass --model PATH (a bundle written by `noisestop train`)")
        raise FileNotFoundError(f"{where}: not a noisestop model bundle (no {MANIFEST})")
    meta = read_manifest(manifest)      # schema-checked (learning.models.bundle_check)
    return str(meta.get("name") or meta["kind"])


def parse_model_specs(specs: list[str] | None) -> dict[str, str | None]:
    """`--model` values (PATH or NAME=PATH) -> {name: path}; none -> the bundled model.

    A bare PATH takes the name its manifest gives. Names are URL-safe and unique, and
    `default` is reserved for the alias of the first model.
    """
    if not specs:
        return {bundle_name(None): None}
    models: dict[str, str | None] = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or Path(spec).exists():
            name, path = bundle_name(spec), spec
        if not _NAME.match(name) or name == DEFAULT:
            raise ValueError(f"--model {spec}: model name {name!r} must be 1-64 letters, digits, "
                             f"'_', '.', '-' and not {DEFAULT!r}")
        if name in models:
            raise ValueError(f"--model {spec}: two models are named {name!r}; name them (NAME=PATH)")
        models[name] = path
    return models


@dataclass
class ServedModel:
    """One loaded bundle and the request-level rules of its inputs and outputs."""

    name: str
    model: Model
    load_seconds: float
    version: str = "1"
    offset: float | None = None     # `serve --offset`: overrides the model's calibrated offset
    tau: float | None = None        # `serve --tau`: the noise target (None: the model's own calibration)

    @property
    def effective_offset(self) -> float:
        return self.model.offset_at(self.tau) if self.offset is None else float(self.offset)

    def offset_for(self, offset: float | None, tau: float | None) -> float:
        """The offset a request's verdicts are made at: its own `offset`, else the model's
        calibrated offset at its `tau`, else the server's (`--offset`, else `--tau`'s);
        a tau the model was not calibrated for is a 400 naming the range."""
        if offset is not None:
            return float(offset)
        if tau is None:
            return self.effective_offset
        try:
            return self.model.offset_at(tau)
        except ValueError as exc:
            raise ApiError(400, str(exc)) from None

    @property
    def inputs(self) -> list[TensorMetadata]:
        """Raw-block and quick-'none' models accept (and ignore) `quick`: one client serves all.
        `halves` models take the half buffers `even` and `odd` instead of `blocks`; only
        feature models take `features` (an image classifier reads pictures)."""
        image = [-1, -1, -1, 3]
        if self.model.needs_halves:
            inputs = [TensorMetadata(name="even", datatype="FP32", shape=image),
                      TensorMetadata(name="odd", datatype="FP32", shape=image)]
        else:
            inputs = [TensorMetadata(name="blocks", datatype="FP32", shape=image),
                      TensorMetadata(name="quick", datatype="FP32", shape=image)]
        if self.model.input == "features":
            inputs.append(TensorMetadata(name="features", datatype="FP32", shape=[-1, self.model.n_features]))
        return inputs

    def image_inputs(self, blocks: np.ndarray) -> dict[str, np.ndarray]:
        """The request tensors that ask about `blocks` as this model reads them (both half
        buffers equal to the block for a `halves` model, the block as its own quick image
        otherwise): warm-up and the stability matrix."""
        if self.model.needs_halves:
            return {"even": blocks, "odd": blocks}
        return {"blocks": blocks, "quick": blocks} if self.model.needs_quick else {"blocks": blocks}

    def metadata(self, name: str | None = None) -> ModelMetadata:
        m = self.model.manifest
        lo, hi = tau_range(m)
        params: dict[str, Any] = {"kind": str(m.get("kind")), "input": self.model.input, "quick": self.model.quick,
                                  "offset": self.effective_offset, "calibrated_offset": self.model.offset,
                                  "tau": self.tau, "tau_range": [lo, hi]}
        if self.model.input == "image":    # what its base transfers, and the one block size it reads
            params.update(base=self.model.label, block=list(self.model.block_shape or ()))
        else:
            params["n_features"] = int(m.get("n_features", 0))
        return ModelMetadata(
            name=name or self.name, versions=[self.version],
            platform=PLATFORM_IMAGE if self.model.input == "image" else PLATFORM, inputs=self.inputs,
            outputs=[TensorMetadata(name=k, datatype=v, shape=[-1]) for k, v in OUTPUTS.items()],
            parameters=params)

    def infer(self, tensors: dict[str, np.ndarray], exposure: float = 0.0, offset: float | None = None,
              tau: float | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """({verdict int8 [N], score float32 [N]}, response parameters); bad input -> 400.

        Verdicts come from the one stop rule at `offset_for(offset, tau)` (the request's
        offset, else the model's at the request's noise target tau, else the server's);
        blocks whose display image is flat are converged whatever their score (rows of
        `features` carry no image: no flat test)."""
        self._check_names(tensors)
        offset = self.offset_for(offset, tau)
        params: dict[str, Any] = {"offset": offset}
        if tau is not None or self.tau is not None:
            params["tau"] = float(tau if tau is not None else self.tau)  # type: ignore[arg-type]
        try:
            if "features" in tensors:
                verdict, score = self.model.score_inputs(self._features(tensors), offset)
            elif self.model.needs_halves:
                even, odd = self._halves(tensors)
                verdict, score, bad = self.model.assess_halves(even, odd, exposure=exposure, offset=offset,
                                                               tau=params.get("tau", DEFAULT_TAU))
                params["nonfinite_pixels"] = [int(c) for c in bad]
            else:
                blocks, quick = self._blocks(tensors)
                if not self.model.needs_quick:
                    quick = None  # raw-block and quick-'none' models read the current block only
                verdict, score, bad = self.model.assess_blocks(blocks, quick, exposure=exposure, offset=offset)
                params["nonfinite_pixels"] = [int(c) for c in bad["blocks"]]
                if self.model.needs_quick:
                    params["nonfinite_quick_pixels"] = [int(c) for c in bad["quick"]]
        except ValueError as exc:  # what the feature base and estimator reject
            raise ApiError(400, str(exc)) from None
        return {"verdict": verdict, "score": np.asarray(score, np.float32)}, params

    def _check_names(self, tensors: dict[str, np.ndarray]) -> None:
        unknown = sorted(set(tensors) - {t.name for t in self.inputs})
        if unknown:
            raise ApiError(400, f"model {self.name!r} has no input {unknown[0]!r}; it takes "
                                f"{[t.name for t in self.inputs]}")
        for name, arr in tensors.items():
            if arr.dtype != np.float32:
                raise ApiError(400, f"input {name!r} must be FP32")

    def _features(self, tensors: dict[str, np.ndarray]) -> np.ndarray:
        if len(tensors) > 1:
            images = "'even' and 'odd'" if self.model.needs_halves else "'blocks' (+ 'quick')"
            raise ApiError(400, f"send either 'features' or {images}, not both")
        X = tensors["features"]
        n = self.model.n_features
        if X.ndim != 2 or X.shape[1] != n:
            raise ApiError(400, f"input 'features' must have shape [N, {n}], got {list(X.shape)}")
        return X

    def _halves(self, tensors: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        even, odd = tensors.get("even"), tensors.get("odd")
        if even is None or odd is None:
            raise ApiError(400, f"model {self.name!r} reads the half buffers of every block: send "
                                "'even' and 'odd' (the means of the even and odd passes), FP32 [N, H, W, 3]")
        if even.ndim != 4 or even.shape[-1] != 3:
            raise ApiError(400, f"input 'even' must have shape [N, H, W, 3], got {list(even.shape)}")
        if odd.shape != even.shape:
            raise ApiError(400, f"inputs 'even' {list(even.shape)} and 'odd' {list(odd.shape)} must have "
                                "the same shape")
        if len(even) and min(even.shape[1:3]) < MIN_SIZE:
            raise ApiError(400, f"blocks must be at least {MIN_SIZE}x{MIN_SIZE} pixels, got "
                                f"{even.shape[1]}x{even.shape[2]}")
        return even, odd

    def _blocks(self, tensors: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray | None]:
        blocks, quick = tensors.get("blocks"), tensors.get("quick")
        if blocks is None:
            raise ApiError(400, f"model {self.name!r} needs input 'blocks'"
                                + (" and 'quick'" if self.model.needs_quick else ""))
        if blocks.ndim != 4 or blocks.shape[-1] != 3:
            raise ApiError(400, f"input 'blocks' must have shape [N, H, W, 3], got {list(blocks.shape)}")
        if len(blocks) and min(blocks.shape[1:3]) < MIN_SIZE:
            raise ApiError(400, f"blocks must be at least {MIN_SIZE}x{MIN_SIZE} pixels, got "
                                f"{blocks.shape[1]}x{blocks.shape[2]}")
        if quick is not None and quick.shape != blocks.shape:
            raise ApiError(400, f"inputs 'quick' {list(quick.shape)} and 'blocks' "
                                f"{list(blocks.shape)} must have the same shape")
        if self.model.input == "raw":
            n = int(self.model.manifest.get("n_features", 0))
            if blocks.shape[1] * blocks.shape[2] != n:
                raise ApiError(400, f"model {self.name!r} reads raw blocks of {n} pixels, got "
                                    f"{blocks.shape[1]}x{blocks.shape[2]}")
        elif quick is None and self.model.needs_quick:
            raise ApiError(400, f"model {self.name!r} needs input 'quick' (the quick image of every block)")
        return blocks, quick


@dataclass
class ModelRegistry:
    """Models by name (insertion order; the first is also `default`)."""

    specs: dict[str, str | None]
    models: dict[str, ServedModel] = field(default_factory=dict)
    offset: float | None = None     # `serve --offset`, for every model served
    tau: float | None = None        # `serve --tau`, for every model served

    def __post_init__(self) -> None:
        if self.offset is not None:
            self.offset = check_offset(self.offset)
        if not self.specs:
            self.specs = parse_model_specs(None)
        if DEFAULT in self.specs:
            raise ValueError(f"{DEFAULT!r} is reserved for the alias of the first model")

    @property
    def ready(self) -> bool:
        return len(self.models) == len(self.specs)

    @property
    def default_name(self) -> str:
        return next(iter(self.specs))

    def load(self) -> None:
        """Load every model not yet loaded (clear FileNotFoundError/ValueError on failure)."""
        for name, path in self.specs.items():
            if name in self.models:
                continue
            if path is None:
                bundle_name(None)  # the clear message when nothing is bundled
            t0 = time.perf_counter()
            model = load_model(path)
            served = ServedModel(name, model, time.perf_counter() - t0,
                                 version=str(model.manifest.get("model_version", "1")), offset=self.offset,
                                 tau=self.tau)
            if self.offset is None and self.tau is not None:
                try:
                    model.offset_at(self.tau)
                except ValueError as exc:
                    raise ValueError(f"model {name} ({path or 'the bundled model'}): {exc}") from None
            try:
                _warm_up(served)
            except Exception as exc:   # whatever the model raises, serve stops here with one line
                raise ValueError(f"model {name} ({path or 'the bundled model'}) failed its warm-up "
                                 f"inference: {type(exc).__name__}: {getattr(exc, 'message', exc)}") from None
            self.models[name] = served
            log.info("model %s loaded from %s in %.2f s (%s, input %s, offset %.3g%s)", name,
                     path or "the bundled model", served.load_seconds,
                     model.manifest.get("kind"), model.input, served.effective_offset,
                     "" if self.offset is None else f" by --offset, calibrated {model.offset:.3g}")

    def get(self, name: str, version: str | None = None) -> ServedModel:
        served = self.models.get(self.default_name if name == DEFAULT else name)
        if served is None:
            raise ApiError(404, f"unknown model {name!r}; this server has {self.names()}")
        if version is not None and version != served.version:
            raise ApiError(404, f"model {name!r} has no version {version!r} (versions: [{served.version!r}])")
        return served

    def names(self) -> list[str]:
        return [DEFAULT, *self.specs]


def _warm_up(served: ServedModel) -> None:
    """One tiny inference through the very route requests take: builds the shared feature
    base before threads race for it, and a model that cannot answer fails here, before
    the port is bound, instead of at its first request."""
    side = 32
    if served.model.input == "raw":
        n = served.model.n_features
        side = next((h for h in range(MIN_SIZE, math.isqrt(n) + 1) if n % h == 0 and n // h >= MIN_SIZE), 0)
        if not side:
            return                         # no block of >= 8x8 pixels has n pixels: nothing to ask
        blocks = np.full((1, side, n // side, 3), 0.5, np.float32)
    elif served.model.input == "image":    # an image classifier reads its training block size
        blocks = np.full((1, *served.model.block_shape, 3), 0.5, np.float32)
    else:
        blocks = np.full((1, side, side, 3), 0.5, np.float32)
    arrays, _ = served.infer(served.image_inputs(blocks))
    if arrays["verdict"].shape != (1,) or not np.isfinite(arrays["score"]).all():
        raise ValueError(f"answered {arrays['verdict'].shape} verdicts and scores {arrays['score'].tolist()} "
                         "for one block")
