"""Dataset format v1 (DESIGN "Dataset format v1"): one directory per scene, its names and layout.

```
<scene>/meta.json                 # written last: its presence means "complete"
<scene>/meta.partial.json         # only while a build is in progress: the plan
<scene>/levels/000032.exr ...     # cumulative-mean linear RGB, named by spp (%06d)
<scene>/reference.exr             # high-spp linear RGB
<scene>/quick.exr                 # the quick noise-free image (absent if meta "quick" == "none")
<scene>/quick_direct.exr          # optional, beyond format v1: direct-lighting quick image
```

Why a module of its own: the reader (`stack`), the writer (`stack_write`), the meta.json
rules (`stack_validate`) and the dataset check (`check`) all name these files; they agree
by importing them from here.

Extra quick images (`EXTRA_QUICK`, only for the quick-image ablation) are not part of
format v1: readers that do not know them ignore them, a stack is complete without them,
and adding one to a complete stack leaves it complete (`StackWriter.write_extra_quick`).

Resume rule (used by `StackWriter`, hence by `dataset build` and `import-lisic`):

* a directory with `meta.json` is a complete stack;
* a directory with `meta.partial.json` (and no `meta.json`) is a build in progress. The
  partial file holds the *plan*: every meta.json key except `labeler` and `thresholds`.
  Every image file in it is complete (all writes are atomic), so a writer reopened with an
  identical plan keeps them and only writes what is missing; a different plan is refused
  (ValueError) rather than mixing two builds in one directory;
* writing into a complete stack first removes its `meta.json` (back to "in progress").

`quick == "none"` (e.g. LISIC imports, which have no noise-free image): no quick.exr is
written and `Stack.quick()` returns a flat mid-grey image (`MID_GREY_LINEAR`, sRGB 0.5) of
the right size, so that `features(quick) - features(current)` stays defined and carries no
information beyond `features(current)`.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

FORMAT = "noisestop-stack"
VERSION = 1
META = "meta.json"
PARTIAL = "meta.partial.json"
LEVELS_DIR = "levels"
REFERENCE = "reference.exr"
QUICK = "quick.exr"
#: optional extra quick images by kind (see module doc)
EXTRA_QUICK = {"direct": "quick_direct.exr"}
QUICK_NONE = "none"
#: linear value whose sRGB encoding is 0.5: the stand-in quick image when there is none
MID_GREY_LINEAR = 0.21404114

REQUIRED_KEYS = ("format", "version", "scene", "width", "height", "grid", "block", "spp",
                 "reference_spp", "quick", "renderer")
OPTIONAL_KEYS = ("labeler", "thresholds", "tile", "tile_thresholds")
KNOWN_KEYS = REQUIRED_KEYS + OPTIONAL_KEYS


def level_name(spp: int) -> str:
    """File name of the level with `spp` samples per pixel, relative to the stack dir."""
    return f"{LEVELS_DIR}/{int(spp):06d}.exr"


def block_shape(height: int, width: int, grid: Sequence[int] = (4, 4)) -> tuple[int, int]:
    """(bh, bw) of a `grid` cut; the image must divide exactly (as noisefeat.split_blocks)."""
    gh, gw = (int(g) for g in grid)
    if gh < 1 or gw < 1:
        raise ValueError(f"grid must be two positive integers, got {list(grid)}")
    if height % gh or width % gw:
        raise ValueError(f"a {width}x{height} image cannot be cut into a {gh}x{gw} grid "
                         f"of equal blocks (height % {gh} = {height % gh}, width % {gw} = "
                         f"{width % gw})")
    return height // gh, width // gw


def file_kind(path: Path) -> str:
    """The `noisefeat.safeio` kind (size cap) a stack's file is opened as."""
    return "meta.json" if path.name == META else "EXR" if path.suffix == ".exr" else "file"
