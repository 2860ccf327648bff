"""Everything an adaptive render needs, made once before its first pass (`prepare`): the
settings checked, the reference and the scene loaded, the spec resolved once knowing the
frame, the renderer and the criterion built. One place, so that the doors cannot drift apart."""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from learning.data.dataset_dir import find_stack
from learning.data.stack import Stack
from noisefeat.safeio import check_regular

from ..criteria import Criterion
from ..plugin_schema import noisestop_of
from ..spec import ARGUMENT, RenderSpec, checked, reference_settings, resolve
from .blocks import BlockRenderer
from .outputs import prepare_output_dir

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Reference:
    """What a render is compared with: `given` as the caller gave it (None: nothing), a
    labelled `stack` or an `image` (final_vs_reference only)."""

    given: Any = None
    stack: Stack | None = None
    image: np.ndarray | None = None


@dataclass(frozen=True)
class RenderPlan:
    """A render ready for its first pass: its `label` in reports, `scene` as the checkpoint
    records it (a built-in name, a file's path, a loaded scene's label), the resolved `spec`,
    the `renderer` (the caller closes it), `criterion`, `reference` and Mitsuba `variant`."""

    label: str
    scene: str
    spec: RenderSpec
    renderer: BlockRenderer
    criterion: Criterion
    reference: Reference
    variant: str


def prepare(scene: Any, given: Mapping[str, Any], *, reference: Any = None, source: str = ARGUMENT,
            plugin: Mapping[str, Any] | None = None, sensor: Any = None, integrator: Any = None,
            out: str | os.PathLike[str] | None = None) -> RenderPlan:
    """The `RenderPlan` of a render, or a one-line ValueError. `scene`: a built-in name, an XML path or
    a loaded ``mi.Scene``. `given`: the render spec's rows (None: not given), given by `source`. `plugin`:
    the ``noisestop`` properties under them (None: the scene's own integrator's, if it is one).
    `reference`: a labelled stack or dataset directory of this scene (its grid and levels become the
    defaults), or a reference image. `sensor` / `integrator`: instead of the scene's first sensor and
    own integrator. `out`: a folder checked writable before the scene loads."""
    from learning.data.relabel import observed
    from learning.data.variant import current_variant, select_variant

    from ..criteria import make_criterion
    from ..scenes.catalog import load_scene

    loaded, label = _scene_arg(scene, given)
    ref = load_reference(reference, label)
    values = checked(given)            # each given setting once: a bad one fails before anything loads
    if out is not None:
        prepare_output_dir(out)
    variant = select_variant() or current_variant()
    implied = reference_settings(ref.stack) if ref.stack is not None else {}
    scene_obj = scene if loaded else load_scene(scene, values.get("resolution", implied.get("resolution")),
                                                defines=values.get("defines"))
    own = noisestop_of(scene_obj.integrator())
    if own is not None:
        own.check()                    # a bad property: its one line, here
    spec = resolve(values, source=source, plugin=(own.settings if own else {}) if plugin is None else plugin,
                   reference=ref.stack, frame=_frame(scene_obj, sensor, label))
    if ref.stack is not None:
        ref = replace(ref, stack=observed(ref.stack, spec.tau))
    br = BlockRenderer(scene_obj, sensor=sensor, integrator=integrator, **spec.cut())
    try:
        crit = make_criterion(spec, None if ref.stack is None else ref.stack.thresholds)
        logger.info("%s: %s", label, spec.describe())
        _check_reference(ref, br)
    except BaseException:
        br.close()
        raise
    return RenderPlan(label, label if loaded else os.fspath(scene), spec, br, crit, ref, variant)


def _scene_arg(scene: Any, given: Mapping[str, Any]) -> tuple[bool, str]:
    """(whether `scene` is a loaded mi.Scene, its label); a one-line ValueError for what
    cannot be asked of a loaded scene."""
    if isinstance(scene, (str, os.PathLike)):
        from ..scenes.catalog import scene_label
        return False, scene_label(scene)
    from noisefeat.extras import require

    if not isinstance(scene, require("mitsuba").Scene):
        raise ValueError(f"scene must be an mi.Scene, an XML file path or a built-in scene name, "
                         f"got {type(scene).__name__}")
    if given.get("resolution") is not None:
        raise ValueError("resolution cannot be changed on an already-loaded mi.Scene: set the film's "
                         "width and height in the scene, or pass the XML file's path")
    if given.get("defines"):
        raise ValueError("defines (-D) set parameters while an XML file loads: pass the file's path, "
                         "not an already-loaded mi.Scene")
    try:                               # its id when the file or dict gave one
        sid = str(scene.id())
    except Exception:                  # an id is cosmetic: never fail a render over it
        sid = ""
    return True, sid if sid and not sid.startswith("_unnamed") else "scene"


def _frame(scene: Any, sensor: Any, label: str) -> tuple[int, int]:
    """(width, height): the film's crop of `sensor`, else of the scene's first sensor."""
    if sensor is None:
        sensors = scene.sensors()
        if not sensors:
            raise ValueError(f"{label}: the scene has no sensor (camera) to render from; add one")
        sensor = sensors[0]
    crop = sensor.film().crop_size()
    return int(crop[0]), int(crop[1])


def load_reference(reference: Stack | str | os.PathLike[str] | np.ndarray | None, label: str) -> Reference:
    """A reference as given: None, a stack or dataset directory (not yet labelled: the
    observer's tau is the spec's), or an image (EXR file or float [H, W, 3] array), which has
    no per-level errors, so no oracle thresholds."""
    if reference is None:
        return Reference()
    if isinstance(reference, np.ndarray):
        img = np.asarray(reference, np.float32)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"a reference image must be float [H, W, 3] linear RGB, got shape {img.shape}")
    elif isinstance(reference, (str, os.PathLike)) and (
            os.fspath(reference).lower().endswith(".exr")
            or (os.path.exists(reference) and not os.path.isdir(reference))):
        from learning.data.exr import read_exr

        if not os.path.lexists(reference):
            raise FileNotFoundError(f"{os.fspath(reference)}: reference image not found")
        check_regular(reference, "reference image")     # a device, a FIFO, a folder: one line saying which
        img = read_exr(reference)
    else:
        return Reference(reference, stack=find_stack(reference, label))
    finite = np.isfinite(img)
    if not finite.all():       # every figure would be NaN
        raise ValueError(f"the reference image has {int(finite.size - np.count_nonzero(finite))} non-finite "
                         f"value(s) (NaN/Inf) of {img.size}: a reference must be finite")
    return Reference(reference, image=img)


def _check_reference(ref: Reference, br: BlockRenderer) -> None:
    """One-line ValueError for a reference of other blocks or another size (a stack of
    another size is only warned about)."""
    st = ref.stack
    if st is not None:
        if tuple(st.grid) != tuple(br.grid):
            raise ValueError(f"{st.path}: reference grid {list(st.grid)} differs from "
                             f"the render's {list(br.grid)}: its thresholds are for other blocks")
        if (st.width, st.height) != (br.width, br.height):
            logger.warning("reference %s is %dx%d, the render %dx%d: thresholds compared anyway",
                           st.path, st.width, st.height, br.width, br.height)
    if ref.image is not None and ref.image.shape[:2] != (br.height, br.width):
        raise ValueError(f"the reference image is {ref.image.shape[1]}x{ref.image.shape[0]}, the render "
                         f"{br.width}x{br.height}: give a reference of the render's size")
