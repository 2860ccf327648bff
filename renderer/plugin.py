"""The ``noisestop`` Mitsuba integrator: the adaptive loop inside ``mi.render``, wrapping a
nested integrator (``path`` if none) as Mitsuba's ``aov`` does::

    <integrator type="noisestop">
        <float name="tau" value="0.02"/>
        <integrator type="path"/>
    </integrator>

``mi.render`` returns [H, W, 5]: R, G, B and the AOVs ``spp`` and ``converged`` (1 where the
block stopped); ``integrator.result`` keeps the last `RenderResult`. Properties (the rows of
`renderer.settings.PLUGIN_ROWS`): ``criterion``, ``tau``, ``threshold``, ``offset``, ``quantile``,
``model``, ``exposure``, ``block``, ``tile``, ``min_spp``, ``max_spp``, ``step``, ``decide_skip``,
``decide_growth``, ``seed``, ``time_limit``, ``spp_budget``, ``quick_spp``, and ``progress``
(boolean); resolved as `renderer.render`'s arguments (source "scene plugin"), a bad one is one
ValueError line when the integrator is used. ``mi.render``'s nonzero ``spp`` is the max_spp, its
``seed`` adds to the resolved one.

Mitsuba's bindings take one base class per variant: `integrator_class` binds the methods of
`NoisestopIntegrator` to the variant's ``mi.SamplingIntegrator``; `register` needs a variant,
so importing does not register (`renderer.api.register_for` does, before a scene file loads).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from learning.data.variant import select_variant
from noisefeat.extras import require

from .plugin_schema import AOVS, CLASSES, PLUGIN, PROPERTIES, noisestop_of
from .scenes.plugin_libs import preload
from .spec import PLUGIN as FROM_PLUGIN
from .spec import resolve

_registered: set[str] = set()


class NoisestopIntegrator:
    """Adaptive sampling around a nested integrator: the methods `integrator_class` binds."""

    #: the variant's ``mi.SamplingIntegrator`` (set on the class `integrator_class` makes)
    base: Any = None

    def __init__(self, props: Any) -> None:
        mi = require("mitsuba")
        self.base.__init__(self, props)
        nested = [props[k] for k in props.keys()
                  if props.type(k) == mi.Properties.Type.Object and isinstance(props[k], mi.Integrator)]
        #: the integrator the samples come from (Mitsuba's path tracer if none is nested)
        self.nested = nested[0] if nested else mi.load_dict({"type": "path"})
        #: the last render's RenderResult (image, spp, converged, report)
        self.result = None
        #: a bad property's one-line message, raised when the integrator is used (module docstring)
        self.property_error: str | None = None
        #: the seed they resolve to, which ``mi.render``'s seed adds to (an int: Dr.Jit
        #: traverses an integrator's attributes, so the resolved spec itself is not kept)
        self.base_seed = 0
        self.progress = False
        # every property is read before anything is checked: Mitsuba refuses to load an
        # integrator that left one unread, with a message naming it instead of the cause
        #: the properties set (the render spec's rows, as given)
        self.settings: dict[str, Any] = {k: props[k] for k in PROPERTIES if k in props and k != "progress"}
        progress = props["progress"] if "progress" in props else False
        try:
            if len(nested) > 1:
                raise ValueError(f"the noisestop integrator wraps one integrator, got {len(nested)} nested ones")
            if nested and noisestop_of(nested[0]) is not None:
                raise ValueError("the noisestop integrator cannot wrap another noisestop integrator: nest the "
                                 "integrator that makes the samples (path, volpath, ...) in one noisestop")
            if not isinstance(progress, bool):
                raise ValueError(f"progress must be a boolean, got {progress!r}")
            self.progress = progress
            self.base_seed = resolve(self.settings, source=FROM_PLUGIN).seed
        except ValueError as exc:
            self.property_error = f"noisestop integrator: {exc}".replace(
                "noisestop integrator: noisestop integrator: ", "noisestop integrator: ")

    def check(self) -> None:
        """ValueError (one line) if a property was bad: raised where the integrator is used."""
        if self.property_error is not None:
            raise ValueError(self.property_error)

    def aov_names(self) -> list[str]:
        return list(AOVS)

    def render(self, scene: Any, sensor: Any = 0, seed: Any = 0, spp: int = 0, develop: bool = True,
               evaluate: bool = True) -> Any:
        """The adaptive render of `scene` from `sensor` as [H, W, 5] (R, G, B, spp, converged)."""
        from .live.adaptive import run_adaptive

        self.check()
        if not develop:
            raise ValueError("the noisestop integrator returns its developed image: call it with "
                             "develop=True (as mi.render does)")
        if isinstance(sensor, (int, np.integer)):
            sensors = scene.sensors()
            if not 0 <= int(sensor) < len(sensors):
                raise ValueError(f"sensor {int(sensor)} is out of range: the scene has {len(sensors)} sensor(s), "
                                 f"0 to {len(sensors) - 1}")
            sensor = sensors[int(sensor)]
        s = dict(self.settings)
        if int(spp) > 0:
            s["max_spp"] = int(spp)
        if _as_int(seed):
            s["seed"] = self.base_seed + _as_int(seed)
        self.result = result = run_adaptive(scene, source=FROM_PLUGIN, plugin={}, progress=self.progress,
                                            sensor=sensor, integrator=self.nested, **s)  # its settings, not the scene's
        data = np.concatenate([result.image, result.spp[..., None].astype(np.float32),
                               result.converged[..., None].astype(np.float32)], axis=-1)
        return require("mitsuba").TensorXf(np.ascontiguousarray(data))

    def traverse(self, callback: Any) -> None:
        callback.put("nested", self.nested, require("mitsuba").ParamFlags.NonDifferentiable)

    def to_string(self) -> str:
        inner = "\n".join("  " + line for line in str(self.nested).splitlines())
        return f"NoisestopIntegrator[\n  settings = {self.settings},\n  nested =\n{inner}\n]"


def integrator_class() -> type:
    """`NoisestopIntegrator` as an integrator of the variant that is set (`select_variant`'s
    if none is), made once per variant."""
    variant = select_variant()
    if variant not in CLASSES:
        mi = require("mitsuba")
        methods = {k: v for k, v in vars(NoisestopIntegrator).items() if k not in ("__dict__", "__weakref__")}
        CLASSES[variant] = type("NoisestopIntegrator", (mi.SamplingIntegrator,),
                                {**methods, "base": mi.SamplingIntegrator})
    return CLASSES[variant]


def _as_int(seed: Any) -> int:
    """mi.render's seed (an int, or a one-element Dr.Jit array on JIT variants) as an int."""
    try:
        return int(seed)
    except TypeError:
        return int(np.asarray(seed).ravel()[0])


def register() -> str:
    """Register the ``noisestop`` integrator with Mitsuba for the current variant (choosing one
    first, as `learning.data.variant.select_variant` does, if none is set), once; the variant."""
    mi = require("mitsuba")
    cls = integrator_class()
    preload()          # Mitsuba's plugin libraries from its own folder (the nested path one included)
    variant = mi.variant()
    if variant not in _registered:
        mi.register_integrator(PLUGIN, lambda props: cls(props))
        _registered.add(variant)
    return variant
