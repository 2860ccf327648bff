"""Optional parts of noisestop: which extra of `pip install 'noisestop[...]'` brings each
third-party package, and `require`, which imports one or says in one line what to install.

The core install (`pip install noisestop`) holds the feature base, learning, the stop rule
and the dataset format. Extras: `render` (Mitsuba, Dr.Jit, matplotlib), `serve` (FastAPI,
uvicorn, h11, Prometheus), `data` (flip-evaluator, Dask), `transfer` (torchvision), `all`.
A missing one raises `MissingExtra`, a ModuleNotFoundError whose message names the extra; the
command line prints it as its one error line.
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: top-level import name -> the extra that installs it (None: the core install)
EXTRA_OF: dict[str, str | None] = {
    "mitsuba": "render", "drjit": "render", "matplotlib": "render", "cmap": "render",
    "fastapi": "serve", "starlette": "serve", "anyio": "serve", "uvicorn": "serve", "h11": "serve",
    "prometheus_fastapi_instrumentator": "serve", "prometheus_client": "serve",
    "flip_evaluator": "data", "dask": "data", "distributed": "data",
    "torchvision": "transfer",
    "OpenEXR": None, "PIL": None,
}
#: extra -> the import names it brings (the first of each pair of aliases)
PACKAGES_OF: dict[str, tuple[str, ...]] = {
    "render": ("mitsuba", "drjit", "matplotlib", "cmap"),
    "serve": ("fastapi", "uvicorn", "h11", "prometheus_fastapi_instrumentator"),
    "data": ("flip_evaluator", "dask", "distributed"),
    "transfer": ("torchvision",),
}


class MissingExtra(ModuleNotFoundError):
    """An optional package is not installed; the message names the extra that brings it
    (`purpose`, if given, says what needs it)."""

    def __init__(self, module: str, extra: str | None = None, purpose: str | None = None):
        top = module.split(".")[0]
        extra = EXTRA_OF.get(top) if extra is None else extra
        if extra:
            how = f"it comes with the [{extra}] extra: pip install 'noisestop[{extra}]'"
        else:
            how = "it belongs to noisestop's core install: pip install noisestop"
        what = f"{purpose} need {top}, which is not installed" if purpose else f"{top} is not installed"
        super().__init__(f"{what}; {how}", name=top)
        self.extra = extra


def require(module: str, extra: str | None = None, purpose: str | None = None) -> ModuleType:
    """Import `module` (dotted names too) and return it; if it, or an optional package it
    needs, is not installed, raise MissingExtra naming the extra (`extra`, else the one
    EXTRA_OF gives) and, if given, `purpose`: what needs it."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top, missing = module.split(".")[0], (exc.name or "").split(".")[0]
        if missing == top and (extra or top in EXTRA_OF):
            raise MissingExtra(top, extra, purpose) from None
        if missing in EXTRA_OF:
            raise MissingExtra(missing, None, purpose) from None
        raise                      # not one of noisestop's packages: the plain error


def require_extra(extra: str) -> None:
    """Check that every package of `extra` imports (MissingExtra for the first that does not)."""
    for module in PACKAGES_OF[extra]:
        require(module, extra)


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
