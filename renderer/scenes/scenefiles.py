"""Every file a scene XML names, checked before Mitsuba opens any of them (past `noisefeat.safeio`,
a ply naming /dev/zero or a bitmap of a FIFO would exhaust memory or hang a render).

The XML is walked as Mitsuba 3's parser reads it (src/core/parser.cpp, 3.9): ``$name``
substituted, includes followed, ``<path>`` folders added, each ``filename`` resolved where the
plugin will (the top file's folders), paths joined as Mitsuba joins them, never normalised. Each
file must be a regular file within its kind's cap (`safeio.CAPS`) and header bounds
(`image_headers`, `mesh_headers`); a DOCTYPE (expat would apply it, pugixml skips it), text not
read as pugixml reads it (`xml_encoding`), a plugin library in the scene's folders (`plugin_libs`)
and a walk past the MAX_ bounds are refused too, each in one line naming the file and element.
"""
from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from typing import TypeVar
from xml.parsers import expat

from noisefeat.extras import require
from noisefeat.safeio import InputFileError, check_regular, read_input

from .image_headers import check_image
from .mesh_headers import check_grid, check_obj, check_ply, check_serialized
from .plugin_libs import plugin_library_error
from .xml_encoding import declaration_error, pugixml_encoding

T = TypeVar("T")

#: Mitsuba's own include depth bound (ParserConfig.max_include_depth): the top file is depth 0
MAX_DEPTH = 15
#: most XML files one scene may read (its includes counted each time they are included)
MAX_FILES = 4096
#: most bytes of XML Mitsuba may parse for one scene (includes counted each time)
MAX_XML_BYTES = 1 << 30
#: deepest nesting of objects (<scene> is 1): real scenes stay under 8, while Mitsuba's load
#: doubles with each level of twosided BSDFs (40 levels: over 30 s and 1.4 GB)
MAX_NESTING = 16
#: deepest nesting of any XML element (objects, their properties, transforms)
MAX_ELEMENT_DEPTH = 64
#: most <path> folders one scene adds (its includes' counted): each name is looked up in each
MAX_PATHS = 64
#: the kind (safeio.CAPS) of a `filename` property by the element it belongs to
KIND_BY_TAG = {"shape": "mesh", "texture": "texture", "emitter": "environment map", "spectrum": "spectrum",
               "volume": "volume grid", "bsdf": "BSDF data"}
OBJECT_TAGS = frozenset({"scene", "bsdf", "emitter", "film", "integrator", "medium", "phase", "rfilter",
                         "sampler", "sensor", "shape", "texture", "volume", "spectrum"})
#: the header check of the file a plugin reads, by (element, type): the rest are size-capped only
HEADER_CHECKS: dict[tuple[str, str], Callable[..., None]] = {
    ("shape", "ply"): check_ply, ("shape", "ellipsoids"): check_ply, ("shape", "ellipsoidsmesh"): check_ply,
    ("shape", "obj"): check_obj, ("shape", "serialized"): check_serialized, ("shape", "sdfgrid"): check_grid,
    ("volume", "gridvolume"): check_grid, ("texture", "bitmap"): check_image, ("emitter", "envmap"): check_image,
}


