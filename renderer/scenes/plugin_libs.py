"""No code is loaded from a scene's folders: Mitsuba's plugin libraries come from Mitsuba.

Why: Mitsuba's PluginManager loads the library of a plugin it has not loaded yet as
``plugins/<type>.so`` through the file resolver (src/core/plugin.cpp, 3.9), and while a
scene file loads, that resolver holds the scene's ``<path>`` folders and its own folder
first, then the current folder (as it was when Mitsuba was imported), then Mitsuba's own:
a ``plugins/diffuse.so`` built by whoever wrote the scene ran its code in our process.
Two closes, both needed:

* `preload`: every library in Mitsuba's own ``plugins`` folder is loaded once per process,
  resolved in Mitsuba's folder alone, before any scene loads (the manager caches libraries
  by name, so the built-in names, the ones Mitsuba itself creates behind a scene's back
  included, never reach the resolver again);
* `plugin_library_error`: a ``type`` the walker reads in a scene must be a plain name (a
  dot or a slash would change the library's file name), and no search folder before
  Mitsuba's own may hold ``plugins/<type>.so`` (any name: one that is not built in would
  still be looked up there).
"""
from __future__ import annotations

import os
import re
import sys
import threading
from collections.abc import Sequence

#: a type Mitsuba may look a library up for: no dot (its extension would be replaced), no slash
PLAIN = re.compile(r"[A-Za-z0-9_\-]+")
_SUFFIX = {"win32": ".dll", "darwin": ".dylib"}.get(sys.platform, ".so")
_done = False
_lock = threading.Lock()


def mitsuba_folder() -> str:
    """Mitsuba's own folder (its library's, where its ``plugins`` folder is)."""
    from noisefeat.extras import require

    return os.path.dirname(os.path.abspath(require("mitsuba").__file__))


def preload() -> int:
    """Load every plugin library of Mitsuba's own folder (once per process; later calls
    return 0), resolved there alone; the number loaded."""
    global _done
    from noisefeat.extras import require

    with _lock:
        if _done:
            return 0
        mi = require("mitsuba")
        folder = mitsuba_folder()
        names = sorted(n[:-len(_SUFFIX)] for n in os.listdir(os.path.join(folder, "plugins")) if n.endswith(_SUFFIX))
        own = mi.FileResolver()
        own.clear()
        own.append(folder)
        previous = mi.file_resolver()
        mi.set_file_resolver(own)
        try:
            manager = mi.PluginManager.instance()
            for name in names:
                manager.plugin_type(name)          # loads the library (and caches it by name)
        finally:
            mi.set_file_resolver(previous)
        _done = True
        return len(names)


def plugin_library_error(type_: str, folders: Sequence[str], own: str | None) -> str | None:
    """Why a scene naming plugin `type_` is refused, or None: Mitsuba would look its library
    up in `folders` (the resolver's, in order) and one before `own` (Mitsuba's folder) holds
    ``plugins/<type_>.so``, or the name is not plain."""
    if not PLAIN.fullmatch(type_):
        return (f'plugin type "{type_[:64]}" is not a plain name (letters, digits, _ and -): Mitsuba would '
                "look for a library by that file name")
    for folder in folders:
        if own is not None and os.path.realpath(folder) == os.path.realpath(own):
            return None
        library = os.path.join(folder, "plugins", type_ + _SUFFIX)
        if os.path.lexists(library):
            return f"{library}: a plugin library Mitsuba would load and run (only its own are loaded)"
    return None
