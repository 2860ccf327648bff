"""Import of the LISIC (prise-3d) human-threshold datasets into format v1 stacks.

Layout (REFERENCES "LISIC layout"):

```
<src>/<Scene>/config              # 5 lines: last image, prefix, start index, end index, step
<src>/<Scene>/<Scene>_00020.png   # 8-bit sRGB display images, number = spp (zero padded)
<src>/<Scene>/zone00/seuilExpe    # one integer: the human threshold of block 0, in spp
...           zone15/seuilExpe
```

Zones are numbered row-major like our blocks: the LISIC code cuts images with
`ipfml.processing.divide_in_blocks`, whose outer loop runs over rows, and matches the
n-th block with zoneNN.

What the import writes (and why):

* levels: linear RGB = inverse sRGB of the PNG values, stored as EXR. The data are
  display-referred (values never exceed 1, quantised to 8 bits): meta says so in
  `"import"`; the display transform gives the PNG back exactly.
* reference: the highest-spp image (it is also the last level); `reference_spp` = its spp.
* quick: none exists; meta `"quick": "none"`, no quick.exr (see `learning.data.stack_format`).
  Writing a copy of the reference instead would leak the answer into the model input.
* thresholds: the human integers in zone order, unchanged (they need not be level spp);
  labeler `{"name": "human", "source": "LISIC"}`.

The import goes through `StackWriter`, so an interrupted import resumes.
"""
from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from noisefeat.safeio import read_input

from .exr import read_png
from .frame_flip import srgb_decode
from .stack_format import QUICK_NONE, block_shape
from .stack_write import StackWriter, make_plan

log = logging.getLogger(__name__)

THRESHOLD_FILE = "seuilExpe"
CONFIG_FILE = "config"
LABELER = {"name": "human", "source": "LISIC"}


@dataclass
class LisicScene:
    """One LISIC scene directory, parsed but not yet read."""

    name: str
    path: Path
    images: list[tuple[int, Path]]  # (spp, png), spp strictly increasing
    thresholds: list[int]           # zone order


def _zone_dir(scene: Path, z: int) -> Path:
    return scene / f"zone{z:02d}"


