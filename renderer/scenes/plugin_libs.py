"""No code is loaded from a scene's folders: Mitsuba's plugin libraries come from Mitsuba.

Mitsuba loads a plugin library as ``plugins/<type>.so`` through the file resolver (src/core/
plugin.cpp, 3.9), which holds the scene's folders first while it loads: a ``plugins/diffuse.so``
next to a scene would run in our process. So `preload` loads every library of Mitsuba's own
folder before any scene (the manager caches them by name), and `plugin_library_error` refuses
a type that is not a plain name or whose library a folder before Mitsuba's holds.
"""
from __future__ import annotations

import os
import re
import sys
import threading
from collections.abc import Sequence

from noisefeat.extras import require

#: a type Mitsuba may look a library up for: no dot (its extension would be replaced), no slash
PLAIN = re.compile(r"[A-Za-z0-9_\-]+")
_SUFFIX = {"win32": ".dll", "darwin": ".dylib"}.get(sys.platform, ".so")
_done = False
_lock = threading.Lock()


def mitsuba_folder() -> str:
    """Mitsuba's own folder (its library's, where its ``plugins`` folder is)."""
    return os.path.dirname(os.path.abspath(require("mitsuba").__file__))


def preload() -> int:
    """Load every plugin library of Mitsuba's own folder, resolved there alone; how many (0
    after the first call)."""
    global _done
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
    """Why a scene naming plugin `type_` is refused, or None: the name is not plain, or one of
    `folders` (the resolver's, in order) before `own` (Mitsuba's) holds its library."""
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