class _Walk:
    """One walk over a scene and its includes: parameters, search folders, files read."""

    def __init__(self, defines: Mapping[str, str] | None, search: Sequence[str | os.PathLike], own: str | None):
        self.params: dict[str, str] = {str(k): str(v) for k, v in (defines or {}).items()}
        self.search = [os.fspath(s) for s in search]
        self.own = own                       # Mitsuba's folder: plugin libraries there are its own
        self.top_resolver: list[str] = []    # the folders plugins' files resolve in (the top file's)
        #: (name, kind, element, where, tag, type, the element's properties read so far)
        self.plugin_files: list[tuple[str, str, str, str, str, str, dict[str, str]]] = []
        self.types: dict[str, str] = {}      # plugin type -> where it is first named
        self.files_read = self.xml_bytes = self.paths = 0
        #: includes walked: (path, kind, resolver, parameters, chain, nesting) -> (files, bytes) they read
        self.walked: dict[tuple[object, ...], tuple[int, int]] = {}

    def substitute(self, value: str) -> str | None:
        """`value` with its $names replaced as parser.cpp's substitute_parameters replaces them;
        None if one is left that Mitsuba would refuse."""
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

    def _count(self, path: str, files: int, size: int) -> None:
        """Add one visit's files and XML bytes; refuse past `MAX_FILES` or `MAX_XML_BYTES`."""
        self.files_read += files
        self.xml_bytes += size
        if self.files_read > MAX_FILES:
            raise ValueError(f"{path}: the scene reads more than {MAX_FILES} XML files (its includes); refused")
        if self.xml_bytes > MAX_XML_BYTES:
            raise ValueError(f"{path}: the scene's XML (its includes counted each time) is over {MAX_XML_BYTES} "
                             "bytes; refused")

    def read(self, path: str, kind: str, chain: tuple[str, ...], resolver: list[str], named_by: str,
             nesting: int = 0) -> None:
        """Read and walk one XML file (`chain`: the real paths of the files including it;
        `nesting`: the object level it is included at)."""
        if len(chain) >= MAX_DEPTH:
            raise ValueError(f"{path}: includes nest deeper than Mitsuba's {MAX_DEPTH} levels{named_by}; refused")
        real = os.path.realpath(path)
        if real in chain:
            raise ValueError(f"{path}: includes itself (an include loop){named_by}; refused")
        key = (path, kind, tuple(resolver), len(self.params), chain, nesting)   # parameters only grow
        if key in self.walked:          # walked in this very state: nothing new, its cost counted again
            self._count(path, *self.walked[key])
            return
        before = (self.files_read, self.xml_bytes)
        data = _checked(lambda: read_input(path, kind), named_by)
        self._count(path, 1, len(data))
        encoding = pugixml_encoding(data)
        if encoding is None:
            raise ValueError(f"{path}: is UTF-16 or UTF-32 text, which this check does not read{named_by}; "
                             "save it as UTF-8; refused")
        # the folder as Mitsuba takes it (parent_path: never normalised, the OS resolves L/..)
        folder = os.path.dirname(path if os.path.isabs(path) else os.path.join(os.getcwd(), path))
        resolver = list(resolver)        # <path> in this file: this file's later includes (and nested ones)
        stack: list[tuple[str, str, int, dict[str, str]]] = []        # (tag, type, object level, properties)
        parser = expat.ParserCreate(encoding)      # pugixml's encoding, whatever the file declares
        parser.SetParamEntityParsing(expat.XML_PARAM_ENTITY_PARSING_NEVER)

        def where() -> str:
            return f"{path}, line {parser.CurrentLineNumber}"

        def declaration(_version: str, declared: str | None, _standalone: int) -> None:
            if why := declaration_error(declared, encoding, data):
                raise ValueError(f"{path}: {why}{named_by}; refused")

        def doctype(*_: object) -> None:
            raise ValueError(f"{where()}: has a DOCTYPE (a DTD: entity and attribute declarations), which "
                             f"Mitsuba does not read{named_by}; refused")

        def start(tag: str, attrs: dict[str, str]) -> None:
            values = {k: self.substitute(v) for k, v in attrs.items()}
            parent = stack[-1][2] if stack else nesting
            is_object = tag in OBJECT_TAGS and (tag != "spectrum" or "type" in values) and (
                bool(stack) or not chain or tag != "scene")          # an included <scene> merges into its parent
            stack.append((tag, values.get("type") or "", parent + is_object, {}))
            if len(stack) > MAX_ELEMENT_DEPTH or parent + is_object > MAX_NESTING:
                what = ("objects", MAX_NESTING) if parent + is_object > MAX_NESTING else ("elements", MAX_ELEMENT_DEPTH)
                raise ValueError(f"{where()}: {what[0]} nest deeper than {what[1]} levels{named_by}; refused")
            if is_object and tag != "scene" and values.get("type") is not None:
                self.types.setdefault(values["type"], f'<{tag} type="{values["type"][:64]}"> in {where()}')
            if tag == "default" and values.get("name") and values.get("value") is not None:
                self.params.setdefault(values["name"], values["value"])       # -D and earlier ones win
            elif tag == "path" and values.get("value") and len(stack) == 2:
                self.paths += 1
                if self.paths > MAX_PATHS:
                    raise ValueError(f"{where()}: the scene adds more than {MAX_PATHS} <path> folders; refused")
                self._path(values["value"], folder, resolver)
            elif tag == "include" and values.get("filename") is not None:
                named = f' (named by <include> in {where()})'
                inc_resolver = [folder, *resolver]
                self.read(_found(values["filename"], inc_resolver, "included scene", named), "included scene",
                          (*chain, real), inc_resolver, named, parent)
            elif tag == "spectrum" and not values.get("type") and values.get("filename"):
                named = f" (named by <spectrum> in {where()})"
                spectrum = _found(values["filename"], resolver, "spectrum", named)   # read while parsing
                _checked(lambda: check_regular(spectrum, "spectrum"), named)
            elif tag in ("string", "integer") and values.get("name") in ("filename", "shape_index") \
                    and values.get("value") is not None:
                owner = next(((t, ty, p) for t, ty, lv, p in reversed(stack[:-1]) if t in OBJECT_TAGS),
                             ("scene", "", {}))
                owner[2].setdefault(values["name"], values["value"])      # what a header check reads
                if tag == "string" and values["name"] == "filename":
                    element = f'<{owner[0]} type="{owner[1]}">' if owner[1] else f"<{owner[0]}>"
                    self.plugin_files.append((values["value"], KIND_BY_TAG.get(owner[0], "file"), element, where(),
                                              owner[0], owner[1], owner[2]))

        parser.StartElementHandler = start
        parser.EndElementHandler = lambda _tag: stack.pop()
        parser.XmlDeclHandler = declaration
        parser.StartDoctypeDeclHandler = doctype
        try:
            parser.Parse(data, True)
        except expat.ExpatError as exc:
            raise ValueError(f"{path}: not well-formed XML ({expat.ErrorString(exc.code)}, line {exc.lineno})"
                             f"{named_by}") from None
        if not chain:       # the top file's resolver (its <path>s included) loads every plugin
            self.top_resolver = resolver
        self.walked[key] = (self.files_read - before[0], self.xml_bytes - before[1])

    def _path(self, value: str, folder: str, resolver: list[str]) -> None:
        """A <path> folder, resolved as parser.cpp does (the file's folder, then the resolver)."""
        p = value
        if not os.path.isabs(p):
            p = os.path.join(folder, value)
            if not os.path.exists(p):
                p = _resolve(value, resolver)
        resolver.insert(0, p)

    def check_plugin_files(self) -> None:
        """Each plugin's `filename`, resolved as when the plugin loads: a regular file within its
        kind's cap and its header check's bounds."""
        seen: set[tuple[object, ...]] = set()
        for name, kind, element, where, tag, type_, props in self.plugin_files:
            named = f" (named by {element} in {where})"
            path = _found(name, self.top_resolver, kind, named)
            check = HEADER_CHECKS.get((tag, type_))
            args = (_integer(props.get("shape_index")),) if check is check_serialized else ()
            if (path, kind, check, args) not in seen:
                seen.add((path, kind, check, args))
                _checked(lambda: check_regular(path, kind), named)
                if check is not None:
                    _checked(lambda: check(path, kind, *args), named)

    def check_plugin_types(self) -> None:
        """No plugin type whose library Mitsuba would look up in the scene's folders."""
        for type_, where in self.types.items():
            if why := plugin_library_error(type_, self.top_resolver, self.own):
                raise ValueError(f"{why} (named by {where}); refused")