def read_threshold(path: Path) -> int:
    """The integer of one seuilExpe file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing human threshold file")
    text = read_input(path, "LISIC file").decode("utf-8", errors="replace")
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if len(lines) < 1:
        raise ValueError(f"{path}: empty; expected one integer (samples per pixel)")
    try:
        value = int(lines[0])
    except ValueError:
        raise ValueError(f"{path}: expected one integer (samples per pixel), "
                         f"got {lines[0][:40]!r}") from None
    if value <= 0:
        raise ValueError(f"{path}: threshold must be a positive number of spp, got {value}")
    return value


def read_config(path: Path) -> tuple[str, int, int, int, int]:
    """config -> (prefix, start, end, step, index width)."""
    lines = [ln.strip() for ln in read_input(path, "LISIC file").decode("utf-8", errors="replace")
             .splitlines()]
    lines = [ln for ln in lines if ln]
    if len(lines) < 5:
        raise ValueError(f"{path}: expected 5 lines (last image, prefix, start index, end "
                         f"index, step), got {len(lines)}")
    _, prefix, start_s, end_s, step_s = lines[:5]
    try:
        start, end, step = int(start_s), int(end_s), int(step_s)
    except ValueError:
        raise ValueError(f"{path}: start/end/step must be integers, got "
                         f"{start_s!r}, {end_s!r}, {step_s!r}") from None
    if step <= 0 or end < start:
        raise ValueError(f"{path}: images would not have increasing spp (start {start}, "
                         f"end {end}, step {step})")
    if start <= 0:
        raise ValueError(f"{path}: start index {start} is not a positive spp")
    return prefix, start, end, step, len(start_s)


def _images_from_config(scene: Path) -> list[tuple[int, Path]]:
    cfg = scene / CONFIG_FILE
    prefix, start, end, step, width = read_config(cfg)
    images = [(s, scene / f"{prefix}{s:0{width}d}.png") for s in range(start, end + 1, step)]
    missing = [p.name for _, p in images if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"{scene}: {len(missing)} image(s) listed by {cfg.name} are "
                                f"missing: {', '.join(missing[:5])}")
    return images


def _images_from_names(scene: Path) -> list[tuple[int, Path]]:
    pattern = re.compile(rf"^{re.escape(scene.name)}_(\d+)\.png$")
    found: dict[int, Path] = {}
    for p in sorted(scene.iterdir()):
        m = pattern.match(p.name)
        if not m:
            continue
        s = int(m.group(1))
        if s <= 0:
            raise ValueError(f"{p}: spp {s} is not positive")
        if s in found:
            raise ValueError(f"{scene}: two images for spp {s}: {found[s].name} and {p.name}; "
                             "spp must be strictly increasing")
        found[s] = p
    return sorted(found.items())


def scan_scene(scene: str | os.PathLike, grid: Sequence[int] = (4, 4)) -> LisicScene:
    """Parse one scene directory (zones, thresholds, image list); reads no image."""
    scene = Path(scene)
    n = int(grid[0]) * int(grid[1])
    missing = [_zone_dir(scene, z).name for z in range(n) if not _zone_dir(scene, z).is_dir()]
    if missing:
        raise FileNotFoundError(f"{scene}: missing zone folder(s) {', '.join(missing)} "
                                f"(a {grid[0]}x{grid[1]} grid needs zone00..zone{n - 1:02d})")
    extra = sorted(p.name for p in scene.glob("zone*") if p.is_dir()
                   and re.fullmatch(r"zone\d+", p.name) and int(p.name[4:]) >= n)
    if extra:
        raise ValueError(f"{scene}: more zones than the {grid[0]}x{grid[1]} grid has blocks: "
                         f"{', '.join(extra)}")
    thresholds = [read_threshold(_zone_dir(scene, z) / THRESHOLD_FILE) for z in range(n)]
    if (scene / CONFIG_FILE).is_file():
        images = _images_from_config(scene)
    else:
        log.warning("%s: no %s file; taking images named %s_NNNNN.png", scene, CONFIG_FILE,
                    scene.name)
        images = _images_from_names(scene)
    if not images:
        raise FileNotFoundError(f"{scene}: no images {scene.name}_NNNNN.png found")
    return LisicScene(scene.name, scene, images, thresholds)


def find_scenes(src: str | os.PathLike) -> list[Path]:
    """Scene directories under `src` (or `src` itself if it is one): they hold zone00/."""
    src = Path(src)
    if not src.is_dir():
        raise FileNotFoundError(f"{src}: no such LISIC dataset directory")
    if (src / "zone00").is_dir():
        return [src]
    return sorted(p for p in src.iterdir() if p.is_dir() and (p / "zone00").is_dir())


def _load_linear(path: Path, shape: tuple[int, int, int] | None, first: Path | None) -> np.ndarray:
    img = read_png(path)
    if shape is not None and img.shape != shape:
        raise ValueError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, but {first.name} is "
                         f"{shape[1]}x{shape[0]}; all images of a scene must have one size")
    return srgb_decode(img)


def import_scene(scene: LisicScene, out: Path, *, grid: Sequence[int] = (4, 4),
                 every: int = 1, half: bool = False) -> Path:
    """Write one parsed scene as a stack in `out`/<name>; returns its directory."""
    images = scene.images[::every]
    if images[-1] != scene.images[-1]:
        images.append(scene.images[-1])  # the reference level is always kept
    first_path = images[0][1]
    first = read_png(first_path)
    shape = first.shape
    try:
        block_shape(shape[0], shape[1], grid)
    except ValueError as exc:
        raise ValueError(f"{first_path}: {exc}") from None
    spp = [s for s, _ in images]
    top = max(scene.thresholds)
    if top > spp[-1]:
        log.warning("%s: a human threshold (%d spp) exceeds the last image (%d spp)",
                    scene.path, top, spp[-1])
    plan = make_plan(scene=scene.name, width=shape[1], height=shape[0], spp=spp,
                     reference_spp=spp[-1], quick=QUICK_NONE, renderer="LISIC (unknown)",
                     grid=grid,
                     source={"format": "LISIC", "scene": scene.name},
                     **{"import": "display-referred: levels are the inverse sRGB of 8-bit "
                                  "PNGs; reference = highest-spp image (also the last "
                                  "level); no quick image"})
    dest = Path(out) / scene.name
    w = StackWriter(dest, plan, half=half)
    if not w.is_complete:  # a complete stack only gets its thresholds refreshed
        for s, p in images:
            if not w.has_level(s):
                w.write_level(s, _load_linear(p, shape, first_path))
        if not w.has_reference():
            w.write_reference(_load_linear(images[-1][1], shape, first_path))
    w.finish(scene.thresholds, LABELER)
    log.info("%s: imported %d levels (%d..%d spp) into %s", scene.name, len(spp), spp[0],
             spp[-1], dest)
    return dest


def import_lisic(src: str | os.PathLike, out: str | os.PathLike, *,
                 scenes: Sequence[str] | None = None, grid: Sequence[int] = (4, 4),
                 every: int = 1, half: bool = False, strict: bool = True) -> list[Path]:
    """Import every LISIC scene of `src` into `out`; returns the stack directories.

    `scenes` restricts to these names; `every` keeps one image in `every` (the last is
    always kept: 500 float EXR levels of 800x800 take 3.8 GB); `half` stores levels as
    half floats (enough for 8-bit sources). With `strict=False` a bad scene is logged and
    skipped instead of stopping the import.
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    dirs = find_scenes(src)
    if scenes is not None:
        wanted = set(scenes)
        unknown = wanted - {d.name for d in dirs}
        if unknown:
            raise ValueError(f"{src}: no LISIC scene named {', '.join(sorted(unknown))}")
        dirs = [d for d in dirs if d.name in wanted]
    if not dirs:
        raise FileNotFoundError(f"{src}: no LISIC scene (a folder with zone00/) found")
    done = []
    for d in dirs:
        try:
            done.append(import_scene(scan_scene(d, grid), Path(out), grid=grid, every=every,
                                     half=half))
        except (ValueError, FileNotFoundError) as exc:
            if strict:
                raise
            log.error("skipping LISIC scene %s: %s", d.name, exc)
    return done
