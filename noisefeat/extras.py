"""Optional parts of noisestop: which extra of `pip install 'noisestop[...]'` brings each
third-party package, and `require`, which imports one or says in one line what to install.

The core install (`pip install noisestop`) holds the feature base, learning, the stop rule
and the dataset format. Extras: `render` (Mitsuba, Dr.Jit, matplotlib), `serve` (FastAPI,
uvicorn, h11, Prometheus), `data` (flip-evaluator, Dask), `transfer` (torchvision), `all`.
A missing one raises `MissingExtra`, an ImportError whose message names the extra; the
command line prints it as its one error line.
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: top-level import name -> the extra that installs it (None: the core install)
EXTRA_OF: dict[str, str | None] = {
    "mitsuba": "render", "drjit": "render", "matplotlib": "render",
    "fastapi": "serve", "starlette": "serve", "uvicorn": "serve", "h11": "serve",
    "prometheus_fastapi_instrumentator": "serve", "prometheus_client": "serve",
    "flip_evaluator": "data", "dask": "data", "distributed": "data",
    "torchvision": "transfer",
    "OpenEXR": None, "PIL": None,
}


class MissingExtra(ImportError):
    """An optional package is not installed; the message names the extra that brings it."""

    def __init__(self, module: str, extra: str | None = None):
        top = module.split(".")[0]
        extra = EXTRA_OF.get(top) if extra is None else extra
        target = f"'noisestop[{extra}]'" if extra else "noisestop"
        what = f"the [{extra}] extra" if extra else "noisestop's core install"
        super().__init__(f"{top} is not installed (part of {what}): pip install {target}", name=top)
        self.extra = extra


def require(module: str, extra: str | None = None) -> ModuleType:
    """Import `module` (dotted names too) and return it; if its package is not installed,
    raise MissingExtra naming the extra (`extra`, else the one EXTRA_OF gives)."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if missing != module.split(".")[0]:
            raise                      # the package is there but something it needs is not
        raise MissingExtra(module, extra) from None


def missing_extra(exc: BaseException) -> MissingExtra | None:
    """`exc` as a MissingExtra if it says an optional package is not installed, else None
    (for import errors raised by plain `import` statements)."""
    if isinstance(exc, MissingExtra):
        return exc
    if isinstance(exc, ModuleNotFoundError):
        top = (exc.name or "").split(".")[0]
        if top in EXTRA_OF:
            return MissingExtra(top)
    return None