def _integer(value: str | None) -> int:
    """An <integer> property as Mitsuba reads it; 0 if absent (or unreadable: Mitsuba refuses it)."""
    try:
        return int((value or "0").strip())
    except ValueError:
        return 0


def _resolve(name: str, resolver: Sequence[str]) -> str:
    """Mitsuba's FileResolver.resolve: the first folder a relative name exists in, else the name."""
    if not os.path.isabs(name):
        for base in resolver:
            candidate = os.path.join(base, name)
            if os.path.exists(candidate):
                return candidate
    return name


def _found(name: str, resolver: Sequence[str], kind: str, named_by: str) -> str:
    """`name` resolved; a relative name found nowhere: FileNotFoundError naming the folders."""
    path = _resolve(name, resolver)
    if not os.path.isabs(name) and not os.path.lexists(path):
        raise FileNotFoundError(f"{name}: {kind} not found in {', '.join(dict.fromkeys(resolver))}{named_by}")
    return path


def _checked(call: Callable[[], T], named_by: str) -> T:
    """`call()`, its one-line refusal told which element named the file."""
    try:
        return call()
    except (FileNotFoundError, InputFileError) as exc:
        raise type(exc)(f"{exc}{named_by}") from None


def check_scene_files(path: str | os.PathLike[str], defines: Mapping[str, str] | None = None,
                      search: Sequence[str | os.PathLike] | None = None, own: str | None = None) -> None:
    """Refuse, in one line, the scene XML Mitsuba is given as `path` if a file it names (or the
    walk) breaks a rule of this module. `defines`: its -D parameters; `search`: Mitsuba's search
    folders (None: the current folder); `own`: Mitsuba's folder, whose plugin libraries are its
    own (None: none is)."""
    path = os.fspath(path)
    path = path if os.path.isabs(path) else os.path.join(os.getcwd(), path)
    walk = _Walk(defines, [os.getcwd()] if search is None else search, own)
    walk.read(path, "scene", (), [os.path.dirname(path), *walk.search], "")
    walk.check_plugin_types()
    walk.check_plugin_files()


def mitsuba_search_paths() -> list[str]:
    """The folders Mitsuba resolves a relative file name in (its file resolver's, in order)."""
    fr = require("mitsuba").file_resolver()
    return [str(fr[i]) for i in range(len(fr))]
