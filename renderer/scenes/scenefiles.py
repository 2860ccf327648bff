"""Every file a scene XML names, checked before Mitsuba opens any of them.

Why: Mitsuba opens what a scene names itself, past `noisefeat.safeio`: a ``<shape
type="ply">`` naming /dev/zero grew a render to 7.6 GB, an ``<include>`` or a bitmap of a
FIFO hung it (issue 51). So the XML is walked first, as Mitsuba 3's parser reads it
(src/core/parser.cpp, 3.9), and each file it names must be a regular file within its kind's
cap (`safeio.CAPS`: mesh, texture, environment map, included scene, ...); the first that is
not is refused in one line naming the file and the element naming it.

What the walk follows, as Mitsuba does:

* ``$name`` in any attribute is replaced by the -D value or the ``<default>`` seen so far
  (longest name first, ``\\$`` escaped); an attribute left with an unknown ``$name`` is not
  checked: Mitsuba refuses it while parsing, before it opens anything;
* ``<include filename>`` is resolved against the including file's folder, then the folders
  the include chain was resolved with, and read (depth below Mitsuba's 15; a file that
  includes itself, directly or not, is refused as a loop; at most `MAX_FILES` files read);
* ``<path value>`` at a file's top adds a search folder (for the includes after it, and,
  in the top file, for every plugin's file);
* a ``filename`` property (``<string name="filename">``: ply, obj and serialized meshes,
  bitmaps, environment maps, volume grids, measured BSDFs) is resolved as Mitsuba resolves it
  when the plugin loads: against the top file's ``<path>`` folders, its own folder, then
  Mitsuba's search paths (the current folder first), **not** an include's folder;
  ``<spectrum filename>`` likewise.

A name found nowhere is checked where Mitsuba would look last (relative to the current
folder): a missing file is a one-line FileNotFoundError here, not Mitsuba's later error.
Entity declarations (a DTD) are refused: Mitsuba's pugixml never expands them, and expanding
them is how an XML file grows without bound.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from typing import TypeVar
from xml.parsers import expat

from noisefeat.safeio import InputFileError, check_regular, read_input

T = TypeVar("T")

#: Mitsuba's own include depth bound (ParserConfig.max_include_depth): the top file is depth 0
MAX_DEPTH = 15
#: most XML files one scene may read (its includes counted each time they are included)
MAX_FILES = 4096
#: the kind (safeio.CAPS) of a `filename` property by the element it belongs to
KIND_BY_TAG = {"shape": "mesh", "texture": "texture", "emitter": "environment map", "spectrum": "spectrum",
               "volume": "volume grid", "bsdf": "BSDF data"}
OBJECT_TAGS = frozenset({"scene", "bsdf", "emitter", "film", "integrator", "medium", "phase", "rfilter",
                         "sampler", "sensor", "shape", "texture", "volume", "spectrum"})


class _Walk:
    """One walk over a scene and its includes: parameters, search folders, files read."""

    def __init__(self, defines: Mapping[str, str] | None, search: Sequence[str | os.PathLike]):
        self.params: dict[str, str] = {str(k): str(v) for k, v in (defines or {}).items()}
        self.search = [os.fspath(s) for s in search]
        self.top_resolver: list[str] = []    # the folders plugins' files resolve in (the top file's)
        self.plugin_files: list[tuple[str, str, str, str]] = []    # (name, kind, element, where)
        self.files_read = 0

    # -- substitution, as parser.cpp's substitute_parameters
    def substitute(self, value: str) -> str | None:
        """`value` with its $names replaced; None if one is left that Mitsuba would refuse."""
        if "$" not in value:
            return value
        for key in sorted(self.params, key=len, reverse=True):
            token, pos = "$" + key, 0
            while (pos := value.find(token, pos)) != -1:
                if pos > 0 and value[pos - 1] == "\\":
                    pos += len(token)
                else:
                    value = value[:pos] + self.params[key] + value[pos + len(token):]
                    pos += len(self.params[key])
        pos = 0
        while (pos := value.find("$", pos)) != -1:
            if pos == 0 or value[pos - 1] != "\\":
                return None
            pos += 1
        return value.replace("\\$", "$")

    # -- one XML file
    def read(self, path: str, kind: str, chain: tuple[str, ...], resolver: list[str], named_by: str) -> None:
        """Read and walk one XML file (`chain`: the real paths of the files including it)."""
        if len(chain) >= MAX_DEPTH:
            raise ValueError(f"{path}: includes nest deeper than Mitsuba's {MAX_DEPTH} levels{named_by}; refused")
        real = os.path.realpath(path)
        if real in chain:
            raise ValueError(f"{path}: includes itself (an include loop){named_by}; refused")
        self.files_read += 1
        if self.files_read > MAX_FILES:
            raise ValueError(f"{path}: the scene reads more than {MAX_FILES} XML files (its includes); refused")
        data = _checked(lambda: read_input(path, kind), named_by)
        folder = os.path.dirname(os.path.abspath(path))
        resolver = list(resolver)        # <path> in this file: this file's later includes (and nested ones)
        stack: list[tuple[str, str]] = []
        parser = expat.ParserCreate()
        parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)

        def where() -> str:
            return f"{path}, line {parser.CurrentLineNumber}"

        def entity(*_: object) -> None:
            raise ValueError(f"{where()}: declares an XML entity (a DTD), which Mitsuba does not read; refused")

        def start(tag: str, attrs: dict[str, str]) -> None:
            values = {k: self.substitute(v) for k, v in attrs.items()}
            stack.append((tag, values.get("type") or ""))
            if tag == "default" and values.get("name") and values.get("value") is not None:
                self.params.setdefault(values["name"], values["value"])       # -D and earlier ones win
            elif tag == "path" and values.get("value") and len(stack) == 2:
                self._path(values["value"], folder, resolver, chain)
            elif tag == "include" and values.get("filename") is not None:
                named = f' (named by <include> in {where()})'
                inc_resolver = [folder, *resolver]
                self.read(_found(values["filename"], inc_resolver, "included scene", named), "included scene",
                          (*chain, real), inc_resolver, named)
            elif tag == "spectrum" and not values.get("type") and values.get("filename"):
                named = f" (named by <spectrum> in {where()})"
                spectrum = _found(values["filename"], resolver, "spectrum", named)   # read while parsing
                _checked(lambda: check_regular(spectrum, "spectrum"), named)
            elif tag == "string" and values.get("name") == "filename" and values.get("value") is not None:
                owner = next(((t, ty) for t, ty in reversed(stack[:-1]) if t in OBJECT_TAGS), ("scene", ""))
                element = f'<{owner[0]} type="{owner[1]}">' if owner[1] else f"<{owner[0]}>"
                self.plugin_files.append((values["value"], KIND_BY_TAG.get(owner[0], "file"), element, where()))

        parser.StartElementHandler = start
        parser.EndElementHandler = lambda _tag: stack.pop()
        parser.EntityDeclHandler = entity
        try:
            parser.Parse(data, True)
        except expat.ExpatError as exc:
            raise ValueError(f"{path}: not well-formed XML ({expat.ErrorString(exc.code)}, line {exc.lineno})"
                             f"{named_by}") from None
        if not chain:       # the top file's resolver (its <path>s included) loads every plugin
            self.top_resolver = resolver

    def _path(self, value: str, folder: str, resolver: list[str], chain: tuple[str, ...]) -> None:
        """A <path> folder, resolved as parser.cpp does (the file's folder, then the resolver)."""
        p = value
        if not os.path.isabs(p):
            p = os.path.join(folder, value)
            if not os.path.exists(p):
                p = _resolve(value, resolver)
        resolver.insert(0, p)

    def check_plugin_files(self) -> None:
        """Each plugin's `filename`, resolved as it will be when the plugin loads."""
        seen: set[tuple[str, str]] = set()
        for name, kind, element, where in self.plugin_files:
            named = f" (named by {element} in {where})"
            path = _found(name, self.top_resolver, kind, named)
            if (path, kind) not in seen:
                seen.add((path, kind))
                _checked(lambda: check_regular(path, kind), named)


def _resolve(name: str, resolver: Sequence[str]) -> str:
    """Mitsuba's FileResolver.resolve: the first folder in which a relative name exists,
    else the name as given (relative to the current folder)."""
    if not os.path.isabs(name):
        for base in resolver:
            candidate = os.path.join(base, name)
            if os.path.exists(candidate):
                return candidate
    return name


def _found(name: str, resolver: Sequence[str], kind: str, named_by: str) -> str:
    """`name` resolved (`_resolve`); a relative name found nowhere: FileNotFoundError naming
    the folders searched."""
    path = _resolve(name, resolver)
    if not os.path.isabs(name) and not os.path.lexists(path):
        raise FileNotFoundError(f"{name}: {kind} not found in {', '.join(dict.fromkeys(resolver))}{named_by}")
    return path


def _checked(call: Callable[[], T], named_by: str) -> T:
    """`call()`, its one-line refusal told which element named the file."""
    try:
        return call()
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{exc}{named_by}") from None
    except InputFileError as exc:
        raise InputFileError(f"{exc}{named_by}") from None


def check_scene_files(path: str | os.PathLike[str], defines: Mapping[str, str] | None = None,
                      search: Sequence[str | os.PathLike] | None = None) -> None:
    """Refuse, in one line, a scene XML at `path` (absolute) that names a file which is not
    a regular file within its kind's cap, or whose includes loop or nest too deep.

    `defines`: the -D parameters it is loaded with; `search`: Mitsuba's search folders
    (``mi.file_resolver()``; None: the current folder)."""
    path = os.path.abspath(os.fspath(path))
    walk = _Walk(defines, [os.getcwd()] if search is None else search)
    walk.read(path, "scene", (), [os.path.dirname(path), *walk.search], "")
    walk.check_plugin_files()


def mitsuba_search_paths() -> list[str]:
    """The folders Mitsuba resolves a relative file name in (its file resolver's, in order)."""
    from noisefeat.extras import require

    fr = require("mitsuba").file_resolver()
    return [str(fr[i]) for i in range(len(fr))]

