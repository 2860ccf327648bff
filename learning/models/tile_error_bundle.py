"""The learned stop's bundle: a directory with manifest.json (the input columns, the
tile, c(tau) and the training record) and estimator.skops (a `TileErrorEstimator`), never
a pickle: skops loads only the types on `ALLOWED_TYPES`. The package ships one in
learning/bundled_estimate (`make estimate`); `noisestop train-estimate --out DIR` writes a
user's own.
"""
from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import skops.io as sio

from noisefeat.atomic import atomic_write
from noisefeat.errors import InputNotFound
from noisefeat.jsonout import json_default
from noisefeat.safeio import read_input, read_json
from noisefeat.userdata import find as find_user_file

from ..inputs.halves import check_curve, flip_c
from ..inputs.tile_features import FEATURE_NAMES
from .bundle_check import load_skops
from .tile_error import TileErrorEstimator

FORMAT = "noisestop-tile-error"
MANIFEST = "manifest.json"
ESTIMATOR_FILE = "estimator.skops"
BUNDLED_DIR = Path(__file__).parents[1] / "bundled_estimate"
#: a user's own bundle (`noisestop calibrate --criterion estimate` without --out), found first
USER_DIR = "estimate"
ALLOWED_TYPES = ["learning.models.tile_error.TileErrorEstimator",
                 "sklearn.ensemble._hist_gradient_boosting.predictor.TreePredictor"]


@dataclass(frozen=True)
class TileErrorBundle:
    """A loaded bundle: the `estimator`, the `tile` it was trained at, its c(tau)
    `calibration` ({"curve": [{"tau", "c"}, ...]}), where it came from (`source`) and the
    `training` record."""

    estimator: TileErrorEstimator
    tile: int
    calibration: dict[str, Any]
    source: str
    training: dict[str, Any] = field(default_factory=dict)

    def c(self, tau: float) -> float:
        """c(tau), interpolated in log between calibrated points; ValueError outside them."""
        return flip_c({**self.calibration, "source": self.source}, tau)

    def describe(self) -> dict[str, Any]:
        return {"kind": self.estimator.kind, "tile": self.tile, "source": self.source,
                "rows": self.training.get("rows"), "scenes": len(self.training.get("scenes", []))}


def save_tile_error_bundle(estimator: TileErrorEstimator, path: str | os.PathLike, *, tile: int,
                           calibration: dict[str, Any], training: dict[str, Any]) -> Path:
    """Write the bundle directory (estimator first, manifest last: a bundle without its
    manifest is not one)."""
    out = Path(path)
    out.mkdir(parents=True, exist_ok=True)
    check_curve(calibration.get("curve"))
    atomic_write(out / ESTIMATOR_FILE, sio.dumps(estimator))
    manifest = {"format": FORMAT, "tile": int(tile), "features": list(FEATURE_NAMES), "kind": estimator.kind,
                "calibration": calibration, "training": training}
    atomic_write(out / MANIFEST, json.dumps(manifest, indent=1, default=json_default).encode())
    return out


def load_tile_error_bundle(path: str | os.PathLike | None = None) -> TileErrorBundle:
    """The bundle at `path` (None: the user's own in the user data directory if they trained
    one, else the shipped one). InputNotFound when there is none; ValueError naming the file
    on anything damaged, foreign or trained on other inputs."""
    d = find_user_file(USER_DIR, BUNDLED_DIR) if path is None else Path(path)
    if not (d / MANIFEST).is_file():
        raise InputNotFound(f"{d}: not a noisestop estimate bundle (no {MANIFEST}); `make estimate` builds the "
                            "shipped one")
    return _load(d.resolve(), _signature(d))


def _signature(d: Path) -> tuple[tuple[int, int] | None, ...]:
    """What identifies a bundle's files on disk (modification time and size, None if absent)."""
    out = []
    for f in (d / MANIFEST, d / ESTIMATOR_FILE):
        try:
            st = f.stat()
            out.append((st.st_mtime_ns, st.st_size))
        except OSError:
            out.append(None)
    return tuple(out)


@functools.lru_cache(maxsize=4)
def _load(d: Path, signature: tuple[tuple[int, int] | None, ...]) -> TileErrorBundle:
    """The checked bundle of directory `d`, read once per process while its files are
    unchanged (`signature`): every render with the estimate would otherwise pay a second
    for the allow-listed skops load. A failed load is not kept."""
    manifest = read_json(d / MANIFEST, "manifest")          # one line naming the file if not JSON
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ValueError(f"{d / MANIFEST}: not a {FORMAT} manifest")
    if manifest.get("features") != list(FEATURE_NAMES):
        raise ValueError(f"{d / MANIFEST}: trained on other inputs ({manifest.get('features')}); this version "
                         f"reads {list(FEATURE_NAMES)}: retrain it")
    tile = manifest.get("tile")
    if not isinstance(tile, int) or isinstance(tile, bool) or tile <= 0:
        raise ValueError(f"{d / MANIFEST}: tile must be a positive integer, got {tile!r}")
    cal = manifest.get("calibration")
    if not isinstance(cal, dict):
        raise ValueError(f"{d / MANIFEST}: no calibration")
    try:
        check_curve(cal.get("curve"))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{d / MANIFEST}: {exc}") from None
    f = d / ESTIMATOR_FILE
    if not f.is_file():
        raise InputNotFound(f"{f}: missing")
    est = load_skops(read_input(f, "model"), ALLOWED_TYPES, f)     # a regular file within the model cap
    if not isinstance(est, TileErrorEstimator) or getattr(est, "n_features_in_", None) != len(FEATURE_NAMES):
        raise ValueError(f"{f}: not a fitted TileErrorEstimator on {len(FEATURE_NAMES)} inputs")
    return TileErrorBundle(est, tile, cal, str(d), manifest.get("training") or {})
